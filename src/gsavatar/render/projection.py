"""EWA projection of 3D Gaussians into pinhole cameras (pure PyTorch).

Mirrors gsplat 1.5.3's fused pinhole projection kernel
(``ProjectionEWA3DGSFused.cu``) so the CPU compositor sees the same 2D Gaussians
that gsplat's CUDA rasteriser would: same Jacobian clamping, same 0.3 px
low-pass dilation, same opacity-aware bounding radius and the same culling.

Conventions:
    * ``viewmats`` are ``cam_from_world`` 4x4 matrices, OpenCV camera axes
      (+x right, +y down, +z forward).
    * Quaternions are ``wxyz`` and need not be normalised; like gsplat's kernel, R is that of the
      normalised quaternion (:func:`gsavatar.geometry.rotations.quat_to_matrix`; zero -> identity).
    * Pixel ``(i, j)`` (row, column) has its centre at ``(j + 0.5, i + 0.5)``.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from gsavatar.geometry.rotations import quat_to_matrix

# gsplat's ALPHA_THRESHOLD: a Gaussian never contributes where alpha < 1/255.
ALPHA_THRESHOLD = 1.0 / 255.0
# gsplat's largest bounding extent in standard deviations: sqrt(2 ln 255) ~ 3.33,
# i.e. exactly where a fully opaque Gaussian drops below ALPHA_THRESHOLD.
MAX_EXTEND = 3.33


class ProjectedGaussians(NamedTuple):
    """Per-camera 2D Gaussians; entries with ``valid == False`` are meaningless.

    Attributes:
        means2d: Tensor  # [C, N, 2] pixel coordinates (x right, y down)
        conics: Tensor  # [C, N, 3] inverse 2D covariance (a, b, c) = [[a, b], [b, c]]
        depths: Tensor  # [C, N] camera-frame z (metres, +z forward)
        radii: Tensor  # [C, N, 2] int32 half extents (x, y) in pixels; 0 when culled
        valid: Tensor  # [C, N] bool, True where the Gaussian may touch the image
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    valid: Tensor


