"""numba, shared set-up for the compiled CPU kernels (render, models, prep, drive).

numba is a declared dependency; every compiled kernel keeps a torch/numpy path (its test oracle) that
runs when it is missing. Threads follow torch's (``OMP_NUM_THREADS`` / ``torch.set_num_threads``) so a
one-thread run stays on one core, and the threading layer prefers OpenMP: numba's default order probes
TBB first, which warns on the older TBB that Debian ships.
"""

from __future__ import annotations

import torch

try:
    import numba
except ImportError:  # pragma: no cover - exercised only where numba is not installed
    numba = None

if numba is not None:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


def available() -> bool:
    """Whether numba can be imported here."""
    return numba is not None


def set_threads() -> int:
    """Cap numba's threads at torch's (and numba's own maximum); returns the number used."""
    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n
