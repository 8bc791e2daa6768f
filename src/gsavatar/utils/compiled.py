"""numba, shared set-up for the compiled CPU kernels (render, models, prep, drive).

numba is a declared dependency; every compiled kernel keeps a torch/numpy path (its test oracle) that
runs when it is missing. Threads follow torch's (``OMP_NUM_THREADS`` / ``torch.set_num_threads``) so a
one-thread run stays on one core. The threading layer is numba's own ``workqueue``: its OpenMP layer
shares libgomp with torch and, once started, raised torch's intra-op threads from 1 to numba's count
(measured: a 43,690-element ``mul`` went from 9 us to 1.6 ms on the 2-core box, and a training step
from ~0.6 s to ~3 s); numba's default order probes TBB first, which warns on Debian's older TBB.
``NUMBA_THREADING_LAYER`` in the environment still wins.
"""

from __future__ import annotations

import os

import torch

try:
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is not installed
    numba = None

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
