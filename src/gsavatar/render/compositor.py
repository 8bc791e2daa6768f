"""Tiled, differentiable front-to-back alpha compositing of 2D Gaussians (CPU-friendly).

Rules are gsplat 1.5.3's (``RasterizeToPixels3DGSFwd.cu``), per pixel centre p:

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,   dx = mean - p,  conic = (a, b, c)
    skip if sigma < 0;  alpha = min(0.999, opacity exp(-sigma));  skip if alpha < 1/255
    next_T = T (1 - alpha); stop (this Gaussian excluded) once next_T <= 1e-4
    color = sum_i c_i alpha_i T_i,   alpha_out = 1 - T_final

Algorithm (see docs/render.md for the rationale):

1. *Binning* (no grad): every visible (camera, Gaussian) instance is sorted by
   depth, then listed in every tile its pixel bounding box touches; a stable sort
   by tile id gives per-tile, depth-ordered lists (gsplat's isect + radix sort).
2. *Candidates* (no grad, chunked): each pixel of a tile is paired with every
   instance of its tile's list, laid out pixel-major so each pixel's list is a
   contiguous, depth-ordered segment (a ragged version of a per-tile
   [pixels, K] matrix, no padding). Alphas, the 1/255 skip and the transmittance
   (segmented exclusive cumsum of log(1 - alpha), float64) are evaluated for all
   candidates; the early stop is a mask on that cumsum. Only *contributing*
   pairs survive, which for opaque surfaces is a small fraction.
3. *Backward* (custom autograd): recomputes alpha/T for the contributing pairs
   only and applies gsplat's analytic VJP, scattering into per-instance grads.

Memory is bounded by ``max_candidates`` per chunk (chunks are runs of whole
tiles) plus the saved contributing pair indices (two int64 per pair).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from .projection import ALPHA_THRESHOLD

MAX_ALPHA = 0.999
TRANSMITTANCE_MIN = 1e-4
_LOG_T_MIN = math.log(TRANSMITTANCE_MIN)


class TileBins(NamedTuple):
    """Depth-ordered instance lists per touched tile (all integer tensors).

    Attributes:
        tile_ids: Tensor  # [A] global tile id (camera-major, then row, column) of each touched tile
        list_offsets: Tensor  # [A] start of each tile's list in ``instance_lists``
        list_counts: Tensor  # [A] K_t, number of instances touching the tile
        instance_lists: Tensor  # [Q] instance indices, grouped by tile, front to back
    """

    tile_ids: Tensor
    list_offsets: Tensor
    list_counts: Tensor
    instance_lists: Tensor


class CompositeStats(NamedTuple):
    """Work counters of one compositing call (python ints, for logs/benchmarks)."""

    n_tile_pairs: int
    n_candidates: int
    n_contributing: int
    n_chunks: int


def bin_to_tiles(
    means2d: Tensor,
    radii: Tensor,
    camera_ids: Tensor,
    width: int,
    height: int,
    tile_size: int,
) -> TileBins:
    """Assign depth-sorted instances to the tiles covered by their pixel bounding boxes.

    Args:
        means2d: Tensor  # [V, 2] pixel coordinates of instances already sorted front to back
        radii: Tensor  # [V, 2] integer half extents in pixels (x, y)
        camera_ids: Tensor  # [V] int64 camera index of each instance
        width, height: image size in pixels
        tile_size: tile edge in pixels

    Returns:
        TileBins; instance order inside each tile list follows the input order.
    """
    device = means2d.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    mx, my = means2d.detach().unbind(-1)
    rx, ry = radii.to(means2d.dtype).unbind(-1)
    # A pixel column j is inside the box iff |j + 0.5 - mx| <= rx. Clamping in
    # float first keeps far off-screen coordinates from overflowing int64.
    x_lo = torch.ceil((mx - rx - 0.5).clamp(-1.0, width)).long().clamp_min(0)
    x_hi = torch.floor((mx + rx - 0.5).clamp(-1.0, width)).long().clamp_max(width - 1)
    y_lo = torch.ceil((my - ry - 0.5).clamp(-1.0, height)).long().clamp_min(0)
    y_hi = torch.floor((my + ry - 0.5).clamp(-1.0, height)).long().clamp_max(height - 1)
    nonempty = (x_hi >= x_lo) & (y_hi >= y_lo)
    tx_lo = torch.div(x_lo, tile_size, rounding_mode="floor")
    ty_lo = torch.div(y_lo, tile_size, rounding_mode="floor")
    ntx = torch.div(x_hi, tile_size, rounding_mode="floor") - tx_lo + 1
    nty = torch.div(y_hi, tile_size, rounding_mode="floor") - ty_lo + 1
    counts = torch.where(nonempty, ntx * nty, torch.zeros_like(ntx))

    n_inst = means2d.shape[0]
    inst = torch.repeat_interleave(torch.arange(n_inst, device=device), counts)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(inst.shape[0], device=device) - starts[inst]
    ntx_i = ntx[inst]
    ty = ty_lo[inst] + torch.div(local, ntx_i, rounding_mode="floor")
    tx = tx_lo[inst] + local % ntx_i
    tile = (camera_ids[inst] * tiles_y + ty) * tiles_x + tx
    # Stable sort keeps the front-to-back instance order inside each tile.
    tile_sorted, perm = torch.sort(tile, stable=True)
    tile_ids, list_counts = torch.unique_consecutive(tile_sorted, return_counts=True)
    list_offsets = torch.cumsum(list_counts, 0) - list_counts
    return TileBins(tile_ids, list_offsets, list_counts, inst[perm])


def _chunk_bounds(cost: Tensor, budget: int) -> list[tuple[int, int]]:
    """Split a run of tiles into consecutive ranges of at most ``budget`` cost
    (a single tile above budget gets its own range)."""
    n = int(cost.shape[0])
    if n == 0:
        return []
    csum = torch.cumsum(cost, 0)
    total = int(csum[-1])
    if total <= budget:
        return [(0, n)]
    bounds = []
    start = 0
    base = 0
    csum_list = csum.tolist()
    while start < n:
        # Largest end with cumulative cost - base <= budget, at least one tile.
        end = int(torch.searchsorted(csum, base + budget, right=True))
        end = max(end, start + 1)
        bounds.append((start, end))
        base = csum_list[end - 1]
        start = end
    return bounds


def _tile_pixels(
    tile_ids: Tensor, width: int, height: int, tile_size: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Enumerate the in-image pixels of tiles, row-major inside each tile.

    Returns:
        pix_tile: Tensor  # [P] index (into ``tile_ids``) of each pixel's tile
        pix_global: Tensor  # [P] global pixel id  camera * H * W + row * W + col
        pix_center: Tensor  # [2, P] float pixel centre (x + 0.5, y + 0.5)
        tile_npix: Tensor  # [T] pixels per tile (border tiles are clipped)
    """
    device = tile_ids.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    cam = torch.div(tile_ids, tiles_x * tiles_y, rounding_mode="floor")
    rem = tile_ids - cam * (tiles_x * tiles_y)
    x0 = (rem % tiles_x) * tile_size
    y0 = torch.div(rem, tiles_x, rounding_mode="floor") * tile_size
    tw = (width - x0).clamp_max(tile_size)
    th = (height - y0).clamp_max(tile_size)
    tile_npix = tw * th
    pix_tile = torch.repeat_interleave(torch.arange(tile_ids.shape[0], device=device), tile_npix)
    local = torch.arange(pix_tile.shape[0], device=device) - (torch.cumsum(tile_npix, 0) - tile_npix)[pix_tile]
    tw_p = tw[pix_tile]
    px = x0[pix_tile] + local % tw_p
    py = y0[pix_tile] + torch.div(local, tw_p, rounding_mode="floor")
    pix_global = (cam[pix_tile] * height + py) * width + px
    pix_center = torch.stack([px, py]) + 0.5
    return pix_tile, pix_global, pix_center, tile_npix