def covariance_factor(quats: Tensor, scales: Tensor) -> Tensor:
    """Factor ``M = R(q) diag(s)`` of the world covariance ``Sigma = M M^T``.

    Args:
        quats: Tensor  # [N, 4] wxyz, any norm
        scales: Tensor  # [N, 3] standard deviations along the local axes (metres)

    Returns:
        Tensor  # [N, 3, 3] world_from_local scaled axes
    """
    return quat_to_matrix(quats) * scales[..., None, :]


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> ProjectedGaussians:
    """Project 3D Gaussians into every camera (EWA splatting, pinhole model).

    Args:
        means: Tensor  # [N, 3] world-frame centres (metres)
        quats: Tensor  # [N, 4] wxyz orientation, any norm
        scales: Tensor  # [N, 3] activated standard deviations (metres)
        opacities: Tensor  # [N] in [0, 1]; only used for the bounding radius and culling
        viewmats: Tensor  # [C, 4, 4] cam_from_world, OpenCV axes
        Ks: Tensor  # [C, 3, 3] pinhole intrinsics (skew ignored, as in gsplat)
        width, height: image size in pixels
        near_plane, far_plane: camera-frame z range kept (metres)
        eps2d: low-pass dilation added to the 2D covariance diagonal (px^2)

    Returns:
        ProjectedGaussians with [C, N, ...] tensors. Invalid entries hold finite
        placeholder values whose gradients are exactly zero.
    """
    rot_cw = viewmats[:, None, :3, :3]  # [C, 1, 3, 3] cam_from_world rotation
    t_cw = viewmats[:, None, :3, 3]  # [C, 1, 3]
    means_cam = (rot_cw @ means[None, :, :, None]).squeeze(-1) + t_cw  # [C, N, 3]
    x, y, z = means_cam.unbind(-1)

    in_depth = (z >= near_plane) & (z <= far_plane)
    # Behind-camera entries would divide by ~0; give them a harmless depth so
    # neither the values nor the (masked) gradients become NaN/Inf.
    z_safe = torch.where(in_depth, z, torch.ones_like(z))
    rz = 1.0 / z_safe

    fx = Ks[:, 0, 0, None]  # [C, 1]
    fy = Ks[:, 1, 1, None]
    cx = Ks[:, 0, 2, None]
    cy = Ks[:, 1, 2, None]

    # gsplat clamps the view direction used by the Jacobian to 1.3x the FOV so
    # that off-screen Gaussians do not get absurdly stretched footprints.
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.minimum(torch.maximum(x * rz, -lim_x_neg), lim_x_pos)
    ty = z_safe * torch.minimum(torch.maximum(y * rz, -lim_y_neg), lim_y_pos)

    zeros = torch.zeros_like(z_safe)
    jac = torch.stack([fx * rz, zeros, -fx * tx * rz * rz, zeros, fy * rz, -fy * ty * rz * rz], dim=-1).reshape(
        z.shape + (2, 3)
    )  # [C, N, 2, 3] d(pixel)/d(cam point)

    # cov2d = T T^T with T = J R_cw M; keeping the 2x3 factor lets us take the
    # determinant by Cauchy-Binet (a sum of squares), which stays >= 0 and
    # accurate for needle-like or huge Gaussians where a*c - b^2 cancels badly.
    factor = covariance_factor(quats, scales)  # [N, 3, 3]
    tmat = jac @ rot_cw @ factor[None]  # [C, N, 2, 3]
    # det below is quartic in tmat: cap each footprint's pixel-space extent at
    # finfo.max^(1/5) (float32: 5e7 px, float64: 1e61 px) so it cannot overflow.
    # Without the cap, huge Gaussians (float32: std > ~1e9 px) got det = inf, were
    # culled, and their zero upstream gradient met inf partials (0 * inf = NaN).
    # Capped footprints still cover any image uniformly (conic ~ 1e-15), and the
    # detached factor is exactly 1 for every Gaussian below the cap.
    extent_cap = torch.finfo(tmat.dtype).max ** 0.2
    with torch.no_grad():
        peak_px = tmat.abs().amax(dim=(-2, -1), keepdim=True)
        shrink = extent_cap / peak_px.clamp_min(extent_cap)
    tmat = tmat * shrink
    r0, r1 = tmat[..., 0, :], tmat[..., 1, :]
    cov_a = (r0 * r0).sum(-1)
    cov_b = (r0 * r1).sum(-1)
    cov_c = (r1 * r1).sum(-1)
    minors = torch.stack(
        [
            r0[..., 0] * r1[..., 1] - r0[..., 1] * r1[..., 0],
            r0[..., 0] * r1[..., 2] - r0[..., 2] * r1[..., 0],
            r0[..., 1] * r1[..., 2] - r0[..., 2] * r1[..., 1],
        ],
        dim=-1,
    )
    det_orig = (minors * minors).sum(-1)
    cov_a = cov_a + eps2d
    cov_c = cov_c + eps2d
    # det(cov + eps I) = det(cov) + eps tr(cov) + eps^2 >= eps^2 > 0 analytically
    # (0.09 by default). With eps2d ~ 0 a needle or flat footprint is (nearly)
    # singular: gsplat's CUDA kernel inverts det as is and culls det <= 0. A floor
    # (gsplat's torch reference clamps at 1e-10) would blow a sub-pixel footprint up
    # into a blob tens of pixels wide. Instead cull where d(conic)/d(det), at most
    # max(a, c) / det^2, exceeds sqrt(finfo.max) (float32: footprints below ~1e-4 px
    # std), so that neither the conic nor its gradient can overflow; culled entries
    # get a finite placeholder with zero gradient. Never triggers for eps2d >= ~1e-4.
    det = det_orig + eps2d * (cov_a + cov_c - eps2d)
    with torch.no_grad():
        invertible = (det > 0) & ((torch.maximum(cov_a, cov_c) / det) / det < torch.finfo(det.dtype).max ** 0.5)
    det = torch.where(invertible, det, torch.ones_like(det))
    conics = torch.stack([cov_c / det, -cov_b / det, cov_a / det], dim=-1)

    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)  # [C, N, 2]

    with torch.no_grad():
        opac = opacities.detach()[None].expand_as(z)
        # Opacity-aware extent: the ellipse where opacity*exp(-sigma) >= 1/255
        # (gsplat, arXiv:2402.00525 B.2). Any pixel outside the resulting box
        # would be skipped by the alpha threshold anyway, so tiling is lossless.
        extend = torch.sqrt(2.0 * torch.log((opac / ALPHA_THRESHOLD).clamp_min(1.0)))
        extend = extend.clamp_max(MAX_EXTEND)
        rad_x = torch.ceil(extend * torch.sqrt(cov_a.detach()))
        rad_y = torch.ceil(extend * torch.sqrt(cov_c.detach()))
        mx, my = means2d.detach().unbind(-1)
        valid = (
            in_depth
            & (opac >= ALPHA_THRESHOLD)
            & ((rad_x > 0) | (rad_y > 0))
            & invertible
            & torch.isfinite(det)
            & (mx + rad_x > 0)
            & (mx - rad_x < width)
            & (my + rad_y > 0)
            & (my - rad_y < height)
        )
        # Clamp before the int cast: huge Gaussians would overflow int32.
        big = float(4 * max(width, height) + 1)
        radii = torch.stack([rad_x, rad_y], dim=-1).clamp(0.0, big)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii)).int()

    depths = torch.where(in_depth, z, zeros)
    return ProjectedGaussians(means2d, conics, depths, radii, valid)


def camera_centers(viewmats: Tensor) -> Tensor:
    """World-frame camera centres.

    Args:
        viewmats: Tensor  # [C, 4, 4] cam_from_world (rigid)

    Returns:
        Tensor  # [C, 3] position of each camera in the world frame
    """
    rot_cw = viewmats[:, :3, :3]
    t_cw = viewmats[:, :3, 3]
    # world_from_cam translation = -R^T t for a rigid transform.
    return -(rot_cw.transpose(-1, -2) @ t_cw[..., None]).squeeze(-1)
