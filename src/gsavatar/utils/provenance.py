"""Which code produced a result: the git commit of the checkout the package runs from.

The results table (benchmarks/results_table.py) records it per run, so a row can be checked against the code
it claims to describe. Outside a git checkout (an installed wheel) there is no commit: ``None``."""

from __future__ import annotations

import subprocess
from functools import lru_cache
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[3]  # src/gsavatar/utils/provenance.py -> the checkout


@lru_cache(maxsize=1)
def code_version() -> dict:
    """``{"commit": sha or None, "dirty": bool or None}`` of the checkout holding this package; ``dirty`` is true
    when tracked files under ``src/`` differ from the commit (the run used uncommitted code)."""

    def git(*args: str) -> str | None:
        try:
            got = subprocess.run(["git", "-C", str(_ROOT), *args], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.SubprocessError):
            return None
        return got.stdout.strip() if got.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None:
        return {"commit": None, "dirty": None}
    status = git("status", "--porcelain", "--untracked-files=no", "--", "src")
    return {"commit": commit, "dirty": None if status is None else bool(status)}
