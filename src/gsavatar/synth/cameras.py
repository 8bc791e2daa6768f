"""Synthetic camera domes: full-body, upper-body and lower-body views on rings.

As in the paper's captures, the cameras are split evenly between three kinds:

- ``full``: two rings (hip and above-head height) aimed at the body centre, framing
  the whole body and its motion;
- ``upper``: rings at chest and above-head height aimed at the chest, framing the
  torso, arms and head (hands may leave the frame at full reach);
- ``lower``: rings at knee and hip height aimed at the knees, framing hips to feet.

Cameras are OpenCV pinholes, world-to-camera (``x_cam = R x_world + T``, +z forward,
+y down), built with :func:`gsavatar.geometry.camera.look_at`. Azimuth 0 is the
front of the body (+Z); each kind's first camera is frontal. With ``distortion`` about
half the cameras get a small radial-tangential distortion (|k1| <= 0.05).

:func:`special_cameras` adds the stress-test views of the ``hard`` preset: a top-down
grazing view, a floor-level view looking up, and a camera pointed away from the body.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from gsavatar.data_schema.capture import Camera
from gsavatar.geometry.camera import look_at

CameraKind = Literal["full", "upper", "lower"]
SpecialKind = Literal["top", "floor", "away"]

# Per kind: camera heights (fractions of body height, cycled), vertical band to frame
# (fractions of body height; ``None`` = the motion's lowest/highest point) and the
# horizontal half extent to frame as a fraction of ``reach``.
_LAYOUT: dict[str, tuple[tuple[float, ...], tuple[float | None, float | None], float]] = {
    "full": ((0.55, 1.15, 0.85), (None, None), 1.0),
    "upper": ((0.95, 1.25), (0.45, None), 0.62),
    "lower": ((0.30, 0.65), (None, 0.58), 0.62),
}


def dome_kinds(num_cams: int) -> list[str]:
    """Kind of each camera of an evenly split dome (full gets the remainder first)."""
    if num_cams < 1:
        raise ValueError(f"num_cams must be >= 1, got {num_cams}")
    n_full = -(-num_cams // 3)
    n_upper = -(-(num_cams - n_full) // 2)
    return ["full"] * n_full + ["upper"] * n_upper + ["lower"] * (num_cams - n_full - n_upper)


def camera_kind(name: str) -> str:
    """Kind encoded in a dome camera name (``full03`` -> ``full``)."""
    return name.rstrip("0123456789")


def _intrinsics(
    width: int, height: int, dist_to_target: float, half_v: float, half_h: float, jitter: np.ndarray
) -> np.ndarray:
    f = min(height / 2 * dist_to_target / half_v, width / 2 * dist_to_target / half_h)
    return np.array(
        [[f, 0.0, width / 2 + jitter[0] * width], [0.0, f, height / 2 + jitter[1] * height], [0.0, 0.0, 1.0]]
    )


def make_dome(
    num_cams: int,
    width: int,
    height: int,
    body_height: float = 1.7,
    seed: int = 0,
    distortion: bool = False,
    *,
    center: Sequence[float] = (0.0, 0.0),
    radius: float = 3.2,
    reach: float = 0.8,
    y_range: Sequence[float] | None = None,
    margin: float = 1.08,
    max_k1: float = 0.05,
) -> dict[str, Camera]:
    """An evenly split full/upper/lower-body dome around a body standing at ``center``.

    num_cams: total number of cameras (split with :func:`dome_kinds`).
    width, height: image size, pixels.
    body_height: metres; heights and framing scale with it.
    center: (x, z) of the body (e.g. the mean root position of the motion), metres.
    radius: horizontal distance of the cameras from ``center``, metres.
    reach: largest horizontal distance of any body point from ``center`` over the motion,
        metres; full-body views frame ``reach``, partial views about 60 % of it.
    y_range: (lowest, highest) height of any body point over the motion, metres (default
        ``(0, body_height)``); jumps and raised arms widen the framed bands (the partial
        views' bands move up by the lift above ``body_height``).
    margin: extra framing factor (> 1 leaves a border).
    Returns ``{name: Camera}`` with names ``full00 .. upper00 .. lower00 ..``.
    """
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    if body_height <= 0 or radius <= 0 or reach <= 0:
        raise ValueError(f"body_height, radius and reach must be positive, got {body_height}, {radius}, {reach}")
    rng = np.random.default_rng(seed)
    kinds = dome_kinds(num_cams)
    cx, cz = float(center[0]), float(center[1])
    H = float(body_height)
    y_lo, y_hi = (0.0, H) if y_range is None else (float(y_range[0]), float(y_range[1]))
    lift = max(0.0, y_hi - H)
    cams: dict[str, Camera] = {}
    offsets = {"full": 0.0, "upper": 0.5, "lower": 0.25}  # stagger the kinds' azimuths (fraction of a step)
    for kind in ("full", "upper", "lower"):
        n = kinds.count(kind)
        heights, (band_lo, band_hi), half_h = _LAYOUT[kind]
        lo = y_lo if band_lo is None else band_lo * H
        hi = y_hi if band_hi is None else band_hi * H + lift
        target_y, half_v = 0.5 * (lo + hi), 0.5 * (hi - lo)
        for i in range(n):
            step = 2 * np.pi / n
            az = (i + (offsets[kind] if i else 0.0)) * step + rng.uniform(-0.06, 0.06)
            cam_y = heights[i % len(heights)] * H * rng.uniform(0.97, 1.03)
            r = radius * rng.uniform(0.95, 1.05)
            eye = np.array([cx + r * np.sin(az), cam_y, cz + r * np.cos(az)])
            target = np.array([cx, target_y, cz]) + rng.uniform(-0.02, 0.02, 3)
            R, T = look_at(eye, target)
            d = float(np.linalg.norm(target - eye))
            K = _intrinsics(
                width, height, d, half_v * margin, max(half_h * reach, 0.25 * H) * margin, rng.uniform(-0.02, 0.02, 2)
            )
            dist = np.zeros(5)
            if distortion and rng.random() < 0.5:
                dist[:4] = [
                    rng.uniform(-max_k1, max_k1),
                    rng.uniform(-0.2, 0.2) * max_k1,
                    rng.uniform(-1e-3, 1e-3),
                    rng.uniform(-1e-3, 1e-3),
                ]
            name = f"{kind}{i:02d}"
            cams[name] = Camera(name, K, R, T, dist, int(width), int(height))
    return cams


def special_cameras(
    kinds: Sequence[SpecialKind],
    width: int,
    height: int,
    body_height: float = 1.7,
    *,
    center: Sequence[float] = (0.0, 0.0),
    reach: float = 0.8,
) -> dict[str, Camera]:
    """Stress-test views: ``top`` (above the head looking almost straight down: grazing on the
    body's sides), ``floor`` (at the feet, looking up along the body: grazing, sees surfaces
    no ring camera sees), ``away`` (on the dome, pointed away from the body: sees nothing)."""
    cx, cz = float(center[0]), float(center[1])
    H = float(body_height)
    out: dict[str, Camera] = {}
    for k in kinds:
        if k == "top":
            eye = np.array([cx + 0.25, 1.9 * H, cz + 0.35])
            target = np.array([cx, 0.3 * H, cz])
            half = max(reach, 0.45 * H) * 1.1
        elif k == "floor":
            # Just in front of the feet, looking up along the body (wide angle, ~100 deg).
            eye = np.array([cx + 0.1, 0.04, cz + reach + 0.35])
            target = np.array([cx, 0.8 * H, cz])
            half = 1.2 * float(np.linalg.norm(target - eye))
        elif k == "away":
            eye = np.array([cx - 3.0, 1.2, cz - 0.6])
            target = eye + np.array([-1.0, 0.05, -0.3])
            half = 1.0
        else:
            raise ValueError(f"unknown special camera kind {k!r}; expected 'top', 'floor' or 'away'")
        R, T = look_at(eye, target)
        d = float(np.linalg.norm(target - eye))
        K = _intrinsics(width, height, d, half, half, np.zeros(2))
        out[k] = Camera(k, K, R, T, np.zeros(5), int(width), int(height))
    return out
