"""Stateless math of the Gaussian avatar (supp. A), used by :class:`~gsavatar.models.avatar.GaussianAvatar`.

Pipeline for one batch of frames:

1. MLP conditioning pose: pose PCA + clamping (:func:`pca_project`), then per-anchor
   masking and concatenation with the masked face embedding and the appearance
   latent (:func:`anchor_inputs`).
2. Anchor MLP outputs ``[B, A, n_basis + n_ctrl_basis]`` are interpolated to Gaussians
   and control points with the 3-NN inverse-distance weights (:func:`interpolate`).
3. Every property is ``h(λ + <w, ΔΛ>)`` (:func:`apply_basis` + activations).
4. Canonical position = rest + interpolated control displacement + per-Gaussian
   offset; then LBS (:func:`pose_gaussians`).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from gsavatar.geometry.rotations import matrix_to_quat, orthonormalize, quat_to_matrix
from gsavatar.models.config import SH_C0

HAND_GROUP_NAMES = ("left_hand", "right_hand")


# --- conditioning ---------------------------------------------------------------------
def pca_project(pose: Tensor, mean: Tensor, basis: Tensor, limit: Tensor) -> Tensor:
    """Pose -> PCA coefficients, clamp to ``±limit``, back (as ``PosePCA.project``).

    pose [B, P], mean [P], basis [P, C] unit columns, limit [C] (``clamp_sigma * σ``) -> [B, P]
    """
    coeffs = (pose - mean) @ basis  # [B, C]
    coeffs = torch.maximum(torch.minimum(coeffs, limit), -limit)
    return coeffs @ basis.T + mean


def pca_mode_for(mode: str, training: bool) -> str:
    """Which PCA the MLP input uses: ``local``/``global``/``none``.

    ``global_test_only`` (MMLPs-dagger) is ``none`` in training and ``global`` in eval.
    """
    if mode == "global_test_only":
        return "none" if training else "global"
    if mode not in ("local", "global", "none"):
        raise ValueError(f"unknown pca mode {mode!r}")
    return mode


def effective_pose_mask(pose_mask: np.ndarray, slot_groups: np.ndarray, hand_groups: list[int], variant: str, local_pose: bool) -> np.ndarray:
    """Per-anchor pose-input mask for a model variant.

    - ``local_pose=False`` (ablation "w/o local pose") or ``conv_uv`` (nRFGCA-dagger): all ones.
    - ``ours``: the localization mask.
    - ``mmlps``: all ones, except the hand/finger slots (``slot_groups`` in
      ``hand_groups``), which keep their localization columns.

    pose_mask [A, P] bool, slot_groups [P] int -> [A, P] bool
    """
    pose_mask = np.asarray(pose_mask, bool)
    if not local_pose or variant == "conv_uv":
        return np.ones_like(pose_mask)
    if variant == "ours":
        return pose_mask.copy()
    if variant == "mmlps":
        out = np.ones_like(pose_mask)
        hand = np.isin(np.asarray(slot_groups), hand_groups)
        out[:, hand] = pose_mask[:, hand]
        return out
    raise ValueError(f"unknown variant {variant!r}")


def anchor_inputs(
    pose: Tensor,
    pose_mask: Tensor,
    face: Tensor | None,
    face_mask: Tensor,
    face_dim: int,
    latents: Tensor | None,
    latent_dim: int,
) -> Tensor:
    """Concatenated per-anchor MLP input ``[θ̂_i, φ̂_i, l_i]``.

    Args:
        pose: Tensor  # [B, P] conditioning pose (after PCA)
        pose_mask: Tensor  # [A, P] float 0/1
        face: Tensor | None  # [B, E]; None -> zeros
        face_mask: Tensor  # [A] float 0/1
        face_dim: E (0: no face block)
        latents: Tensor | None  # [B, A, L]; None -> zeros
        latent_dim: L (0: no latent block)

    Returns:
        Tensor  # [B, A, P + E + L]
    """
    B = pose.shape[0]
    A = pose_mask.shape[0]
    parts = [pose[:, None, :] * pose_mask[None]]  # [B, A, P]
    if face_dim > 0:
        if face is None:
            parts.append(pose.new_zeros(B, A, face_dim))
        else:
            parts.append(face[:, None, :].to(pose.dtype) * face_mask[None, :, None])  # [B, A, E]
    if latent_dim > 0:
        parts.append(pose.new_zeros(B, A, latent_dim) if latents is None else latents.to(pose.dtype))
    return torch.cat(parts, dim=-1)


def interpolate(values: Tensor, idx: Tensor, weights: Tensor) -> Tensor:
    """3-NN inverse-distance interpolation (supp. eq. 1).

    values [B, M, D] (per anchor / control point), idx [N, k] long, weights [N, k] -> [B, N, D]
    """
    return torch.einsum("bnkd,nk->bnd", values[:, idx], weights.to(values.dtype))


def apply_basis(bias: Tensor, basis: Tensor | None, coeffs: Tensor | None, batch: int) -> Tensor:
    """Pre-activation property ``λ + <w, ΔΛ>``.

    bias [N, *D], basis [N, K, *D] or None, coeffs [B, N, K] or None (no correctives)
    -> [B, N, *D] (an expanded view of ``bias`` without correctives)
    """
    if coeffs is None or basis is None:
        return bias[None].expand(batch, *bias.shape)
    delta = torch.einsum("bnk,nkd->bnd", coeffs, basis.reshape(basis.shape[0], basis.shape[1], -1))
    return bias[None] + delta.reshape(coeffs.shape[0], *bias.shape)


# --- activations ----------------------------------------------------------------------
def activate_scale(x: Tensor, scale_max: float) -> Tensor:
    """``min(exp(x), scale_max)``, metres. [...] -> [...]"""
    # exp(x) overflows for x > ~88 (float32) and the clamp's zero gradient times exp's
    # inf partial is NaN. Capping x one unit above log(scale_max) first keeps exp finite
    # without changing any value (the outer clamp still gives exactly scale_max).
    return torch.clamp(torch.exp(torch.clamp(x, max=math.log(scale_max) + 1.0)), max=scale_max)


def activate_quat(x: Tensor) -> Tensor:
    """Normalised wxyz quaternion. [..., 4] -> [..., 4]"""
    # Normalising is scale invariant, so dividing by the detached largest component
    # first changes neither the value nor the gradient, but keeps |x| from overflowing
    # (float32: |x| > ~1e19 had norm inf and silently became the zero quaternion).
    peak = x.detach().abs().amax(dim=-1, keepdim=True)
    x = x / torch.where(peak > 1.0, peak, torch.ones_like(peak))
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def activate_sh0(x: Tensor) -> Tensor:
    """``tanh(x) * 0.5 / C0`` so ``colour = SH0 * C0 + 0.5`` spans (0, 1). [..., 3] -> [..., 3]"""
    return torch.tanh(x) * (0.5 / SH_C0)


def activate_shn(x: Tensor, bound: float) -> Tensor:
    """``bound * tanh(x)``. [...] -> [...]"""
    return torch.tanh(x) * bound


def sh0_from_rgb(rgb: Tensor) -> Tensor:
    """Inverse of :func:`activate_sh0` composed with ``colour = SH0*C0 + 0.5``: pre-activation for rgb in (0, 1)."""
    return torch.atanh((2.0 * rgb - 1.0).clamp(-1 + 1e-6, 1 - 1e-6))


# --- skinning ---------------------------------------------------------------------------
def polar_rotation(M: Tensor, iters: int = 8) -> Tensor:
    """Nearest rotation to blended 3x3 matrices. [..., 3, 3] -> [..., 3, 3]

    Without autograd: :func:`~gsavatar.geometry.rotations.orthonormalize` (SVD, det
    fixed to +1). When ``M`` requires grad, SVD's backward is NaN for (near-)rotations
    (repeated singular values), so Newton's polar iteration ``X <- (X + X^-T) / 2``
    (quadratic convergence; exact for rotations) is used instead. LBS blends of
    rotations with non-negative weights have ``det > 0``, where both agree.
    """
    if not (torch.is_grad_enabled() and M.requires_grad):
        return orthonormalize(M)
    X = M
    for _ in range(iters):
        X = 0.5 * (X + torch.linalg.inv(X).transpose(-1, -2))
    return X


def blend_affine(transforms: Tensor, skin_indices: Tensor, skin_weights: Tensor) -> Tensor:
    """LBS-blended 3x4 affine per point. transforms [B, J, 4, 4] posed_from_rest, idx/weights [N, K] -> [B, N, 3, 4]"""
    return torch.einsum("nk,bnkij->bnij", skin_weights.to(transforms.dtype), transforms[:, skin_indices, :3, :])


def pose_gaussians(canonical: Tensor, quats: Tensor, affine: Tensor) -> tuple[Tensor, Tensor]:
    """Pose canonical Gaussians with blended transforms.

    canonical [B, G, 3] rest-space centres; quats [B, G, 4] wxyz unit (canonical);
    affine [B, G, 3, 4] blended posed_from_rest -> (means [B, G, 3] world, quats [B, G, 4] wxyz)
    """
    means = (affine[..., :3] @ canonical[..., None])[..., 0] + affine[..., 3]
    R = polar_rotation(affine[..., :3]) @ quat_to_matrix(quats)
    return means, matrix_to_quat(R)


# --- initialisation ---------------------------------------------------------------------
def knn_mean_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance to the ``k`` nearest other points.  [N, 3] -> [N] float64"""
    pts = np.asarray(points, np.float64)
    k = min(k, len(pts) - 1)
    if k <= 0:
        return np.full(len(pts), 1e-2)
    d, _ = cKDTree(pts).query(pts, k=k + 1)
    return d[:, 1:].mean(axis=1)


def normal_frames(normals: np.ndarray) -> np.ndarray:
    """Right-handed frames ``[t1, t2, n]`` (columns) with the third axis along ``normals``. [N, 3] -> [N, 3, 3]"""
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0  # axis least aligned with n
    t1 = np.cross(helper, n)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    t2 = np.cross(n, t1)
    return np.stack([t1, t2, n], axis=2)


def init_gaussian_params(positions: np.ndarray, normals: np.ndarray, scale_max: float, normal_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Initial (log-scale [G, 3], quaternion wxyz [G, 4]) biases.

    Tangent scales = mean distance to the 3 nearest Gaussians (clamped to
    ``[1e-5, scale_max]``), normal scale ``normal_ratio`` times that; the rotation maps
    the local z axis (the smallest one) onto the surface normal.
    """
    d = np.clip(knn_mean_distance(positions, 3), 1e-5, scale_max)
    scales = np.stack([d, d, np.maximum(d * normal_ratio, 1e-6)], axis=1)
    R = torch.as_tensor(normal_frames(normals))
    q = matrix_to_quat(R).numpy()
    return np.log(scales).astype(np.float32), q.astype(np.float32)