def _gaussian_alpha(params: Tensor, center: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """gsplat's per-pair Gaussian falloff.

    Args:
        params: Tensor  # [6, M] rows (mean_x, mean_y, conic_a, conic_b, conic_c, opacity)
        center: Tensor  # [2, M] pixel centres (x, y)

    Returns:
        alpha: Tensor  # [M] min(0.999, opacity exp(-sigma))
        sigma: Tensor  # [M]
        vis: Tensor  # [M] exp(-sigma)
        delta: Tensor  # [2, M] mean - pixel centre
    """
    delta = params[:2] - center
    dx, dy = delta[0], delta[1]
    sigma = 0.5 * (params[2] * dx * dx + params[4] * dy * dy) + params[3] * dx * dy
    vis = torch.exp(-sigma)
    alpha = (params[5] * vis).clamp_max(MAX_ALPHA)
    return alpha, sigma, vis, delta


def _segment_starts(seg_ids: Tensor) -> Tensor:
    """Index of the first element of each element's run in a sorted id array.

    Args:
        seg_ids: Tensor  # [M] non-decreasing segment ids

    Returns:
        Tensor  # [M] int64 position of the segment start for each element
    """
    m = seg_ids.shape[0]
    pos = torch.arange(m, device=seg_ids.device)
    is_start = torch.ones(m, dtype=torch.bool, device=seg_ids.device)
    is_start[1:] = seg_ids[1:] != seg_ids[:-1]
    return torch.cummax(torch.where(is_start, pos, torch.zeros_like(pos)), 0).values


def _composite_chunk_forward(
    params_t: Tensor,
    bins: TileBins,
    tiles: tuple[int, int],
    width: int,
    height: int,
    tile_size: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, int]:
    """Evaluate all candidates of a run of tiles and keep the contributing pairs.

    Args:
        params_t: Tensor  # [6, V] (mean_x, mean_y, conic a, b, c, opacity) per instance
        bins: tile lists; ``tiles`` = (start, end) range into them

    Returns:
        inst: Tensor  # [Mc] instance of each contributing pair, pixels grouped, front to back
        pix: Tensor  # [Mc] global pixel id of each contributing pair
        weight: Tensor  # [Mc] alpha_i T_i (params dtype)
        log_t: Tensor  # [Mc] log(1 - alpha_i) (float64), summed per pixel for T_final
        n_candidates: int
    """
    a, b = tiles
    tile_ids = bins.tile_ids[a:b]
    counts = bins.list_counts[a:b]
    offsets = bins.list_offsets[a:b]
    pix_tile, pix_global, pix_center, _ = _tile_pixels(tile_ids, width, height, tile_size)
    pix_k = counts[pix_tile]  # [P] list length of each pixel
    cand_start = torch.cumsum(pix_k, 0) - pix_k  # [P] start of each pixel's segment
    cand_pix = torch.repeat_interleave(torch.arange(pix_k.shape[0], device=pix_k.device), pix_k)
    m = cand_pix.shape[0]
    # Position in the tile list = candidate index - segment start + list offset.
    shift = (offsets[pix_tile] - cand_start)[cand_pix]
    inst = bins.instance_lists[torch.arange(m, device=pix_k.device) + shift]

    alpha, sigma, _, _ = _gaussian_alpha(
        params_t.index_select(1, inst), pix_center.to(params_t.dtype).index_select(1, cand_pix)
    )
    keep = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    # log-space transmittance in float64: a global cumsum minus the value at
    # each pixel's segment start is a segmented cumsum without Python loops.
    log1m = torch.where(keep, torch.log1p(-alpha.double()), torch.zeros((), dtype=torch.float64))
    csum = torch.cumsum(log1m, 0)
    seg_first = cand_start[cand_pix]
    log_t_incl = csum - (csum[seg_first] - log1m[seg_first])
    # next_T <= 1e-4 stops the pixel; T only decreases, so the mask is a prefix.
    keep &= log_t_incl > _LOG_T_MIN
    idx = keep.nonzero().squeeze(1)
    log_t_c = log1m[idx]
    weight = alpha[idx] * torch.exp(log_t_incl[idx] - log_t_c).to(alpha.dtype)
    return inst[idx], pix_global[cand_pix[idx]], weight, log_t_c, m


class _Composite(torch.autograd.Function):
    """Autograd wrapper: forward keeps only contributing pairs, backward is analytic."""

    @staticmethod
    def forward(ctx, params_t, colors, bins, width, height, n_cameras, tile_size, max_candidates, stats_out):
        n_pix = n_cameras * height * width
        dtype, device = params_t.dtype, params_t.device
        out_color = torch.zeros(n_pix, colors.shape[1], dtype=dtype, device=device)
        log_t_final = torch.zeros(n_pix, dtype=torch.float64, device=device)
        npix_tile = torch.full_like(bins.list_counts, tile_size * tile_size)
        chunks = _chunk_bounds(bins.list_counts * npix_tile, max_candidates)
        saved_inst, saved_pix, chunk_sizes = [], [], []
        n_cand = 0
        for chunk in chunks:
            inst, pix, weight, log1m, m = _composite_chunk_forward(
                params_t, bins, chunk, width, height, tile_size
            )
            n_cand += m
            out_color.index_add_(0, pix, weight[:, None] * colors.index_select(0, inst))
            log_t_final.index_add_(0, pix, log1m)
            saved_inst.append(inst)
            saved_pix.append(pix)
            chunk_sizes.append(int(inst.shape[0]))
        t_final = torch.exp(log_t_final)
        inst = torch.cat(saved_inst) if saved_inst else torch.zeros(0, dtype=torch.long, device=device)
        pix = torch.cat(saved_pix) if saved_pix else torch.zeros(0, dtype=torch.long, device=device)
        ctx.save_for_backward(params_t, colors, inst, pix, t_final)
        # Forward chunks hold whole pixels and are bounded, so backward reuses them.
        ctx.chunk_sizes = chunk_sizes
        ctx.width, ctx.height = width, height
        if stats_out is not None:
            stats_out.append(CompositeStats(int(bins.instance_lists.shape[0]), n_cand, int(inst.shape[0]), len(chunks)))
        alpha_out = (1.0 - t_final).to(dtype)
        return out_color, alpha_out

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        params_t, colors, inst_all, pix_all, t_final = ctx.saved_tensors
        n_inst, n_ch = colors.shape
        grads = torch.zeros(n_inst, 6 + n_ch, dtype=torch.float64, device=colors.device)
        if g_color is None:
            g_color = torch.zeros(t_final.shape[0], n_ch, dtype=colors.dtype, device=colors.device)
        g_color = g_color.contiguous()
        # The alpha-output term of dL/dalpha_i is g_A * T_final / (1 - alpha_i).
        g_final = (g_alpha.double() * t_final) if g_alpha is not None else torch.zeros_like(t_final)
        start = 0
        for size in ctx.chunk_sizes:
            end = start + size
            grads.index_add_(0, inst_all[start:end], _backward_pairs(
                params_t, colors, inst_all[start:end], pix_all[start:end], g_color, g_final,
                ctx.width, ctx.height,
            ))
            start = end
        g_params = grads[:, :6].t().to(params_t.dtype)
        g_colors = grads[:, 6:].to(colors.dtype)
        return g_params, g_colors, None, None, None, None, None, None, None


def _backward_pairs(params_t, colors, inst, pix, g_color, g_final, width, height) -> Tensor:
    """gsplat's compositing VJP for a run of whole pixel segments.

    Args:
        params_t: Tensor  # [6, V]; colors: Tensor  # [V, D]
        inst, pix: Tensor  # [Mc] contributing pairs (pixel-grouped, front to back)
        g_color: Tensor  # [P, D] dL/d(accumulated colour)
        g_final: Tensor  # [P] float64 dL/dA * T_final

    Returns:
        Tensor  # [Mc, 6 + D] float64 per-pair grads of (mean2d, conic, opacity, colour)
    """
    pix_center = _pixel_centers(pix, width, height)
    p = params_t.index_select(1, inst)
    alpha, _, vis, delta = _gaussian_alpha(p, pix_center.to(p.dtype))
    alpha = alpha.double()
    log1m = torch.log1p(-alpha)
    first = _segment_starts(pix)
    csum = torch.cumsum(log1m, 0)
    excl = csum - log1m
    trans = torch.exp(excl - excl[first])  # T_i before pair i
    weight = alpha * trans
    g_c = g_color.index_select(0, pix)  # [Mc, D]
    c = colors.index_select(0, inst)
    gdotc = (c * g_c).sum(-1).double()
    v = weight * gdotc
    vsum = torch.cumsum(v, 0)
    seg_total = torch.zeros(g_color.shape[0], dtype=torch.float64, device=v.device).index_add_(0, pix, v)
    # Exclusive suffix sum within the pixel: what later Gaussians add.
    suffix = seg_total[pix] - (vsum - (vsum[first] - v[first]))
    g_alpha = trans * gdotc + (g_final[pix] - suffix) / (1.0 - alpha)
    # min(0.999, o * vis) has no gradient where it clamps (gsplat: o*vis <= 0.999).
    unclamped = (p[5] * vis <= MAX_ALPHA).double()
    g_alpha = g_alpha * unclamped
    g_sigma = -g_alpha * alpha
    dx, dy = delta[0].double(), delta[1].double()
    a, b, cc = p[2].double(), p[3].double(), p[4].double()
    return torch.cat(
        [
            torch.stack(
                [
                    g_sigma * (a * dx + b * dy),
                    g_sigma * (b * dx + cc * dy),
                    g_sigma * 0.5 * dx * dx,
                    g_sigma * dx * dy,
                    g_sigma * 0.5 * dy * dy,
                    g_alpha * vis.double(),
                ],
                dim=1,
            ),
            weight[:, None] * g_c.double(),
        ],
        dim=1,
    )


def _pixel_centers(pix: Tensor, width: int, height: int) -> Tensor:
    """Pixel centres of global pixel ids.

    Args:
        pix: Tensor  # [M] camera * H * W + row * W + col

    Returns:
        Tensor  # [2, M] float64 (col + 0.5, row + 0.5)
    """
    col = pix % width
    row = torch.div(pix, width, rounding_mode="floor") % height
    return torch.stack([col, row]).double() + 0.5


def composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    camera_ids: Tensor,
    n_cameras: int,
    width: int,
    height: int,
    tile_size: int = 8,
    max_candidates: int = 1 << 21,
    stats_out: list | None = None,
) -> tuple[Tensor, Tensor]:
    """Alpha-composite projected Gaussian instances into C images (differentiable).

    Args:
        means2d: Tensor  # [V, 2] pixel coordinates of each (camera, Gaussian) instance
        conics: Tensor  # [V, 3] inverse 2D covariance (a, b, c)
        opacities: Tensor  # [V] in [0, 1]
        colors: Tensor  # [V, D] per-instance features (RGB, depth, ...)
        depths: Tensor  # [V] camera-frame z used for front-to-back ordering
        radii: Tensor  # [V, 2] int half extents of the footprint in pixels
        camera_ids: Tensor  # [V] int64 image each instance belongs to
        n_cameras: number of images C
        width, height: image size in pixels
        tile_size: tile edge in pixels (8 is a good CPU trade-off, see docs)
        max_candidates: bound on (pixel, Gaussian) candidates evaluated at once
        stats_out: if a list is given, a CompositeStats is appended to it

    Returns:
        colors: Tensor  # [C, H, W, D] premultiplied accumulated features
        alphas: Tensor  # [C, H, W, 1] 1 - final transmittance
    """
    n_ch = colors.shape[-1]
    with torch.no_grad():
        order = torch.argsort(depths.detach(), stable=True)
    means2d, conics, opacities = means2d[order], conics[order], opacities[order]
    colors, radii, camera_ids = colors[order], radii[order], camera_ids[order]
    with torch.no_grad():
        bins = bin_to_tiles(means2d, radii, camera_ids, width, height, tile_size)
    params_t = torch.cat([means2d, conics, opacities[:, None]], dim=1).t().contiguous()
    out_color, out_alpha = _Composite.apply(
        params_t, colors.contiguous(), bins, width, height, n_cameras, tile_size, max_candidates, stats_out
    )
    return (
        out_color.reshape(n_cameras, height, width, n_ch),
        out_alpha.reshape(n_cameras, height, width, 1),
    )
