"""Plausible ranges of numbers read from files, shared by every loader that resamples motion.

A number that passes a sign check can still turn a tiny input into unbounded work: a BVH
``Frame Time`` of 1e9 s (or a motion ``fps`` of 1e-7) asked the resampler for ~1e10 output
frames (TiB of memory). Loaders refuse such values with a :class:`SchemaError` naming the file
and field and showing the numbers, before anything is allocated.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gsavatar.utils.errors import SchemaError

MIN_FPS = 1.0
"""Lowest accepted frame rate (frames per second) of a motion: below it consecutive frames are too far
apart to interpolate a body motion (and 1e-7 fps is a unit mistake, not a recording)."""
MAX_FPS = 1000.0
"""Highest accepted frame rate: optical mocap records at 60-480 Hz, high-speed systems at up to ~1000."""
MAX_RESAMPLED_FRAMES = 200_000
"""Most output frames a resampled motion may have: 1.85 h at 30 fps. The driver renders every frame, and
the resampler keeps a few float64 ``[T, pose_dim]`` arrays (160 MB each at T = 200k, 100 parameters)."""


MAX_MOTION_VALUE = 1e4
"""Largest |value| in a driving motion's pose, root rotation and root translation: radians (1600 turns, an
unwrapped spin) and metres (10 km). A finite 1e38 overflowed: rotation maths gave NaN (or "SVD did not
converge") and the float32 conversion inf."""


def check_motion_values(a: np.ndarray, file: str | Path, field: str) -> None:
    """SchemaError(file, field) naming the first value of ``a`` (finite, frames first) beyond +-MAX_MOTION_VALUE."""
    big = np.abs(np.asarray(a, dtype=np.float64)) > MAX_MOTION_VALUE  # float: abs(int64 min) stays negative
    if big.any():
        at = tuple(int(i) for i in np.argwhere(big)[0])
        where = f"frame {at[0]}, column {at[1]}" if len(at) == 2 else f"index {list(at)}"
        raise SchemaError(
            file,
            field,
            f"{int(big.sum())} values beyond +-{MAX_MOTION_VALUE:g} (first at {where}: "
            f"{float(a[at]):g}); radians and metres are expected",
        )


def fps_problem(fps: float) -> str | None:
    """Why ``fps`` is not a plausible frame rate, or None when it is."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float)):
        return f"expected a number of frames per second, got {fps!r}"
    if not (math.isfinite(fps) and MIN_FPS <= fps <= MAX_FPS):
        return f"{fps:g} frames per second is outside the plausible range [{MIN_FPS:g}, {MAX_FPS:g}]"
    return None


def check_fps(fps: float, file: str | Path, field: str) -> float:
    """``fps`` as float; SchemaError(file, field) unless it is in [MIN_FPS, MAX_FPS]."""
    problem = fps_problem(fps)
    if problem is not None:
        raise SchemaError(file, field, problem)
    return float(fps)


def resampled_frame_count(n_in: int, fps_in: float, fps_out: float) -> int:
    """Output frames ``k / fps_out`` within ``[0, (n_in - 1) / fps_in]`` (the resamplers' convention)."""
    return int(math.floor((n_in - 1) * fps_out / fps_in + 1e-6)) + 1


def check_resampled_frames(
    n_in: int, fps_in: float, fps_out: float, file: str | Path, field: str, limit: int = MAX_RESAMPLED_FRAMES
) -> int:
    """Output frame count of resampling ``n_in`` frames from ``fps_in`` to ``fps_out``; SchemaError(file,
    field) with the numbers when it exceeds ``limit``."""
    n_out = resampled_frame_count(n_in, fps_in, fps_out)
    if n_out > limit:
        raise SchemaError(
            file,
            field,
            f"resampling {n_in} frames from {fps_in:g} to {fps_out:g} fps makes {n_out} "
            f"frames, more than the {limit} allowed (drive a part with start/count)",
        )
    return n_out
