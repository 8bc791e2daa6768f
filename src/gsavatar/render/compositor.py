"""Tiled, differentiable front-to-back alpha compositing of 2D Gaussians (CPU-friendly).

Rules are gsplat 1.5.3's (``RasterizeToPixels3DGSFwd.cu``), per pixel centre p:

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,   dx = mean - p,  conic = (a, b, c)
    alpha = min(0.999, opacity exp(-sigma));  skip if alpha < 1/255
    next_T = T (1 - alpha); stop (this Gaussian excluded) once next_T <= 1e-4
    color = sum_i c_i alpha_i T_i,   alpha_out = 1 - T_final

Algorithm (see docs/render.md for the rationale):

1. *Binning* (no grad): visible (camera, Gaussian) instances, sorted by depth,
   are listed in every tile their pixel bounding box touches; a stable sort by
   tile id gives front-to-back lists per tile (gsplat's isect + radix sort).
2. *Forward* (no grad): tiles with similar list lengths K are batched, padded
   to a common K, and evaluated as dense [tiles, pixels, K] blocks: sigma is one
   batched matmul of a per-pixel quadratic basis with per-Gaussian coefficients,
   transmittance is a cumprod over K (the same sequential product gsplat does),
   the 1e-4 early stop is a threshold on it, and the colours (plus a constant-1
   channel giving alpha) are one more batched matmul.
3. *Backward* (custom autograd.Function): re-evaluates each batch and applies
   gsplat's analytic VJP with dense ops (suffix sums by cumsum, matmuls for the
   reductions over pixels), then scatters per tile-list entry into instances.

Peak memory is a few [max_candidates] buffers per batch plus O(tile-list
entries) saved for backward; nothing per (pixel, Gaussian) pair is kept.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from . import compositor_numba
from .projection import ALPHA_THRESHOLD

MAX_ALPHA = 0.999
TRANSMITTANCE_MIN = 1e-4


class TileBins(NamedTuple):
    """Depth-ordered instance lists per touched tile (all int64 tensors).

    Attributes:
        tile_ids: Tensor  # [A] global tile id (camera-major, then tile row, column)
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

    n_tile_pairs: int  # (tile, instance) intersections
    n_candidates: int  # (pixel, instance) entries evaluated in the forward (dense: padded; numba: walked)
    n_contributing: int  # pairs that passed the 1/255 and T thresholds
    n_batches: int  # tile batches (Python loop iterations) in the forward


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
    # Pixel column j is inside the box iff |j + 0.5 - mx| <= rx. Clamping in
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

    inst = torch.repeat_interleave(torch.arange(means2d.shape[0], device=device), counts)
    local = torch.arange(inst.shape[0], device=device) - (torch.cumsum(counts, 0) - counts).index_select(0, inst)
    ntx_i = ntx.index_select(0, inst)
    row = torch.div(local, ntx_i, rounding_mode="floor")
    tx = tx_lo.index_select(0, inst) + local - row * ntx_i
    ty = ty_lo.index_select(0, inst) + row
    tile = (camera_ids.index_select(0, inst) * tiles_y + ty) * tiles_x + tx
    if (int(camera_ids.max()) + 1 if camera_ids.numel() else 0) * tiles_y * tiles_x < 2**31:
        tile = tile.int()  # int32 keys sort ~2x faster
    # Stable sort keeps the front-to-back instance order inside each tile.
    tile_sorted, perm = torch.sort(tile, stable=True)
    tile_ids, list_counts = torch.unique_consecutive(tile_sorted, return_counts=True)
    list_offsets = torch.cumsum(list_counts, 0) - list_counts
    return TileBins(tile_ids.long(), list_offsets, list_counts, inst.index_select(0, perm))


