"""Robust multi-view triangulation: confidence-weighted DLT with outlier views dropped, not averaged in.

For one keypoint seen by views ``c`` with undistorted normalised image coordinates ``(x_c, y_c)``,
confidence ``w_c`` and ``cam_from_world = [R_c | T_c]``, the DLT solves ``A X = 0`` for the homogeneous
point ``X`` with two rows per view, ``w_c (x_c r3 - r1)`` and ``w_c (y_c r3 - r2)`` (``r_i`` the rows of
``[R_c | T_c]``), by the smallest right singular vector.

Outliers: every pair of views is triangulated (a 2-view DLT), each hypothesis counts the views that
reproject within ``threshold_px`` (weighted by confidence); the best hypothesis' inliers are
re-triangulated together and the inlier set re-read once from that point. A keypoint with fewer than two
inlier views stays unset (NaN). All of it is batched over frames and keypoints in numpy (float64).
"""

from __future__ import annotations

from itertools import combinations
from typing import NamedTuple

import numpy as np

from gsavatar.geometry.camera import project, undistort


class Triangulation(NamedTuple):
    points: np.ndarray
    """World points, NaN where fewer than two views agree.  # [F, K, 3]"""
    inliers: np.ndarray
    """Views used for each point.  # [F, K, C] bool"""
    error_px: np.ndarray
    """Mean reprojection error over the inlier views (NaN where unset).  # [F, K]"""


class CameraArrays(NamedTuple):
    """C cameras' calibration stacked (float64), the form the batched maths takes."""

    K: np.ndarray
    """Intrinsics.  # [C, 3, 3]"""
    R: np.ndarray
    """Rotations of ``cam_from_world``.  # [C, 3, 3]"""
    T: np.ndarray
    """Translations of ``cam_from_world``, metres.  # [C, 3]"""
    dist: np.ndarray
    """OpenCV distortion k1, k2, p1, p2, k3.  # [C, 5]"""


def camera_arrays(cameras: list) -> CameraArrays:
    """Stack :class:`~gsavatar.data_schema.capture.Camera` objects in order."""
    return CameraArrays(
        *(np.stack([getattr(c, a) for c in cameras]).astype(np.float64) for a in ("K", "R", "T", "dist"))
    )


def normalized_coords(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixels of one camera -> undistorted normalised coordinates. uv [..., 2] -> [..., 2]"""
    xy = (uv - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    if dist is not None and np.any(dist):
        shape = xy.shape
        xy = undistort(xy.reshape(-1, 2), dist).reshape(shape)
    return xy


def dlt(xy: np.ndarray, w: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Weighted DLT. xy [N, C, 2] normalised coords, w [N, C] weights (0: unused), P [C, 3, 4] -> [N, 3]
    (NaN where fewer than two views have weight)."""
    rows_x = xy[..., 0:1] * P[None, :, 2] - P[None, :, 0]  # [N, C, 4]
    rows_y = xy[..., 1:2] * P[None, :, 2] - P[None, :, 1]
    A = np.concatenate([rows_x * w[..., None], rows_y * w[..., None]], 1)  # [N, 2C, 4]
    _, _, vt = np.linalg.svd(A, full_matrices=False)
    X = vt[:, -1]  # [N, 4]
    with np.errstate(divide="ignore", invalid="ignore"):
        out = X[:, :3] / X[:, 3:4]
    out[(w > 0).sum(1) < 2] = np.nan
    return out


def project_world(X: np.ndarray, cameras: list) -> tuple[np.ndarray, np.ndarray]:
    """World points [N, 3] into every camera (:func:`gsavatar.geometry.camera.project`)
    -> (pixels [N, C, 2], depth [N, C])."""
    proj = [project(X, c.K, c.R, c.T, c.dist) for c in cameras]
    return np.stack([p.pixels for p in proj], 1), np.stack([p.depth for p in proj], 1)


def triangulate(
    keypoints: np.ndarray, cameras: list, min_confidence: float = 0.1, threshold_px: float = 15.0
) -> Triangulation:
    """Robust triangulation of every keypoint of every frame (module docstring).

    keypoints [F, C, K, 3] pixels + confidence (as :func:`gsavatar.fitting.keypoints.read_keypoints`),
    cameras: C :class:`~gsavatar.data_schema.capture.Camera` in the keypoints' order.
    """
    F, C, K, _ = keypoints.shape
    Ks, Rs, Ts, dists = camera_arrays(cameras)
    P = np.concatenate([Rs, Ts[..., None]], -1)  # [C, 3, 4]
    kp = keypoints.reshape(F, C, K, 3).transpose(0, 2, 1, 3).reshape(F * K, C, 3)  # [N, C, 3]
    uv, conf = kp[..., :2], np.where(kp[..., 2] >= min_confidence, kp[..., 2], 0.0)
    xy = np.stack([normalized_coords(uv[:, c], Ks[c], dists[c]) for c in range(C)], 1)  # [N, C, 2]
    N = len(kp)

    def inliers_of(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pix, z = project_world(np.nan_to_num(X), cameras)
        err = np.linalg.norm(pix - uv, axis=-1)  # [N, C]
        ok = (conf > 0) & (z > 0) & (err < threshold_px) & np.isfinite(X).all(1, keepdims=True)
        return ok, err

    best_score = np.full(N, -1.0)
    best_in = np.zeros((N, C), bool)
    for a, b in combinations(range(C), 2):
        both = (conf[:, a] > 0) & (conf[:, b] > 0)
        if not both.any():
            continue
        w = np.zeros((N, C))
        w[:, a], w[:, b] = conf[:, a], conf[:, b]
        X = dlt(xy, w, P)
        ok, _ = inliers_of(X)
        ok &= both[:, None]
        score = (ok * conf).sum(1) + 1e-6 * ok.sum(1)
        better = score > best_score
        best_score[better], best_in[better] = score[better], ok[better]
    for _ in range(2):  # re-triangulate on the inliers, re-read the inlier set from that point
        w = np.where(best_in, conf, 0.0)
        X = dlt(xy, w, P)
        ok, err = inliers_of(X)
        best_in = np.where((ok.sum(1) >= 2)[:, None], ok, best_in)
    w = np.where(best_in, conf, 0.0)
    X = dlt(xy, w, P)
    _, err = inliers_of(X)
    unset = best_in.sum(1) < 2
    X[unset] = np.nan
    best_in[unset] = False
    with np.errstate(invalid="ignore"):
        e = np.where(best_in, err, 0.0).sum(1) / best_in.sum(1)
    e[unset] = np.nan
    return Triangulation(X.reshape(F, K, 3), best_in.reshape(F, K, C), e.reshape(F, K))
