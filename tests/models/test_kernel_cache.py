"""numba's on-disk cache is used only where the user names its folder (``NUMBA_CACHE_DIR``): without it nothing is
written beside the sources; with it a second process loads the compiled kernels instead of compiling them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PROBE = """
import numpy as np
from gsavatar.models import kernels
from gsavatar.utils.compiled import CACHE
out = np.zeros((2, 3, 4), np.float32)
kernels._forward(np.ones((2, 3, 5), np.float32), np.ones((3, 5, 4), np.float32), out)
assert float(out[0, 0, 0]) == 5.0
print(CACHE, type(kernels._forward._cache).__name__, kernels._forward.stats.cache_hits.total())
"""


def probe(env_extra: dict) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(PYTHONPATH=str(REPO / "src"), OMP_NUM_THREADS="1", **env_extra)
    r = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout.split()


def test_no_cache_folder_no_cache():
    assert probe({})[:2] == ["False", "NullCache"]


def test_a_named_cache_folder_is_filled_then_read(tmp_path):
    folder = tmp_path / "numba"
    first = probe({"NUMBA_CACHE_DIR": str(folder)})
    assert first == ["True", "FunctionCache", "0"]
    assert any(p.suffix == ".nbi" for p in folder.rglob("*"))  # the index numba writes beside each kernel
    second = probe({"NUMBA_CACHE_DIR": str(folder)})
    assert second[:2] == ["True", "FunctionCache"] and int(second[2]) >= 1  # loaded, not compiled
