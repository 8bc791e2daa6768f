"""Fit the rig's pose, root motion to triangulated multi-view keypoints (batched over frames, torch).

Per frame ``t`` the unknowns are the pose parameters ``theta_t`` [P] (radians, rig order), the root
rotation ``r_t`` (axis-angle) and translation ``s_t``; forward kinematics gives the keypoints' points ``J_t``
[M, 3] (:func:`keypoint_points`: a joint's posed head, or a marker point riding rigidly on its joint). The
objective, summed over a shard of frames:

- reprojection, robust: ``sum_{c,m} w_{tcm} rho(|pi_c(J_tm) - u_tcm|)`` / ``sum w``, with ``pi_c`` the camera's
  projection (distortion included), ``w`` = detection confidence x triangulation inlier, and the
  Geman-McClure ``rho(e) = sigma^2 e^2 / (e^2 + sigma^2)`` (an outlier costs at most ``sigma^2``);
- 3D: ``lambda_3d rho_m(|J_tm - X_tm|)`` to the triangulated points (speeds up convergence, robust in metres);
- pose prior: ``lambda_pose sum_p ((theta_tp - mu_p) / s_p)^2``, ``mu`` the rest pose (0) or the mean pose of
  motion capture on the same rig (``prior_mean``, :mod:`gsavatar.fitting.prior`), ``s`` 1 rad or, with that motion's
  per-parameter spread (``prior_std``), ``sqrt(std^2 + prior_std_floor^2)``; joints no keypoint sees stay near it;
- joint limits: ``lambda_limit sum relu(|theta| - limit)^2``;
- temporal smoothness: ``lambda_smooth |J_{t+1} - 2 J_t + J_{t-1}|^2`` (metres) and the same on ``theta``
  (optionally ramped up from 0 over the first half of the pose stage, ``smooth_ramp``);
- silhouette (optional, :class:`Silhouette`; a third stage of ``silhouette_steps`` after the keypoint fit):
  ``lambda_sil mean_{c,n} rho_sil(D_tc(pi_c(V_tn)))`` with ``V_tn`` points of the template's surface posed by
  linear blend skinning and ``D_tc`` the distance (pixels) from the camera's foreground mask, 0 inside: every
  surface point must project inside every view's silhouette. One-sided on purpose: clothing and hair only widen a
  real silhouette. It sees what keypoints do not: a hand turned about the forearm pokes its fingers out of the
  hand's silhouette, a torso twisted by the rig's pass-through hip and
  spine joints moves its flanks.

Shape, where the body model has it (:class:`ShapeBasis`: rest joints linear in shape coefficients, e.g. SMPL-X's
``J_regressor (v_template + shapedirs beta)``): one ``beta`` [B] per sequence joins the unknowns of the second
stage, the rig's rest heads become ``heads + beta . dheads`` and ``lambda_shape |beta|^2`` (betas in the model's
standard-deviation units) keeps unseen directions at the mean shape.

Initialisation: the root transform per frame by Kabsch from the rest-pose joints to the triangulated torso
joints, the pose at the prior's centre ``mu``; then ``root_steps`` Adam steps on the root alone and ``steps`` on
everything.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from gsavatar.fitting.triangulate import camera_arrays
from gsavatar.geometry.lbs import RigTensors, lbs, skinning_transforms
from gsavatar.geometry.rotations import matrix_to_axis_angle


@dataclass(frozen=True)
class FitConfig:
    """Weights and schedule of the body fit (module docstring)."""

    steps: int = 800
    """Adam steps on pose + root (after the root-only ones)."""
    root_steps: int = 100
    """Adam steps on the root transform alone, first."""
    lr: float = 0.05
    """Adam learning rate (radians / metres per step, roughly)."""
    sigma_px: float = 10.0
    """Geman-McClure scale of the reprojection residual, pixels."""
    sigma_m: float = 0.05
    """Geman-McClure scale of the 3D residual, metres."""
    w_3d: float = 1.0
    """Weight of the 3D term (per m^2 of rho, against the reprojection's per px^2: see ``fit_sequence``)."""
    w_pose: float = 1e-2
    """Pose prior weight (per rad^2; with a prior spread ``prior_std``, per squared spread)."""
    prior_std_floor: float = 0.05
    """Radians added (in quadrature) to a prior spread, so a parameter the prior's motion never moves can still move."""
    w_limit: float = 1.0
    """Joint-limit weight (per rad^2 beyond ``limit``)."""
    limit: float = 2.6
    """|theta| beyond this (radians) is penalised."""
    w_smooth: float = 0.1
    """Joint acceleration weight (per m^2, frames^-4; detector keypoints: 1.0 with ``smooth_ramp``, fit_body.md)."""
    w_smooth_pose: float = 0.01
    """Pose acceleration weight (per rad^2; with detector keypoints 0.1 and ``smooth_ramp``)."""
    smooth_ramp: bool = False
    """Ramp both smoothness weights from 0 (root stage and first pose step) to their value (half-way through the pose
    stage; full after, while the learning rate decays): the frames are fitted one by one first and made smooth after
    (a continuation; strong smoothness from the start couples the frames before they fit, and the fixed step budget
    then leaves them unconverged). Measured in docs/fit_body.md."""
    w_shape: float = 1e-2
    """Shape prior weight (per unit^2 of beta), when a :class:`ShapeBasis` is fitted."""
    min_confidence: float = 0.1
    """Detections below this confidence are ignored."""
    threshold_px: float = 15.0
    """Triangulation inlier threshold, pixels."""
    w_silhouette: float = 0.0
    """Weight of the silhouette term (per px^2 of rho, like the reprojection's) when masks are given
    (:class:`Silhouette`); 0 = keypoints only."""
    silhouette_steps: int = 200
    """Adam steps of a third stage on pose + root with the silhouette term added (its own cosine schedule from
    ``lr``), after the keypoint fit has converged (the term costs ~4x a keypoint step)."""
    sigma_silhouette_px: float = 4.0
    """Geman-McClure scale of the silhouette distance, pixels."""


class Silhouette(NamedTuple):
    """What the silhouette term needs: surface points of the template with their skinning, and every frame's
    masks as distance maps (:func:`silhouette_distance`)."""

    points: np.ndarray
    """Rest positions of surface points (a subset of the template's vertices), metres.  # [N, 3]"""
    skin_indices: np.ndarray
    """Joint per skinning slot.  # [N, K] int"""
    skin_weights: np.ndarray
    """Skinning weights.  # [N, K] float"""
    distance: np.ndarray
    """Per frame and camera, the distance in full-image pixels from the mask (0 inside), resampled to a common
    size; NaN maps (no mask) are skipped.  # [F, C, h, w] float32"""
    sizes: np.ndarray
    """Full image (width, height) of every camera.  # [C, 2]"""


def silhouette_distance(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Distance (in the mask's pixels) of every pixel from the foreground (mask >= 0.5), 0 inside, resampled to
    ``size`` = (w, h) by area averaging. [H, W] -> [h, w] float32"""
    import cv2

    outside = (np.asarray(mask) < 0.5).astype(np.uint8)
    if not (1 - outside).any():  # an empty mask says nothing about where the body is
        return np.full(size[::-1], np.nan, np.float32)
    d = cv2.distanceTransform(outside, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return cv2.resize(d, size, interpolation=cv2.INTER_AREA).astype(np.float32)


def surface_subset(template, count: int, seed: int = 0) -> np.ndarray:
    """``count`` vertex indices of ``template`` spread over its surface (farthest-point sampling from a seeded
    start; all vertices when it has fewer). -> [min(count, V)] int64"""
    V = np.asarray(template.vertices, np.float64)
    if count >= len(V):
        return np.arange(len(V))
    idx = np.empty(count, np.int64)
    idx[0] = np.random.default_rng(seed).integers(len(V))
    d = np.linalg.norm(V - V[idx[0]], axis=1)
    for i in range(1, count):
        idx[i] = int(d.argmax())
        d = np.minimum(d, np.linalg.norm(V - V[idx[i]], axis=1))
    return idx


class SilhouetteTensors(NamedTuple):
    """:class:`Silhouette` as the tensors the loss reads (made once per fit: :meth:`of`)."""

    points: Tensor  # [N, 3]
    skin_indices: Tensor  # [N, K] long
    skin_weights: Tensor  # [N, K]
    maps: Tensor  # [F * C, 1, h, w] float32, NaN maps zeroed
    valid: Tensor  # [F, C] bool: the map came from a non-empty mask
    sizes: Tensor  # [1, C, 1, 2] full image (width, height)

    @classmethod
    def of(cls, sil: Silhouette, dtype: torch.dtype = torch.float64) -> SilhouetteTensors:
        dist = torch.as_tensor(sil.distance, dtype=torch.float32)
        F, C = dist.shape[:2]
        return cls(
            torch.as_tensor(sil.points, dtype=dtype),
            torch.as_tensor(sil.skin_indices).long(),
            torch.as_tensor(sil.skin_weights, dtype=dtype),
            torch.nan_to_num(dist).reshape(F * C, 1, *dist.shape[2:]),
            torch.isfinite(dist.flatten(2)).all(-1),
            torch.as_tensor(sil.sizes, dtype=dtype)[None, :, None],
        )


def silhouette_loss(
    rig: RigTensors,
    sil: Silhouette | SilhouetteTensors,
    pose: Tensor,
    root_rotation: Tensor,
    root_translation: Tensor,
    cams,
    sigma: float,
) -> Tensor:
    """Mean Geman-McClure silhouette distance of the posed surface points over frames, cameras and points
    (maps of NaN and points behind a camera skipped). Pixel ``(i, j)`` covers ``[j, j + 1] x [i, i + 1]`` (centres
    at +0.5, the renderer's convention): grid_sample with ``align_corners=False``. cams: (Ks, Rs, Ts, dists)
    tensors. [F, P], [F, 3], [F, 3] -> scalar"""
    dt = pose.dtype
    st = sil if isinstance(sil, SilhouetteTensors) else SilhouetteTensors.of(sil, dt)
    T = skinning_transforms(rig, pose, root_rotation, root_translation)  # [F, J, 4, 4]
    V = lbs(st.points.to(dt), st.skin_indices, st.skin_weights.to(dt), T)  # [F, N, 3]
    pix, z = _project(V, *cams)  # [F, C, N, 2], [F, C, N]
    F, C, N = z.shape
    grid = (2.0 * pix / st.sizes.to(dt) - 1.0).float()  # grid_sample's [-1, 1] over the image
    d = torch.nn.functional.grid_sample(
        st.maps, grid.reshape(F * C, N, 1, 2), align_corners=False, padding_mode="border"
    )
    d = d.reshape(F, C, N).to(dt)
    ok = (st.valid[..., None] & (z > 1e-3)).to(dt)  # behind a camera: no silhouette to land in
    return (ok * geman_mcclure(d * d, sigma)).sum() / ok.sum().clamp_min(1.0)


class ShapeBasis(NamedTuple):
    """Rest joint positions linear in B shape coefficients: ``heads + einsum('b,bjk->jk', beta, dheads)``."""

    heads: np.ndarray
    """Rest heads at the mean shape (beta = 0), the rig's joint order.  # [J, 3] metres"""
    dheads: np.ndarray
    """Change of the heads per unit of each coefficient.  # [B, J, 3] metres"""


def _shaped_rig(rt: RigTensors, shape: ShapeBasis, betas: Tensor) -> RigTensors:
    """``rt`` with its rest heads replaced by the shape's at ``betas`` [B] (differentiable in ``betas``)."""
    out = copy.copy(rt)
    h0 = torch.as_tensor(shape.heads, dtype=betas.dtype)
    out.heads = h0 + torch.einsum("b,bjk->jk", betas, torch.as_tensor(shape.dheads, dtype=betas.dtype))
    return out


def _project(X: Tensor, Ks: Tensor, Rs: Tensor, Ts: Tensor, dists: Tensor) -> tuple[Tensor, Tensor]:
    """World points [F, M, 3] into C cameras -> (pixels [F, C, M, 2], depth [F, C, M])."""
    pc = torch.einsum("cij,fmj->fcmi", Rs, X) + Ts[None, :, None]
    z = pc[..., 2]
    zs = torch.where(z.abs() < 1e-6, torch.full_like(z, 1e-6), z)
    x, y = pc[..., 0] / zs, pc[..., 1] / zs
    k1, k2, p1, p2, k3 = (dists[:, i][None, :, None] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    u = Ks[:, 0, 0][None, :, None] * xd + Ks[:, 0, 1][None, :, None] * yd + Ks[:, 0, 2][None, :, None]
    v = Ks[:, 1, 0][None, :, None] * xd + Ks[:, 1, 1][None, :, None] * yd + Ks[:, 1, 2][None, :, None]
    return torch.stack([u, v], -1), z


def keypoint_points(
    rig: RigTensors, joints: Tensor, offsets: Tensor, pose: Tensor, root_rotation: Tensor, root_translation: Tensor
) -> Tensor:
    """World points of a map's keypoints: each joint's skinning transform applied to its rest head plus the
    keypoint's rest offset (a joint keypoint has offset 0: its posed head). [F, P], [F, 3], [F, 3] -> [F, M, 3]"""
    T = skinning_transforms(rig, pose, root_rotation, root_translation)[:, joints]  # [F, M, 4, 4]
    p = rig.heads.to(pose)[joints] + offsets.to(pose)  # [M, 3]
    return (T[..., :3, :3] @ p[None, :, :, None])[..., 0] + T[..., :3, 3]


def posed_keypoints(rig, joint_map, pose, root_rotation, root_translation) -> np.ndarray:
    """:func:`keypoint_points` of a motion (numpy in and out, float64 inside). -> [F, M, 3]"""
    d = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64)
    with torch.no_grad():
        return keypoint_points(
            RigTensors(rig, dtype=torch.float64),
            torch.as_tensor(joint_map.joints),
            d(joint_map.rest_offsets()),
            d(pose),
            d(root_rotation),
            d(root_translation),
        ).numpy()


def geman_mcclure(sq: Tensor, sigma: float) -> Tensor:
    """``sigma^2 e^2 / (e^2 + sigma^2)`` of squared residuals ``sq``."""
    s2 = sigma * sigma
    return s2 * sq / (sq + s2)


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted rigid fit ``dst ~ R src + t``. src, dst [M, 3], w [M] -> (R [3, 3], t [3])."""
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = ((src - cs) * w[:, None]).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


def initial_root(
    rig, joints: np.ndarray, points: np.ndarray, offsets: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Root rotation (axis-angle) and translation per frame from the rest-pose torso joints (the mapped joints
    nearest the root: depth <= 2 in the tree, at least 3) to their triangulated points by Kabsch.
    joints [M] rig joint indices, points [F, M, 3] (NaN: unset), offsets [M, 3] of marker keypoints from their
    joints (None: 0) -> ([F, 3], [F, 3]).
    Frames with fewer than 3 points copy the nearest frame that has them (zeros if none has)."""
    F = points.shape[0]
    heads = rig.heads().astype(np.float64)
    parents = rig.parents()
    root = int(np.flatnonzero(parents < 0)[0])
    # the torso: the mapped joints nearest the root in the tree (limbs in the rest pose would tilt the fit)
    depth = np.zeros(len(parents), int)
    for j in range(len(parents)):
        depth[j] = 0 if parents[j] < 0 else depth[parents[j]] + 1
    d = depth[joints]
    torso = d <= max(2, np.sort(d)[min(2, len(d) - 1)])  # depth <= 2, widened until it holds 3 keypoints
    off = np.zeros((len(joints), 3)) if offsets is None else np.asarray(offsets, np.float64)
    joints, points, off = np.asarray(joints)[torso], points[:, torso], off[torso]
    rest = heads[joints] + off
    rot, trans = np.zeros((F, 3)), np.zeros((F, 3))
    good = np.zeros(F, bool)
    for t in range(F):
        ok = np.isfinite(points[t]).all(1)
        if ok.sum() < 3:
            continue
        R, s = kabsch(rest[ok], points[t][ok], np.ones(int(ok.sum())))
        # world = R (x - h) + h + t_root  =>  t_root = s + R h - h
        rot[t] = matrix_to_axis_angle(torch.as_tensor(R)[None]).numpy()[0]
        trans[t] = s + R @ heads[root] - heads[root]
        good[t] = True
    if good.any():
        idx = np.flatnonzero(good)
        near = idx[np.abs(np.arange(F)[:, None] - idx[None]).argmin(1)]
        rot, trans = rot[near], trans[near]
    return rot, trans


def fit_sequence(
    rig,
    cameras: list,
    keypoints: np.ndarray,
    joint_map,
    points: np.ndarray,
    inliers: np.ndarray,
    config: FitConfig = FitConfig(),
    init: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    progress=None,
    shape: ShapeBasis | None = None,
    silhouette: Silhouette | None = None,
    prior_mean: np.ndarray | None = None,
    prior_std: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Fit a shard of frames (module docstring).

    keypoints [F, C, K, 3]; joint_map: :class:`~gsavatar.fitting.keypoints.JointMap` (M used keypoints);
    points [F, K, 3], inliers [F, K, C] from :func:`gsavatar.fitting.triangulate.triangulate`. ``init``:
    (pose [F, P], root_rotation [F, 3], root_translation [F, 3]) to start from (default: Kabsch root, the
    pose at ``prior_mean``). ``progress(i, n)`` is called every step. ``shape``: fit one shape vector for the
    sequence too (its ``heads`` replace the rig's; the Kabsch start uses the rig's). ``silhouette``: masks of these
    frames for the silhouette term (used with ``config.w_silhouette`` > 0 in a third stage on pose and root).
    ``prior_mean`` [P]: the pose prior's centre and the starting pose (default: the rest pose, 0); ``prior_std`` [P]:
    its spread per parameter (default: 1 rad everywhere; see the module docstring). -> pose,
    root_rotation, root_translation (float32), ``reprojection_px`` [F] (mean over inlier detections of the fitted
    joints; NaN without any) and, with ``shape``, ``betas`` [B].
    """
    c = config
    for name in ("sigma_px", "sigma_m", "sigma_silhouette_px"):
        if not getattr(c, name) > 0:
            raise ValueError(f"config.{name} must be > 0, got {getattr(c, name)}")
    for name in ("w_silhouette", "silhouette_steps", "steps", "root_steps"):
        if not getattr(c, name) >= 0:
            raise ValueError(f"config.{name} must be >= 0, got {getattr(c, name)}")
    dt = torch.float64
    mu = np.zeros(rig.pose_dim) if prior_mean is None else np.asarray(prior_mean, np.float64)
    if mu.shape != (rig.pose_dim,) or not np.all(np.isfinite(mu)):
        raise ValueError(f"prior_mean must be [{rig.pose_dim}] finite pose parameters, got shape {list(mu.shape)}")
    if prior_std is None:
        spread = np.ones(rig.pose_dim)
    else:
        sd = np.asarray(prior_std, np.float64)
        if sd.shape != (rig.pose_dim,) or not np.all(np.isfinite(sd)) or (sd < 0).any():
            raise ValueError(f"prior_std must be [{rig.pose_dim}] finite values >= 0, got shape {list(sd.shape)}")
        if not c.prior_std_floor > 0:
            raise ValueError(f"config.prior_std_floor must be > 0, got {c.prior_std_floor}")
        spread = np.sqrt(sd**2 + c.prior_std_floor**2)
    kp_idx, jt_idx = joint_map.keypoints, joint_map.joints
    F = keypoints.shape[0]
    uv = torch.as_tensor(keypoints[:, :, kp_idx, :2], dtype=dt)  # [F, C, M, 2]
    conf = keypoints[:, :, kp_idx, 2]
    w = np.where(conf >= c.min_confidence, conf, 0.0) * inliers[:, kp_idx, :].transpose(0, 2, 1)  # [F, C, M]
    w = torch.as_tensor(w, dtype=dt)
    X = torch.as_tensor(np.nan_to_num(points[:, kp_idx]), dtype=dt)
    wx = torch.as_tensor(np.isfinite(points[:, kp_idx]).all(-1), dtype=dt)  # [F, M]
    Ks, Rs, Ts, ds = (torch.as_tensor(a, dtype=dt) for a in camera_arrays(cameras))
    rt = RigTensors(rig, dtype=dt)
    betas = None
    if shape is not None:
        if shape.heads.shape != (rig.num_joints, 3) or shape.dheads.shape[1:] != (rig.num_joints, 3):
            raise ValueError(
                f"shape basis must be heads [{rig.num_joints}, 3] and dheads [B, {rig.num_joints}, 3], got "
                f"{list(shape.heads.shape)} and {list(shape.dheads.shape)}"
            )
        betas = torch.zeros(shape.dheads.shape[0], dtype=dt, requires_grad=True)
    if init is None:
        rr0, rt0 = initial_root(rig, jt_idx, points[:, kp_idx], joint_map.rest_offsets())
        pose0 = np.tile(mu, (F, 1))
    else:
        pose0, rr0, rt0 = init
    pose = torch.tensor(pose0, dtype=dt, requires_grad=True)
    rr = torch.tensor(rr0, dtype=dt, requires_grad=True)
    tr = torch.tensor(rt0, dtype=dt, requires_grad=True)
    jt = torch.as_tensor(jt_idx)
    mu_t = torch.as_tensor(mu, dtype=dt)
    inv_spread = torch.as_tensor(1.0 / spread, dtype=dt)
    offsets = torch.as_tensor(joint_map.rest_offsets(), dtype=dt)
    norm2d = w.sum().clamp_min(1e-9)
    norm3d = wx.sum().clamp_min(1e-9)
    # 3D residuals in metres against reprojections in pixels: scale the 3D term to pixels with the mean focal length
    f2 = float((Ks[:, 0, 0] * Ks[:, 1, 1]).mean()) / float(Ts[:, 2].abs().mean().clamp_min(0.5)) ** 2

    use_sil = silhouette is not None and c.w_silhouette > 0
    if use_sil and silhouette.distance.shape[:2] != (F, len(cameras)):
        raise ValueError(
            f"silhouette.distance must be [{F}, {len(cameras)}, h, w] (frames, cameras), got "
            f"{list(silhouette.distance.shape)}"
        )

    sil_t = SilhouetteTensors.of(silhouette, dt) if use_sil else None

    def body() -> RigTensors:
        return rt if betas is None else _shaped_rig(rt, shape, betas)

    def loss(with_pose: bool, with_sil: bool = False, smooth: float = 1.0) -> Tensor:
        J = keypoint_points(body(), jt, offsets, pose if with_pose else pose.detach(), rr, tr)  # [F, M, 3]
        pix, z = _project(J, Ks, Rs, Ts, ds)
        sq = ((pix - uv) ** 2).sum(-1)
        l2d = (w * geman_mcclure(sq, c.sigma_px)).sum() / norm2d
        l3d = (wx * geman_mcclure(((J - X) ** 2).sum(-1), c.sigma_m)).sum() / norm3d * f2 * c.w_3d
        total = l2d + l3d
        if F >= 3:
            total = total + smooth * c.w_smooth * f2 * ((J[2:] - 2 * J[1:-1] + J[:-2]) ** 2).sum(-1).mean()
        if with_pose:
            total = (
                total
                + c.w_pose * (((pose - mu_t) * inv_spread) ** 2).sum(-1).mean()
                + c.w_limit * (torch.relu(pose.abs() - c.limit) ** 2).sum(-1).mean()
            )
            if F >= 3:
                total = total + smooth * c.w_smooth_pose * ((pose[2:] - 2 * pose[1:-1] + pose[:-2]) ** 2).sum(-1).mean()
            if betas is not None:
                total = total + c.w_shape * (betas**2).sum()
            if with_sil:
                total = total + c.w_silhouette * silhouette_loss(
                    body(), sil_t, pose, rr, tr, (Ks, Rs, Ts, ds), c.sigma_silhouette_px
                )
        return total

    full = [pose, rr, tr] + ([] if betas is None else [betas])
    stages = [([rr, tr], c.root_steps, False), (full, c.steps, False)]
    if use_sil:
        stages.append(([pose, rr, tr], c.silhouette_steps, True))
    n, done = sum(st[1] for st in stages), 0
    for stage, (params, steps, with_sil) in enumerate(stages):
        if steps <= 0:
            continue
        opt = torch.optim.Adam(params, lr=c.lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=c.lr * 0.05)
        for i in range(steps):
            opt.zero_grad(set_to_none=True)
            smooth = 1.0
            if c.smooth_ramp and not with_sil:  # the silhouette stage comes after the ramp: full weights
                smooth = 0.0 if stage == 0 else min(1.0, 2.0 * i / max(steps, 1))
            loss(stage >= 1, with_sil, smooth).backward()
            opt.step()
            sched.step()
            done += 1
            if progress is not None:
                progress(done - 1, n)
    with torch.no_grad():
        J = keypoint_points(body(), jt, offsets, pose, rr, tr)
        pix, _ = _project(J, Ks, Rs, Ts, ds)
        err = ((pix - uv) ** 2).sum(-1).sqrt()  # [F, C, M]
        used = w > 0
        cnt = used.sum((1, 2))
        rep = torch.where(
            cnt > 0, (err * used).sum((1, 2)) / cnt.clamp_min(1), torch.full_like(cnt, float("nan"), dtype=dt)
        )
    return {
        "pose": pose.detach().numpy().astype(np.float32),
        "root_rotation": rr.detach().numpy().astype(np.float32),
        "root_translation": tr.detach().numpy().astype(np.float32),
        "reprojection_px": rep.numpy(),
        **({} if betas is None else {"betas": betas.detach().numpy().astype(np.float32)}),
    }
