"""Real spherical harmonics (degree 0..3) evaluated the way gsplat does.

gsplat's convention (and Inria 3DGS's): ``rgb = sum_k Y_k(dir) * coeff_k + 0.5``,
then clamped at 0; ``dir`` is the unit vector from the camera centre to the
Gaussian. Basis constants and sign conventions follow gsplat's
``_eval_sh_bases_fast`` (Sloan, "Efficient Spherical Harmonic Evaluation").
"""

from __future__ import annotations

import torch
from torch import Tensor

MAX_SH_DEGREE = 3
SH_C0 = 0.2820947917738781
# Normalising a zero vector would divide by zero; such a direction (Gaussian at
# the camera centre) is meaningless, any finite unit-ish result is fine.
_DIR_NORM_EPS = 1e-12


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients used by ``degree``: (degree + 1)^2."""
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """DC coefficient that reproduces ``rgb`` from every direction.

    Args:
        rgb: Tensor  # [..., 3] colours in [0, 1]

    Returns:
        Tensor  # [..., 3] SH band-0 coefficients
    """
    return (rgb - 0.5) / SH_C0


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the real SH basis up to ``degree`` at unit directions.

    Args:
        degree: 0..3
        dirs: Tensor  # [..., 3] unit directions (x, y, z)

    Returns:
        Tensor  # [..., (degree + 1)^2] basis values, gsplat ordering
    """
    if not 0 <= degree <= MAX_SH_DEGREE:
        raise ValueError(f"sh degree must be in [0, {MAX_SH_DEGREE}], got {degree}")
    # Built from a list + stack (not in-place writes) so autograd reaches dirs.
    out = [torch.full_like(dirs[..., 0], SH_C0)]
    if degree == 0:
        return out[0][..., None]
    x, y, z = dirs.unbind(-1)
    out += [-0.48860251190292 * y, 0.48860251190292 * z, -0.48860251190292 * x]
    if degree >= 2:
        z2 = z * z
        c1 = x * x - y * y
        s1 = 2.0 * x * y
        tmp_b = -1.092548430592079 * z
        out += [
            0.5462742152960395 * s1,
            tmp_b * y,
            0.9461746957575601 * z2 - 0.3153915652525201,
            tmp_b * x,
            0.5462742152960395 * c1,
        ]
    if degree >= 3:
        c2 = x * c1 - y * s1
        s2 = x * s1 + y * c1
        tmp_c = -2.285228997322329 * z2 + 0.4570457994644658
        tmp_b = 1.445305721320277 * z
        out += [
            -0.5900435899266435 * s2,
            tmp_b * s1,
            tmp_c * y,
            z * (1.865881662950577 * z2 - 1.119528997770346),
            tmp_c * x,
            tmp_b * c1,
            -0.5900435899266435 * c2,
        ]
    return torch.stack(out, dim=-1)


def eval_sh_colors(degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """View-dependent colour from SH coefficients (gsplat convention).

    Args:
        degree: SH degree to use (0..3); may be lower than ``coeffs`` supports
        dirs: Tensor  # [..., 3] view directions (camera -> Gaussian), any norm
        coeffs: Tensor  # [..., K, 3] SH coefficients, K >= (degree + 1)^2

    Returns:
        Tensor  # [..., 3] colours, ``max(sum_k Y_k c_k + 0.5, 0)``
    """
    n_bases = num_sh_bases(degree)
    if coeffs.shape[-2] < n_bases:
        raise ValueError(f"coeffs must have at least {n_bases} bases for degree {degree}, got {tuple(coeffs.shape)}")
    if degree > 0:
        norm_sq = (dirs * dirs).sum(-1, keepdim=True)
        dirs = dirs * torch.rsqrt(norm_sq.clamp_min(_DIR_NORM_EPS))
    bases = sh_bases(degree, dirs)  # [..., n_bases]
    rgb = (bases[..., None] * coeffs[..., :n_bases, :]).sum(-2)
    return (rgb + 0.5).clamp_min(0.0)
