"""Pinhole cameras with OpenCV distortion (k1, k2, p1, p2, k3), world-to-camera extrinsics."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Projection(NamedTuple):
    pixels: np.ndarray  # [N, 2] float, OpenCV pixel coords (pixel centre of (0,0) at 0.0)
    depth: np.ndarray  # [N] camera-space z, metres (<= 0 behind the camera)


def distort(xn: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OpenCV radial-tangential distortion to normalised coords. xn: [N, 2] -> [N, 2]."""
    k1, k2, p1, p2, k3 = dist
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def undistort(xd: np.ndarray, dist: np.ndarray, iters: int = 10) -> np.ndarray:
    """Invert :func:`distort` by fixed-point iteration (as cv2.undistortPoints). [N,2] -> [N,2]."""
    if not np.any(dist):
        return xd.copy()
    xn = xd.copy()
    for _ in range(iters):
        err = distort(xn, dist) - xd
        xn = xn - err
    return xn


def project(
    points: np.ndarray, K: np.ndarray, R: np.ndarray, T: np.ndarray, dist: np.ndarray | None = None
) -> Projection:
    """Project world points to pixels. points [N,3]; K [3,3]; R [3,3], T [3] cam_from_world."""
    pc = points @ R.T + T
    z = pc[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    xn = pc[:, :2] / zs[:, None]
    if dist is not None and np.any(dist):
        xn = distort(xn, dist)
    uv = xn @ K[:2, :2].T + K[:2, 2]
    return Projection(uv, z)


def pixel_rays(
    K: np.ndarray, R: np.ndarray, T: np.ndarray, width: int, height: int, dist: np.ndarray | None = None
) -> np.ndarray:
    """World-space rays (origin, unit dir) through every pixel centre. -> [H, W, 6] float32."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    pix = np.stack([xs.ravel(), ys.ravel()], 1)
    xn = (pix - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    if dist is not None and np.any(dist):
        xn = undistort(xn, dist)
    d_cam = np.concatenate([xn, np.ones((len(xn), 1))], 1)
    d_world = d_cam @ R  # R^T d
    d_world /= np.linalg.norm(d_world, axis=1, keepdims=True)
    origin = -R.T @ T
    rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1)
    return rays.reshape(height, width, 6).astype(np.float32)


def look_at(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])
) -> tuple[np.ndarray, np.ndarray]:
    """``cam_from_world`` (R, T) for an OpenCV camera at ``eye`` looking at ``target`` (+y down in image)."""
    f = target - eye
    f = f / np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-6:
        r = np.cross(f, np.array([0.0, 0.0, 1.0]))
    r /= np.linalg.norm(r)
    d = np.cross(f, r)  # image down
    R = np.stack([r, d, f], 0)
    return R, -R @ eye
