"""Stateless math of the Gaussian avatar (supp. A), used by :class:`~gsavatar.models.avatar.GaussianAvatar`.

Pipeline for one batch of frames:

1. MLP conditioning pose: pose PCA + clamping (:func:`~gsavatar.data_schema.pose_pca.pca_project`), then per-anchor
   masking and concatenation with the masked face embedding and the appearance
   latent (:func:`anchor_inputs`).
2. Anchor MLP outputs ``[B, A, n_basis + n_ctrl_basis]`` are interpolated to Gaussians
   and control points with the 3-NN inverse-distance weights (:func:`interpolate`).
3. Every property is ``h(λ + Δ)``: ``Δ = <w, ΔΛ>`` (:func:`basis_delta`) or a pose head's
   own delta (:mod:`gsavatar.models.pose_heads`), :func:`add_delta` + activations.
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
from gsavatar.models.kernels import (
    basis_product,
    polar_rotation_fast,
    pose_lbs_fast,
    posed_quaternion_fast,
    sparse_interpolate_fast,
)
from gsavatar.models.config import SH_C0

HAND_GROUP_NAMES = ("left_hand", "right_hand")


# --- conditioning ---------------------------------------------------------------------
def pca_mode_for(mode: str, training: bool) -> str:
    """Which PCA the MLP input uses: ``local``/``global``/``none``.

    ``global_test_only`` (MMLPs-dagger) is ``none`` in training and ``global`` in eval.
    """
    if mode == "global_test_only":
        return "none" if training else "global"
    if mode not in ("local", "global", "none"):
        raise ValueError(f"unknown pca mode {mode!r}")
    return mode


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


def interpolation_matrix(idx: Tensor, weights: Tensor, num_sources: int) -> Tensor:
    """The weights of a k-NN interpolation as a sparse ``[N, M]`` COO matrix (row n: weights of its k sources).

    idx [N, k] long in [0, M), weights [N, k] -> sparse [N, M] (coalesced; repeated sources add up)
    """
    N, k = idx.shape
    rows = torch.arange(N, device=idx.device).repeat_interleave(k)
    return torch.sparse_coo_tensor(
        torch.stack([rows, idx.reshape(-1)]), weights.reshape(-1), (N, num_sources), check_invariants=True
    ).coalesce()


def sparse_interpolate(values: Tensor, matrix: Tensor, compiled: bool = True) -> Tensor:
    """:func:`interpolate` as one sparse-dense product over the whole batch (the same numbers up to summation
    order; ~8x faster forward+backward on CPU than gathering ``[B, N, k, D]``, measured in
    ``benchmarks/bench_train_step.py``).

    values [B, M, D], matrix sparse [N, M] (:func:`interpolation_matrix`) -> [B, N, D]

    ``compiled`` (CPU): row loops compiled with numba (:func:`~gsavatar.models.kernels.sparse_interpolate_fast`);
    False: ``torch.sparse.mm``, its oracle.
    """
    B, M, D = values.shape
    if matrix.shape[1] != M:
        raise ValueError(f"values has {M} sources, the matrix {matrix.shape[1]}")
    if compiled:
        fast = sparse_interpolate_fast(values, matrix)
        if fast is not None:
            return fast
    flat = values.transpose(0, 1).reshape(M, B * D)  # [M, B*D]
    out = torch.sparse.mm(matrix.to(values.dtype), flat)  # [N, B*D]
    return out.reshape(-1, B, D).transpose(0, 1)


def basis_delta(basis: Tensor, coeffs: Tensor) -> Tensor:
    """Corrective ``<w, ΔΛ>`` of a per-point basis. basis [N, K, *D], coeffs [B, N, K] -> [B, N, *D]

    The product is :func:`~gsavatar.models.kernels.basis_product` (a compiled loop on CPU; the
    einsum it replaces is its oracle)."""
    delta = basis_product(coeffs, basis.reshape(basis.shape[0], basis.shape[1], -1))
    return delta.reshape(coeffs.shape[0], basis.shape[0], *basis.shape[2:])


def add_delta(bias: Tensor, delta: Tensor | None, batch: int) -> Tensor:
    """Pre-activation property ``λ + Δ`` (a pose head's delta, e.g. ``<w, ΔΛ>``).

    bias [N, *D], delta [B, N, *D] or None (no correctives) -> [B, N, *D] (an expanded view of ``bias`` without delta)
    """
    if delta is None:
        return bias[None].expand(batch, *bias.shape)
    return bias[None] + delta


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
    norm = x.norm(dim=-1, keepdim=True)
    if bool(torch.isfinite(norm).all()):  # the common case: one pass fewer (same values and gradients)
        return x / norm.clamp_min(1e-12)
    peak = x.detach().abs().amax(dim=-1, keepdim=True)
    x = x / torch.where(peak > 1.0, peak, torch.ones_like(peak))
    return x / x.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def activate_sh0(x: Tensor) -> Tensor:
    """``tanh(x) * 0.5 / C0`` so ``colour = SH0 * C0 + 0.5`` spans (0, 1). [..., 3] -> [..., 3]"""
    # tanh(x) = 2 sigmoid(2x) - 1: CPU torch's tanh costs ~6x its sigmoid (2.0 vs 0.32 ms for 393k
    # floats, one thread); same values to 2e-7 absolute (tests)
    return (torch.sigmoid(2.0 * x) - 0.5) * (1.0 / SH_C0)


def activate_shn(x: Tensor, bound: float) -> Tensor:
    """``bound * tanh(x)`` (computed as ``bound * (2 sigmoid(2x) - 1)``, see :func:`activate_sh0`). [...] -> [...]"""
    return (torch.sigmoid(2.0 * x) - 0.5) * (2.0 * bound)


def sh0_from_rgb(rgb: Tensor) -> Tensor:
    """Inverse of :func:`activate_sh0` composed with ``colour = SH0*C0 + 0.5``: pre-activation for rgb in (0, 1)."""
    return torch.atanh((2.0 * rgb - 1.0).clamp(-1 + 1e-6, 1 - 1e-6))


# --- skinning ---------------------------------------------------------------------------
POLAR_MIN_DET = 1e-6
"""Blends with ``det`` below this (or negative) take the SVD path of :func:`polar_rotation`."""


def _cofactors(x: list[Tensor]) -> tuple[list[Tensor], Tensor]:
    """Cofactors (row-major, ``X^-T = cof / det``) and determinant of 3x3 matrices given as 9 components."""
    x00, x01, x02, x10, x11, x12, x20, x21, x22 = x
    cof = [
        x11 * x22 - x12 * x21,
        x12 * x20 - x10 * x22,
        x10 * x21 - x11 * x20,
        x21 * x02 - x22 * x01,
        x22 * x00 - x20 * x02,
        x20 * x01 - x21 * x00,
        x01 * x12 - x02 * x11,
        x02 * x10 - x00 * x12,
        x00 * x11 - x01 * x10,
    ]
    return cof, x00 * cof[0] + x01 * cof[1] + x02 * cof[2]


def polar_rotation(M: Tensor, max_iters: int = 12, tol: float | None = None, compiled: bool = True) -> Tensor:
    """Nearest rotation to blended 3x3 matrices (the orthogonal polar factor). [..., 3, 3] -> [..., 3, 3]

    Scaled Newton iteration ``X <- (g X + (g X)^-T) / 2``, ``g = |det X|^(-1/3)`` (Higham 1986),
    on the 9 components with the inverse-transpose in closed form (cofactors / det): no SVD and no
    batched LAPACK call. The SVD it replaces was the largest single cost of a CPU training step
    (~76 ms per step on ~87k matrices; this is ~10x faster, ``benchmarks/bench_train_step.py``).
    Scaling makes convergence independent of the blend's overall shrinkage; it stops when the
    largest update is below ``tol`` (default: 10x the dtype's eps), typically after 4-6 iterations
    for LBS blends. Autograd differentiates the iteration; it matches SVD's gradient (tested) and
    stays finite at exact rotations, where SVD's backward is NaN (repeated singular values).

    Matrices with ``det <= POLAR_MIN_DET`` (reflections, near-singular blends of near-opposite
    rotations) fall back to :func:`~gsavatar.geometry.rotations.orthonormalize` (SVD, det := +1).

    ``compiled`` (CPU): the same iteration compiled per matrix with a closed-form backward
    (:func:`~gsavatar.models.kernels.polar_rotation_fast`, ~10x faster forward+backward); False runs
    the torch iteration above, its oracle.
    """
    if M.shape[-2:] != (3, 3):
        raise ValueError(f"M must be [..., 3, 3], got {tuple(M.shape)}")
    tol = 10 * torch.finfo(M.dtype).eps if tol is None else tol
    flat = M.reshape(*M.shape[:-2], 9)
    _, det0 = _cofactors(list(flat.detach().unbind(-1)))
    bad = ~(det0 > POLAR_MIN_DET)  # also catches NaN
    any_bad = bool(bad.any())
    if any_bad:
        eye = torch.eye(3, dtype=M.dtype, device=M.device).reshape(9)
        flat = torch.where(bad[..., None], eye, flat)
    fast = polar_rotation_fast(flat.reshape(M.shape), tol, max_iters) if compiled else None
    x = [] if fast is not None else list(flat.unbind(-1))
    for it in range(max_iters if fast is None else 0):
        cof, det = _cofactors(x)
        g = det.abs().clamp_min(1e-30).pow(-1.0 / 3.0)
        a, b = 0.5 * g, 0.5 / (g * det)
        x, old = [a * xi + b * ci for xi, ci in zip(x, cof)], x
        # the convergence test costs a device sync: only from the 4th iteration, when it can pass
        if it >= 3 and (not x[0].numel() or max(float((n - o).detach().abs().max()) for n, o in zip(x, old)) <= tol):
            break
    X = fast if fast is not None else torch.stack(x, -1).reshape(M.shape)
    if any_bad:
        X = X.clone()
        X[bad] = orthonormalize(M.detach()[bad]).to(X.dtype)  # only the few bad ones pay for the SVD
    return X


def blend_affine(
    transforms: Tensor, skin_indices: Tensor, skin_weights: Tensor, skin_matrix: Tensor | None = None
) -> Tensor:
    """LBS-blended 3x4 affine per point. transforms [B, J, 4, 4] posed_from_rest, idx/weights [N, K] -> [B, N, 3, 4]

    ``skin_matrix``: the same weights as a sparse ``[N, J]`` matrix (:func:`interpolation_matrix`), one
    sparse product instead of gathering ``[B, N, K, 3, 4]`` (the gather is the reference).
    """
    B, J = transforms.shape[:2]
    if skin_matrix is not None:
        return sparse_interpolate(transforms[:, :, :3, :].reshape(B, J, 12), skin_matrix).reshape(B, -1, 3, 4)
    return torch.einsum("nk,bnkij->bnij", skin_weights.to(transforms.dtype), transforms[:, skin_indices, :3, :])


def pose_gaussians(canonical: Tensor, quats: Tensor, affine: Tensor, compiled: bool = True) -> tuple[Tensor, Tensor]:
    """Pose canonical Gaussians with blended transforms.

    The posed rotation is ``polar(A) @ R(quats)`` as a unit quaternion with ``w >= 0``. ``compiled``
    (CPU, every blend with ``det > POLAR_MIN_DET``): one fused kernel with a closed-form backward
    (:func:`~gsavatar.models.kernels.posed_quaternion_fast`); False: the torch composition, its oracle.

    canonical [B, G, 3] rest-space centres; quats [B, G, 4] wxyz unit (canonical);
    affine [B, G, 3, 4] blended posed_from_rest -> (means [B, G, 3] world, quats [B, G, 4] wxyz)
    """
    means = (affine[..., :3] @ canonical[..., None])[..., 0] + affine[..., 3]
    A = affine[..., :3]
    if compiled and bool((_det3(A.detach()) > POLAR_MIN_DET).all()):
        fast = posed_quaternion_fast(A, quats, 10 * torch.finfo(A.dtype).eps)
        if fast is not None:
            return means, fast
    R = polar_rotation(A, compiled=compiled) @ quat_to_matrix(quats)
    return means, matrix_to_quat(R)


def pose_lbs(
    canonical: Tensor,
    quats: Tensor,
    transforms: Tensor,
    skin_indices: Tensor,
    skin_weights: Tensor,
    skin_matrix: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Skin and pose canonical Gaussians: :func:`blend_affine` then :func:`pose_gaussians`.

    At inference on CPU (no gradients, every blend with ``det > POLAR_MIN_DET``) the three steps run as
    one compiled pass (:func:`~gsavatar.models.kernels.pose_lbs_fast`; the two functions are its oracle).

    canonical [B, G, 3], quats [B, G, 4] wxyz (unit), transforms [B, J, 4, 4] posed_from_rest,
    skin_indices/skin_weights [G, K], skin_matrix sparse [G, J] or None -> (means [B, G, 3], quats [B, G, 4])
    """
    if skin_matrix is not None:
        fast = pose_lbs_fast(
            transforms, skin_matrix, canonical, quats, 10 * torch.finfo(canonical.dtype).eps, POLAR_MIN_DET
        )
        if fast is not None:
            return fast
    return pose_gaussians(canonical, quats, blend_affine(transforms, skin_indices, skin_weights, skin_matrix))


def _det3(M: Tensor) -> Tensor:
    """Determinant of 3x3 matrices in closed form. [..., 3, 3] -> [...]"""
    return (
        M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
        - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
        + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0])
    )


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


def init_gaussian_params(
    positions: np.ndarray, normals: np.ndarray, scale_max: float, normal_ratio: float
) -> tuple[np.ndarray, np.ndarray]:
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