def _tile_batches(
    bins: TileBins, tile_area: int, max_candidates: int, max_padding: float = 0.1, min_batch: int = 1 << 16
) -> list[tuple[Tensor, int]]:
    """Group tiles with similar list lengths into dense batches of bounded size.

    Tiles are visited by increasing list length K and cut into runs; a run's
    padded size is n_tiles * tile_area * max K. A run is closed when adding the
    next length would exceed ``max_candidates`` or waste more than
    ``max_padding`` on padding (small runs may waste more: Python overhead per
    batch costs more than padding a few thousand entries).

    Returns:
        list of (tile indices [nb] into ``bins``, padded K) pairs
    """
    counts, order = torch.sort(bins.list_counts)
    lengths, n_tiles = torch.unique_consecutive(counts, return_counts=True)
    batches: list[tuple[Tensor, int]] = []
    start = n_open = real_open = k_open = 0  # open run: order[start : start + n_open]
    for k, n in zip(lengths.tolist(), n_tiles.tolist()):
        cap = max(1, max_candidates // (tile_area * k))  # tiles per batch at this K
        while n > 0:
            take = min(n, cap - n_open)
            padded = (n_open + take) * k
            wasteful = padded > (1.0 + max_padding) * (real_open + take * k) and padded * tile_area > min_batch
            if n_open and (take <= 0 or wasteful):
                batches.append((order[start : start + n_open], k_open))
                start, n_open, real_open = start + n_open, 0, 0
                continue
            n_open, real_open, k_open, n = n_open + take, real_open + take * k, k, n - take
            if n_open >= cap:
                batches.append((order[start : start + n_open], k_open))
                start, n_open, real_open = start + n_open, 0, 0
    if n_open:
        batches.append((order[start : start + n_open], k_open))
    return batches


def _tile_geometry(
    tile_ids: Tensor, width: int, height: int, tile_size: int, junk: int, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """Tile centres and global ids of their pixels (row-major inside the tile).

    Returns:
        centers: Tensor  # [nb, 2] tile centre (x, y) in pixels
        pix_ids: Tensor  # [nb, P] camera * H * W + row * W + col; ``junk`` outside the image
    """
    device = tile_ids.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    cam = torch.div(tile_ids, tiles_x * tiles_y, rounding_mode="floor")
    rem = tile_ids - cam * (tiles_x * tiles_y)
    x0 = (rem % tiles_x) * tile_size
    y0 = torch.div(rem, tiles_x, rounding_mode="floor") * tile_size
    offs = torch.arange(tile_size, device=device)
    col = x0[:, None, None] + offs[None, None, :]  # [nb, 1, ts]
    row = y0[:, None, None] + offs[None, :, None]  # [nb, ts, 1]
    pix = (cam[:, None, None] * height + row) * width + col
    inside = (col < width) & (row < height)
    pix_ids = torch.where(inside, pix, torch.full_like(pix, junk)).reshape(tile_ids.shape[0], -1)
    centers = torch.stack([x0, y0], dim=1).to(dtype) + 0.5 * tile_size
    return centers, pix_ids


def _pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Quadratic basis (1, u, v, u^2, uv, v^2) of pixel centres relative to the tile centre.

    Returns:
        Tensor  # [P, 6], P = tile_size^2, row-major pixel order
    """
    offs = torch.arange(tile_size, device=device, dtype=dtype) + 0.5 - 0.5 * tile_size
    v, u = torch.meshgrid(offs, offs, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v], dim=1)


class _Batch(NamedTuple):
    """Dense evaluation of one tile batch; K = padded list length, P = pixels per tile."""

    pos: Tensor  # [nb * K] index into the tile-list order (padding -> 0)
    in_list: Tensor  # [nb, K] bool, False on padding
    pix_ids: Tensor  # [nb * P] global pixel ids (``junk`` outside the image)
    local: Tensor  # [6, nb, K] (dx, dy, a, b, c, opacity): mean - tile centre, conic, opacity
    alpha: Tensor  # [nb, P, K] min(0.999, o exp(-sigma)), 0 below 1/255
    one_minus: Tensor  # [nb, P, K] 1 - alpha
    trans: Tensor  # [nb, P, K] T in front of each entry, 0 from the early stop on
    weight: Tensor  # [nb, P, K] alpha T, 0 where skipped, stopped or outside the image


def _float_below(value: float, dtype: torch.dtype) -> float:
    """Largest ``dtype`` number below ``value`` (turns ``x >= v`` into ``x > v'``)."""
    v = torch.tensor(value, dtype=dtype)
    return float(torch.nextafter(v, torch.zeros_like(v)))


def _evaluate_batch(
    params_q: Tensor,
    bins: TileBins,
    tiles: Tensor,
    k_pad: int,
    basis: Tensor,
    width: int,
    height: int,
    tile_size: int,
    junk: int,
) -> _Batch:
    """Alphas, transmittance and weights of every (pixel, list entry) of a tile batch.

    Args:
        params_q: Tensor  # [Q, 6] (mean x, mean y, conic a, b, c, opacity) in tile-list order
        tiles: Tensor  # [nb] tile indices into ``bins``; k_pad >= their list lengths
        basis: Tensor  # [P, 6] from _pixel_basis
    """
    n_tiles = tiles.shape[0]
    ks = torch.arange(k_pad, device=tiles.device)
    in_list = ks[None, :] < bins.list_counts[tiles, None]  # [nb, K]
    pos = torch.where(in_list, bins.list_offsets[tiles, None] + ks[None, :], torch.zeros_like(ks[None, :]))
    pos = pos.reshape(-1)
    p = params_q.index_select(0, pos).view(n_tiles, k_pad, 6).unbind(-1)
    centers, pix_ids = _tile_geometry(bins.tile_ids[tiles], width, height, tile_size, junk, params_q.dtype)
    # sigma(u) = sigma(tile centre) - g.u + 0.5 u^T Q u is exact for the quadratic;
    # expanding around the tile centre (|u| <= ts/2) keeps cancellation small, and
    # turns the [P, K] evaluation into one batched matmul instead of ~10 passes.
    dx = p[0] - centers[:, 0, None]
    dy = p[1] - centers[:, 1, None]
    a, b, c = p[2], p[3], p[4]
    gx = a * dx + b * dy
    gy = b * dx + c * dy
    neg_coef = torch.stack([-0.5 * (gx * dx + gy * dy), gx, gy, -0.5 * a, -b, -0.5 * c], dim=1)
    opacity = torch.where(in_list, p[5], torch.zeros_like(p[5]))  # padding never contributes
    alpha = torch.matmul(basis, neg_coef).exp_().mul_(opacity[:, None, :]).clamp_max_(MAX_ALPHA)
    # threshold_ keeps x > v: with v just below 1/255 it is gsplat's "skip alpha < 1/255",
    # and it is several times faster than a masked_fill.
    torch.nn.functional.threshold_(alpha, _float_below(ALPHA_THRESHOLD, alpha.dtype), 0.0)
    one_minus = 1.0 - alpha
    trans = torch.cumprod(one_minus, dim=-1)  # gsplat's sequential next_T = T * (1 - alpha)
    # next_T <= 1e-4 stops the pixel and T only decreases: zeroing T from there on
    # removes the stopping Gaussian and everything behind it.
    torch.nn.functional.threshold_(trans, TRANSMITTANCE_MIN, 0.0)
    trans.div_(one_minus)  # inclusive -> exclusive transmittance (1 - alpha >= 0.001)
    weight = alpha * trans
    outside = (pix_ids == junk).view(n_tiles, -1, 1)
    if bool(outside.any()):
        weight.masked_fill_(outside, 0.0)
    local = torch.stack([dx, dy, a, b, c, opacity])
    return _Batch(pos, in_list, pix_ids.reshape(-1), local, alpha, one_minus, trans, weight)


def _batch_vjp(batch: _Batch, colors_q: Tensor, g_ext: Tensor, basis: Tensor) -> Tensor:
    """gsplat's compositing VJP for one evaluated batch (consumes ``batch``'s buffers).

    Args:
        colors_q: Tensor  # [Q, D + 1] features in tile-list order, last column = 1 (alpha)
        g_ext: Tensor  # [n_pix + 1, D + 1] dL/d(features, alpha) per pixel, junk row = 0
        basis: Tensor  # [P, 6]

    Returns:
        Tensor  # [nb * K, 6 + D] grads of (mean x, mean y, conic a, b, c, opacity, features)
    """
    n_tiles, n_pix, k_pad = batch.weight.shape
    col_b = colors_q.index_select(0, batch.pos).view(n_tiles, k_pad, -1)
    g_b = g_ext.index_select(0, batch.pix_ids).view(n_tiles, n_pix, -1)
    # alpha_out = sum_i w_i is just one more feature (constant 1), so the
    # alpha-output gradient rides along in g . c.
    g_dot_c = torch.bmm(g_b, col_b.transpose(1, 2))  # [nb, P, K]
    # Fused in-place passes; the batch's dense buffers dominate the runtime.
    # acc_i = -(what the Gaussians behind entry i add) = cumsum_i - total.
    acc = batch.weight * g_dot_c
    total = acc.sum(-1, keepdim=True)
    acc.cumsum_(-1).sub_(total)
    # dL/dalpha_i = T_i g.c_i - behind_i / (1 - alpha_i); zero after the stop
    # because both T_i and behind_i are zero there.
    g_alpha = acc.div_(batch.one_minus).addcmul_(batch.trans, g_dot_c)
    # d alpha / d(-sigma) = alpha, except where min(0.999, .) clamps (gsplat: no
    # gradient) or the entry was skipped (alpha = 0): threshold(-alpha) zeroes both.
    neg_alpha = torch.nn.functional.threshold_(batch.alpha.neg_(), -MAX_ALPHA, 0.0)
    g_sigma = g_alpha.mul_(neg_alpha)  # dL/dsigma = -alpha dL/dalpha
    g_coef = torch.matmul(basis.t(), g_sigma).neg_()  # [nb, 6, K] grads of neg_coef
    # g_b^T @ weight keeps the big operand untransposed (~5x faster bmm on CPU).
    g_feat = torch.bmm(g_b.transpose(1, 2), batch.weight).transpose(1, 2)[..., :-1]  # [nb, K, D]

    # Chain rule through neg_coef = (-sigma0, gx, gy, -a/2, -b, -c/2).
    dx, dy, a, b, c, opacity = batch.local
    gx = a * dx + b * dy
    gy = b * dx + c * dy
    g_s0 = -g_coef[:, 0]
    g_gx, g_gy = g_coef[:, 1], g_coef[:, 2]
    g_dx = g_s0 * gx + g_gx * a + g_gy * b
    g_dy = g_s0 * gy + g_gx * b + g_gy * c
    g_a = g_s0 * 0.5 * dx * dx + g_gx * dx - 0.5 * g_coef[:, 3]
    g_b2 = g_s0 * dx * dy + g_gx * dy + g_gy * dx - g_coef[:, 4]
    g_c = g_s0 * 0.5 * dy * dy + g_gy * dy - 0.5 * g_coef[:, 5]
    # sum_p dL/dalpha * exp(-sigma) = sum_p dL/d(-sigma) / opacity (alpha = o exp(-sigma)).
    g_opacity = g_s0.neg() / torch.where(opacity > 0, opacity, torch.ones_like(opacity))
    g_geo = torch.stack([g_dx, g_dy, g_a, g_b2, g_c, g_opacity], dim=-1)  # [nb, K, 6]
    return torch.cat([g_geo, g_feat], dim=-1).reshape(n_tiles * k_pad, -1)


class _Composite(torch.autograd.Function):
    """Batched dense forward; backward re-evaluates each batch (no per-pair storage)."""

    @staticmethod
    def forward(
        ctx, params, colors, bins, width, height, n_cameras, tile_size, max_candidates, cache_candidates, stats_out
    ):
        n_pix = n_cameras * height * width
        dtype, device = params.dtype, params.device
        # One extra "junk" row absorbs writes of tile pixels outside the image.
        out = torch.zeros(n_pix + 1, colors.shape[1] + 1, dtype=dtype, device=device)
        params_q = params.index_select(0, bins.instance_lists)
        colors_q = _with_ones(colors.index_select(0, bins.instance_lists))
        basis = _pixel_basis(tile_size, dtype, device)
        batches = _tile_batches(bins, tile_size * tile_size, max_candidates)
        n_cand = n_contrib = 0
        cache: list[_Batch | None] = []
        for tiles, k_pad in batches:
            batch = _evaluate_batch(params_q, bins, tiles, k_pad, basis, width, height, tile_size, n_pix)
            # Keep evaluated batches for backward while they fit the cache budget;
            # the rest is recomputed there, so memory stays bounded either way.
            fits = n_cand + batch.weight.numel() <= cache_candidates
            cache.append(batch if fits else None)
            col_b = colors_q.index_select(0, batch.pos).view(tiles.shape[0], k_pad, -1)
            # Every pixel belongs to exactly one tile, so plain row writes suffice.
            # col^T @ weight^T keeps the big operand on the right: ~4x faster CPU bmm.
            color = torch.bmm(col_b.transpose(1, 2), batch.weight.transpose(1, 2)).transpose(1, 2)
            out.index_copy_(0, batch.pix_ids, color.flatten(0, 1))
            n_cand += batch.weight.numel()
            n_contrib += int(batch.weight.bool().sum())  # weights are >= 0
        ctx.save_for_backward(params_q, colors_q)
        ctx.cache = cache
        ctx.setup = (bins, batches, basis, width, height, tile_size, n_pix, params.shape[0])
        if stats_out is not None:
            stats_out.append(CompositeStats(int(bins.instance_lists.shape[0]), n_cand, n_contrib, len(batches)))
        # alpha_out = sum_i alpha_i T_i = 1 - T_final (telescoping sum).
        return out[:n_pix, :-1], out[:n_pix, -1]

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        params_q, colors_q = ctx.saved_tensors
        bins, batches, basis, width, height, tile_size, n_pix, n_inst = ctx.setup
        n_q, n_ext = colors_q.shape
        g_ext = torch.zeros(n_pix + 1, n_ext, dtype=colors_q.dtype, device=colors_q.device)
        if g_color is not None:
            g_ext[:n_pix, :-1] = g_color
        if g_alpha is not None:
            g_ext[:n_pix, -1] = g_alpha
        # Per tile-list entry grads; padding entries land in the junk row n_q.
        g_q = torch.zeros(n_q + 1, 6 + n_ext - 1, dtype=colors_q.dtype, device=colors_q.device)
        cache, ctx.cache = ctx.cache, None  # cached buffers are consumed (mutated) below
        for i, (tiles, k_pad) in enumerate(batches):
            batch = (
                cache[i]
                if cache is not None and cache[i] is not None
                else _evaluate_batch(params_q, bins, tiles, k_pad, basis, width, height, tile_size, n_pix)
            )
            dest = torch.where(batch.in_list.reshape(-1), batch.pos, torch.full_like(batch.pos, n_q))
            g_q.index_copy_(0, dest, _batch_vjp(batch, colors_q, g_ext, basis))
        grads = torch.zeros(n_inst, g_q.shape[1], dtype=g_q.dtype, device=g_q.device)
        grads.index_add_(0, bins.instance_lists, g_q[:n_q])
        return grads[:, :6], grads[:, 6:], None, None, None, None, None, None, None, None


def _with_ones(features: Tensor) -> Tensor:
    """Append a constant-1 column so the accumulated alpha comes out of the same matmul.

    Args:
        features: Tensor  # [Q, D]

    Returns:
        Tensor  # [Q, D + 1]
    """
    return torch.cat([features, torch.ones_like(features[:, :1])], dim=1)


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
    tile_size: int | None = None,
    max_candidates: int = 1 << 19,
    cache_candidates: int = 1 << 24,
    stats_out: list | None = None,
    method: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Alpha-composite projected Gaussian instances into C images (differentiable).

    Args:
        means2d: Tensor  # [V, 2] pixel coordinates of each (camera, Gaussian) instance
        conics: Tensor  # [V, 3] inverse 2D covariance (a, b, c), positive definite
        opacities: Tensor  # [V] in [0, 1]
        colors: Tensor  # [V, D] per-instance features (RGB, depth, ...)
        depths: Tensor  # [V] camera-frame z, only used for front-to-back ordering
        radii: Tensor  # [V, 2] int half extents (x, y) of the footprint in pixels
        camera_ids: Tensor  # [V] int64 image each instance belongs to
        n_cameras: number of images C
        width, height: image size in pixels
        tile_size: tile edge in pixels; None = the method's own (dense: 4, the sweet spot of the
            batched matmuls, see docs/render.md; numba: 4 as well, measured per training step on CPU; gsplat uses 16)
        max_candidates: dense method: bound on padded (pixel, Gaussian) entries evaluated at once
        cache_candidates: dense method: forward batches up to this many entries in total are kept
            for backward (4 buffers of this size, 256 MB in float32 by default);
            the rest is recomputed in backward
        stats_out: if a list is given, a CompositeStats is appended to it
        method: "numba" (compiled per-pixel loops, ``compositor_numba.py``), "dense" (batched torch
            ops, this module; the oracle) or "auto" (numba when importable and the tensors are on
            the CPU, else dense)

    Returns:
        colors: Tensor  # [C, H, W, D] accumulated features (no background)
        alphas: Tensor  # [C, H, W, 1] 1 - final transmittance
    """
    if method not in ("auto", "numba", "dense"):
        raise ValueError(f"method must be 'auto', 'numba' or 'dense', got {method!r}")
    if method == "auto":
        method = "numba" if compositor_numba.available() and means2d.device.type == "cpu" else "dense"
    if method == "numba" and not compositor_numba.available():
        raise RuntimeError("method='numba' needs the numba package (pip install numba)")
    if tile_size is None:
        tile_size = compositor_numba.DEFAULT_TILE_SIZE if method == "numba" else 4
    n_ch = colors.shape[-1]
    with torch.no_grad():
        order = torch.argsort(depths.detach(), stable=True)
        bins = bin_to_tiles(
            means2d.detach().index_select(0, order),
            radii.index_select(0, order),
            camera_ids.index_select(0, order),
            width,
            height,
            tile_size,
        )
        # Lists refer to the caller's instance indices; no need to permute params.
        bins = bins._replace(instance_lists=order.index_select(0, bins.instance_lists))
    params = torch.cat([means2d, conics, opacities[:, None]], dim=1)  # [V, 6]
    if method == "numba":
        counts: list = []
        out_color, out_alpha = compositor_numba.CompositeNumba.apply(
            params.index_select(0, bins.instance_lists),
            colors.index_select(0, bins.instance_lists),
            bins.tile_ids,
            bins.list_offsets,
            bins.list_counts,
            width,
            height,
            n_cameras,
            tile_size,
            counts,
        )
        if stats_out is not None:
            pairs, walked, used = counts[0]
            stats_out.append(CompositeStats(pairs, walked, used, 1))
        return (
            out_color.reshape(n_cameras, height, width, n_ch),
            out_alpha.reshape(n_cameras, height, width, 1),
        )
    if not (torch.is_grad_enabled() and (params.requires_grad or colors.requires_grad)):
        cache_candidates = 0  # no backward will come: do not hold buffers
    out_color, out_alpha = _Composite.apply(
        params,
        colors.contiguous(),
        bins,
        width,
        height,
        n_cameras,
        tile_size,
        max_candidates,
        cache_candidates,
        stats_out,
    )
    return (
        out_color.reshape(n_cameras, height, width, n_ch),
        out_alpha.reshape(n_cameras, height, width, 1),
    )
