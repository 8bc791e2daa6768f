"""numba, shared set-up for the compiled CPU kernels (render, models, prep, drive).

numba is a declared dependency; every compiled kernel keeps a torch/numpy path (its test oracle) that
runs when it is missing. Threads follow torch's (``OMP_NUM_THREADS`` / ``torch.set_num_threads``) so a
one-thread run stays on one core. The threading layer is numba's own ``workqueue``: its OpenMP layer
shares libgomp with torch and, once started, raised torch's intra-op threads from 1 to numba's count
(measured: a 43,690-element ``mul`` went from 9 us to 1.6 ms on the 2-core box, and a training step
from ~0.6 s to ~3 s); numba's default order probes TBB first, which warns on Debian's older TBB.
``NUMBA_THREADING_LAYER`` in the environment still wins.

Compiling the kernels costs every new process 15-20 s on the 2-core box (measured 2026-12-07: a one-step
``avatar-train avatar`` run spent 35 of its 42 profiled seconds in numba's compiler). numba's on-disk cache would
write beside the installed sources, outside any folder the user named, so it is used only when the user names one:
``NUMBA_CACHE_DIR`` set and non-empty turns ``cache=True`` on (:data:`CACHE`). ``scripts/test.sh`` and
``scripts/demo.sh`` set it to ``.cache/numba`` in the checkout, beside the anny cache. numba recompiles a cached kernel
when its own source file changes (timestamp and size), not when a file it calls into does: keep every compiled kernel
calling only compiled functions of its own file (true of all of them today), or clear the folder.
"""

from __future__ import annotations

import os

import torch

try:
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is not installed
    numba = None

CACHE = bool(os.environ.get("NUMBA_CACHE_DIR"))
"""Whether the kernels use numba's on-disk cache: only when ``NUMBA_CACHE_DIR`` names its folder."""

if numba is not None and "NUMBA_THREADING_LAYER" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["workqueue", "omp", "tbb"]


def available() -> bool:
    """Whether numba can be imported here."""
    return numba is not None


def set_threads() -> int:
    """Cap numba's threads at torch's (and numba's own maximum); returns the number used."""
    torch_threads = torch.get_num_threads()
    n = max(1, min(torch_threads, numba.config.NUMBA_NUM_THREADS))
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)
    if torch.get_num_threads() != torch_threads:  # a layer sharing torch's OpenMP runtime must not change it
        torch.set_num_threads(torch_threads)
    return n
