"""Public entry point: render 3D Gaussians into C pinhole cameras.

``backend="torch"`` is the pure-PyTorch CPU path (projection.py + compositor.py),
``backend="gsplat"`` calls ``gsplat.rasterization`` (CUDA only) and ``"auto"``
picks gsplat when the inputs live on a CUDA device.
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor

from .compositor import composite
from .projection import camera_centers, project_gaussians
from .sh import MAX_SH_DEGREE, eval_sh_colors, num_sh_bases

Backend = Literal["auto", "torch", "gsplat"]


class RenderOutput(NamedTuple):
    """Rendered images.

    Attributes:
        colors: Tensor  # [C, H, W, D] composited colours, background blended in
        alphas: Tensor  # [C, H, W, 1] accumulated opacity (1 - final transmittance)
        depths: Tensor | None  # [C, H, W, 1] expected camera-frame z (metres), if requested
        meta: dict  # backend-specific extras. torch backend: "radii" [C, N, 2] int32,
            # "valid" [C, N] bool, "camera_ids"/"gaussian_ids" [V] int64 of the
            # visible instances, "means2d" [V, 2] (retain_grad() it for densification
            # statistics), "depths" [V], "stats" CompositeStats, "backend" str.
    """

    colors: Tensor
    alphas: Tensor
    depths: Tensor | None
    meta: dict[str, Any]


def _check_shape(name: str, t: Tensor, expected: tuple[int | str, ...], pretty: str) -> None:
    if not isinstance(t, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    ok = t.dim() == len(expected) and all(isinstance(e, str) or t.shape[i] == e for i, e in enumerate(expected))
    if not ok:
        raise ValueError(f"{name} must be {pretty}, got {tuple(t.shape)}")


def _validate(
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, sh_degree
) -> tuple[int, int, int]:
    """Boundary checks with messages naming the argument; returns (N, C, D)."""
    _check_shape("means", means, ("N", 3), "[N, 3]")
    n = means.shape[0]
    _check_shape("quats", quats, (n, 4), f"[N={n}, 4] (wxyz)")
    _check_shape("scales", scales, (n, 3), f"[N={n}, 3]")
    _check_shape("opacities", opacities, (n,), f"[N={n}]")
    _check_shape("viewmats", viewmats, ("C", 4, 4), "[C, 4, 4] (cam_from_world)")
    c = viewmats.shape[0]
    _check_shape("Ks", Ks, (c, 3, 3), f"[C={c}, 3, 3]")
    if sh_degree is None:
        _check_shape("colors", colors, (n, "D"), f"[N={n}, D] (or SH [N, K, 3] with sh_degree)")
        d = colors.shape[1]
    else:
        if not 0 <= sh_degree <= MAX_SH_DEGREE:
            raise ValueError(f"sh_degree must be in [0, {MAX_SH_DEGREE}], got {sh_degree}")
        k = num_sh_bases(sh_degree)
        _check_shape("colors", colors, (n, "K", 3), f"SH coefficients [N={n}, K>={k}, 3]")
        if colors.shape[1] < k:
            raise ValueError(
                f"colors must be SH coefficients [N={n}, K>={k}, 3] for sh_degree={sh_degree}, "
                f"got {tuple(colors.shape)}"
            )
        d = 3
    if backgrounds is not None:
        _check_shape("backgrounds", backgrounds, (c, d), f"[C={c}, D={d}]")
    if int(width) <= 0 or int(height) <= 0:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    if not means.is_floating_point():
        raise ValueError(f"means must be a floating point tensor, got {means.dtype}")
    tensors = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "colors": colors,
        "viewmats": viewmats,
        "Ks": Ks,
    }
    if backgrounds is not None:
        tensors["backgrounds"] = backgrounds
    for name, t in tensors.items():
        if t.device != means.device:
            raise ValueError(f"{name} must be on {means.device} like means, got {t.device}")
        if t.dtype != means.dtype:
            raise ValueError(f"{name} must have the dtype of means ({means.dtype}), got {t.dtype}")
    return n, c, d


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor | None = None,
    *,
    sh_degree: int | None = None,
    backend: Backend = "auto",
    render_depth: bool = False,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int | None = None,
    max_candidates: int = 1 << 19,
    compositor: str = "auto",
) -> RenderOutput:
    """Render Gaussians with gsplat's classic 3DGS rules.

    Args:
        means: Tensor  # [N, 3] world-frame centres (metres)
        quats: Tensor  # [N, 4] wxyz rotations, any norm (normalised inside)
        scales: Tensor  # [N, 3] activated standard deviations (metres)
        opacities: Tensor  # [N] activated opacities in [0, 1]
        colors: Tensor  # [N, D] features, or [N, K, 3] SH coefficients when sh_degree is set
        viewmats: Tensor  # [C, 4, 4] cam_from_world, OpenCV axes (+z forward, +y down)
        Ks: Tensor  # [C, 3, 3] pinhole intrinsics in pixels
        width, height: image size in pixels
        backgrounds: Tensor | None  # [C, D] colour behind the Gaussians
        sh_degree: SH degree (0..3) to evaluate, None for plain features
        backend: "torch" (CPU-capable), "gsplat" (CUDA) or "auto"
        render_depth: also return the expected depth map
        near_plane, far_plane: camera-frame z range rendered (metres)
        eps2d: 2D low-pass dilation (px^2), gsplat's 0.3
        tile_size, max_candidates: torch backend tiling / memory knobs (None: the compositor's own tile size)
        compositor: torch backend's compositing method, "auto" / "numba" / "dense" (see ``composite``)

    Returns:
        RenderOutput with colors [C, H, W, D], alphas [C, H, W, 1], depths.
    """
    if backend not in ("auto", "torch", "gsplat"):
        raise ValueError(f"backend must be 'auto', 'torch' or 'gsplat', got {backend!r}")
    n, c, d = _validate(means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, sh_degree)
    width, height = int(width), int(height)
    if backend == "auto":
        backend = "gsplat" if means.device.type == "cuda" else "torch"
    if backend == "gsplat":
        return _rasterize_gsplat(
            means,
            quats,
            scales,
            opacities,
            colors,
            viewmats,
            Ks,
            width,
            height,
            backgrounds,
            sh_degree,
            render_depth,
            near_plane,
            far_plane,
            eps2d,
        )

    proj = project_gaussians(means, quats, scales, opacities, viewmats, Ks, width, height, near_plane, far_plane, eps2d)
    cam_ids, gs_ids = proj.valid.nonzero(as_tuple=True)  # [V], [V]
    # Flat index_select (not advanced indexing): its backward is a fast index_add.
    flat = cam_ids * n + gs_ids
    means2d = proj.means2d.reshape(-1, 2).index_select(0, flat)
    depths = proj.depths.reshape(-1).index_select(0, flat)
    if sh_degree is None:
        feats = colors.index_select(0, gs_ids)
    else:
        # View direction per instance: camera centre -> Gaussian, world frame.
        dirs = means.index_select(0, gs_ids) - camera_centers(viewmats).index_select(0, cam_ids)
        feats = eval_sh_colors(sh_degree, dirs, colors.index_select(0, gs_ids))
    if render_depth:
        feats = torch.cat([feats, depths[:, None]], dim=1)
    stats: list = []
    img, alphas = composite(
        means2d,
        proj.conics.reshape(-1, 3).index_select(0, flat),
        opacities.index_select(0, gs_ids),
        feats,
        depths,
        proj.radii.reshape(-1, 2).index_select(0, flat),
        cam_ids,
        c,
        width,
        height,
        tile_size=tile_size,
        max_candidates=max_candidates,
        stats_out=stats,
        method=compositor,
    )
    depth_img = None
    if render_depth:
        # Expected depth = accumulated z / accumulated alpha (gsplat "ED").
        depth_img = img[..., d:] / alphas.clamp_min(1e-10)
        img = img[..., :d]
    if backgrounds is not None:
        img = img + (1.0 - alphas) * backgrounds[:, None, None, :]
    meta = {
        "backend": "torch",
        "radii": proj.radii,
        "valid": proj.valid,
        "camera_ids": cam_ids,
        "gaussian_ids": gs_ids,
        "means2d": means2d,
        "depths": depths,
        "stats": stats[0],
    }
    return RenderOutput(img, alphas, depth_img, meta)


def _rasterize_gsplat(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    backgrounds,
    sh_degree,
    render_depth,
    near_plane,
    far_plane,
    eps2d,
) -> RenderOutput:
    """Delegate to gsplat's fused CUDA rasteriser (same conventions, its 16 px tiles).

    Unlike the torch path, gsplat normalises quaternions without an epsilon:
    an exactly zero quaternion yields NaN there.
    """
    if means.device.type != "cuda":
        raise ValueError(f"backend='gsplat' needs CUDA tensors, got means on {means.device}")
    from gsplat import rasterization

    img, alphas, meta = rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        backgrounds=backgrounds,
        render_mode="RGB+ED" if render_depth else "RGB",
    )
    depth_img = None
    if render_depth:
        depth_img = img[..., -1:]
        img = img[..., :-1]
    meta = dict(meta)
    meta["backend"] = "gsplat"
    return RenderOutput(img, alphas, depth_img, meta)
