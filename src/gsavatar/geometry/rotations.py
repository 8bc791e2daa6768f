"""Rotation conversions (torch, batched, differentiable, stable at zero angle).

Quaternions are wxyz. Axis-angle vectors are ``axis * angle`` in radians.
"""

from __future__ import annotations

import torch
from torch import Tensor


def axis_angle_to_matrix(aa: Tensor) -> Tensor:
    """Rodrigues' formula. aa: [..., 3] -> [..., 3, 3].

    Uses Taylor expansions below 1e-4 rad so gradients stay finite at zero.
    """
    theta2 = (aa * aa).sum(-1, keepdim=True)  # [..., 1]
    theta = torch.sqrt(theta2.clamp_min(1e-24))
    small = theta2 < 1e-8
    # sin(t)/t and (1-cos t)/t^2 with series near 0
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    x, y, z = aa.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*aa.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=aa.dtype, device=aa.device).expand_as(K)
    return eye + a[..., None] * K + b[..., None] * (K @ K)


def matrix_to_axis_angle(R: Tensor) -> Tensor:
    """Inverse of :func:`axis_angle_to_matrix`. R: [..., 3, 3] -> [..., 3], angle in [0, pi]."""
    return quat_to_axis_angle(matrix_to_quat(R))


def matrix_to_quat(R: Tensor) -> Tensor:
    """Rotation matrix -> unit quaternion wxyz with w >= 0. R: [..., 3, 3] -> [..., 4].

    Shepperd's method: picks the largest diagonal term for stability.
    """
    m = R
    t = torch.stack(
        [
            1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        dim=-1,
    )
    idx = t.argmax(-1, keepdim=True)
    s = torch.sqrt(t.gather(-1, idx).clamp_min(1e-12)) * 2  # [..., 1]
    w = torch.stack(
        [
            s[..., 0] / 4,
            (m[..., 2, 1] - m[..., 1, 2]) / s[..., 0],
            (m[..., 0, 2] - m[..., 2, 0]) / s[..., 0],
            (m[..., 1, 0] - m[..., 0, 1]) / s[..., 0],
        ],
        -1,
    )
    x = torch.stack(
        [
            (m[..., 2, 1] - m[..., 1, 2]) / s[..., 0],
            s[..., 0] / 4,
            (m[..., 0, 1] + m[..., 1, 0]) / s[..., 0],
            (m[..., 0, 2] + m[..., 2, 0]) / s[..., 0],
        ],
        -1,
    )
    y = torch.stack(
        [
            (m[..., 0, 2] - m[..., 2, 0]) / s[..., 0],
            (m[..., 0, 1] + m[..., 1, 0]) / s[..., 0],
            s[..., 0] / 4,
            (m[..., 1, 2] + m[..., 2, 1]) / s[..., 0],
        ],
        -1,
    )
    z = torch.stack(
        [
            (m[..., 1, 0] - m[..., 0, 1]) / s[..., 0],
            (m[..., 0, 2] + m[..., 2, 0]) / s[..., 0],
            (m[..., 1, 2] + m[..., 2, 1]) / s[..., 0],
            s[..., 0] / 4,
        ],
        -1,
    )
    cands = torch.stack([w, x, y, z], dim=-2)  # [..., 4, 4]
    q = cands.gather(-2, idx[..., None].expand(*idx.shape[:-1], 1, 4)).squeeze(-2)
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def quat_to_axis_angle(q: Tensor) -> Tensor:
    """Unit quaternion wxyz -> axis-angle. q: [..., 4] -> [..., 3]."""
    q = q * torch.where(q[..., :1] < 0, -1.0, 1.0)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2 * torch.atan2(s, q[..., :1])
    # angle / sin(angle/2) -> 2 as s -> 0
    scale = torch.where(s < 1e-8, 2.0 / q[..., :1].clamp_min(1e-12), angle / s.clamp_min(1e-12))
    return v * scale


def quat_to_matrix(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Quaternion wxyz (any norm; zero -> identity) -> rotation matrix. q: [..., 4] -> [..., 3, 3]."""
    # R is scale invariant: dividing by the detached largest component keeps |q| from
    # overflowing (float32: |q| > ~1e19 gave n = inf, q / n = 0 and silently R = I).
    peak = q.detach().abs().amax(dim=-1, keepdim=True)
    q = q / torch.where(peak > 1.0, peak, torch.ones_like(peak))
    n = q.norm(dim=-1, keepdim=True)
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    q = torch.where(n > eps, q / n.clamp_min(eps), ident)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(*q.shape[:-1], 3, 3)


def euler_axis_to_matrix(angle: Tensor, axis: Tensor) -> Tensor:
    """Rotation by ``angle`` about unit ``axis``. angle: [...], axis: [..., 3] -> [..., 3, 3]."""
    return axis_angle_to_matrix(axis * angle[..., None])


def orthonormalize(R: Tensor) -> Tensor:
    """Nearest rotation to a (blended) 3x3 matrix via SVD, det fixed to +1. [..., 3, 3] -> [..., 3, 3].

    Linear blend skinning averages rotations, which shrinks and shears them; Gaussians
    and normals need a true rotation.
    """
    U, _, Vh = torch.linalg.svd(R)
    d = torch.det(U @ Vh)
    D = torch.ones_like(R[..., 0])
    D[..., 2] = d
    return (U * D[..., None, :]) @ Vh
