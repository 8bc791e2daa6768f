#!/usr/bin/env bash
# Set up (idempotent) and run the test suite (slow cases are opt-in: pass -m slow).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export ANNY_CACHE_DIR=${ANNY_CACHE_DIR:-$PWD/.cache/anny}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-$PWD/.cache/numba}  # compiled kernels, reused by every process (utils/compiled.py)
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
# the tree is formatted and linted by ruff (pyproject.toml [tool.ruff]) before any test runs
.venv/bin/ruff format --check --quiet src tests benchmarks scripts
.venv/bin/ruff check --quiet src tests benchmarks scripts
exec .venv/bin/python -m pytest -q "$@"
