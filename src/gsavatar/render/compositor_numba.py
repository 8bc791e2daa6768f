"""Per-pixel front-to-back compositing compiled with numba: the CPU fast path of :func:`composite`.

The same rules as the dense torch compositor (``compositor.py``, kept as the oracle and the fallback
when numba is missing), evaluated the way gsplat's CUDA kernels do: one loop per pixel over its tile's
depth-sorted list, stopping at the transmittance cut-off, so only (pixel, Gaussian) pairs up to the
stop are touched and nothing is padded. Tiles run in parallel (``numba.prange``) on
``torch.get_num_threads()`` threads (:func:`gsavatar.utils.compiled.set_threads`).

Backward re-walks each pixel's list once instead of storing per-pair state, applying gsplat's VJP
front to back with ``behind_i = total - prefix_i`` (the torch oracle's cumsum form), where
``total = sum_i w_i g.c_i`` is ``g . (output features, alpha)`` from the forward's float64 output.
Gradients go to per list entry rows, which belong to exactly one tile, so parallel tiles never write the
same row; torch then
adds them up per instance.

Arithmetic is float64 inside the kernels whatever the input dtype; outputs are cast back.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from gsavatar.utils.compiled import CACHE, numba, set_threads

from .projection import ALPHA_THRESHOLD

MAX_ALPHA = 0.999
TRANSMITTANCE_MIN = 1e-4
DEFAULT_TILE_SIZE = 4  # per-pixel lists of 4x4 tiles: fewer (pixel, Gaussian) pairs walked than gsplat's 16 on CPU


def available() -> bool:
    """Whether the compiled compositor can run here (numba importable)."""
    return numba is not None


if numba is not None:

    @numba.njit(cache=CACHE, inline="always")
    def _tile_origin(tid, tiles_x, tiles_y, tile_size):
        # global tile id (camera-major, then row, column) -> (camera, first column, first row)
        cam = tid // (tiles_x * tiles_y)
        rem = tid - cam * tiles_x * tiles_y
        return cam, (rem % tiles_x) * tile_size, (rem // tiles_x) * tile_size

    @numba.njit(cache=CACHE, inline="always")
    def _raw_alpha(params, skip_sigma, q, dx, dy):
        # opacity exp(-sigma) of list entry q at offset (dx, dy) = mean - pixel centre; the forward and the
        # backward walk must take the same decisions, so both use this. 0 where sigma > skip_sigma[q]: alpha
        # < 1/255 for sure, no exp (most pairs of a tile).
        sigma = 0.5 * (params[q, 2] * dx * dx + params[q, 4] * dy * dy) + params[q, 3] * dx * dy
        if sigma > skip_sigma[q]:
            return 0.0
        return params[q, 5] * math.exp(-sigma)

    @numba.njit(parallel=True, cache=CACHE, fastmath=False)
    def _forward_kernel(
        params, skip_sigma, colors, tile_ids, offsets, counts, width, height, tile_size, out, stop, counters
    ):
        # params [Q, 6] (x, y, a, b, c, opacity), colors [Q, D] in tile-list order;
        # out [n_pix, D + 1] (features, alpha), stop [n_pix] one past the last entry walked,
        # counters [n_tiles, 2]: (pixel, entry) pairs walked and pairs that contributed (stats).
        D = colors.shape[1]
        tiles_x = (width + tile_size - 1) // tile_size
        tiles_y = (height + tile_size - 1) // tile_size
        for t in numba.prange(tile_ids.shape[0]):
            cam, x0, y0 = _tile_origin(tile_ids[t], tiles_x, tiles_y, tile_size)
            start = offsets[t]
            end = start + counts[t]
            acc = np.zeros(D, np.float64)
            used = 0
            walked = 0
            for py in range(y0, min(y0 + tile_size, height)):
                for px in range(x0, min(x0 + tile_size, width)):
                    pcx = px + 0.5
                    pcy = py + 0.5
                    T = 1.0
                    acc[:] = 0.0
                    q_stop = start
                    for q in range(start, end):
                        q_stop = q + 1
                        raw = _raw_alpha(params, skip_sigma, q, params[q, 0] - pcx, params[q, 1] - pcy)
                        alpha = min(MAX_ALPHA, raw)
                        if alpha < ALPHA_THRESHOLD:
                            continue
                        next_T = T * (1.0 - alpha)
                        if next_T <= TRANSMITTANCE_MIN:
                            break
                        w = alpha * T
                        for d in range(D):
                            acc[d] += w * colors[q, d]
                        T = next_T
                        used += 1
                    pix = (cam * height + py) * width + px
                    for d in range(D):
                        out[pix, d] = acc[d]
                    out[pix, D] = 1.0 - T
                    stop[pix] = q_stop
                    walked += q_stop - start
            counters[t, 0] = walked
            counters[t, 1] = used

    @numba.njit(parallel=True, cache=CACHE, fastmath=False)
    def _backward_kernel(
        params, skip_sigma, colors, tile_ids, offsets, width, height, tile_size, stop, out, g_pix, g_q
    ):
        # out [n_pix, D + 1] the forward's float64 (features, alpha); g_pix [n_pix, D + 1] dL/d(features, alpha);
        # g_q [Q, 6 + D] per list entry (zero-initialised).
        D = colors.shape[1]
        tiles_x = (width + tile_size - 1) // tile_size
        tiles_y = (height + tile_size - 1) // tile_size
        for t in numba.prange(tile_ids.shape[0]):
            cam, x0, y0 = _tile_origin(tile_ids[t], tiles_x, tiles_y, tile_size)
            start = offsets[t]
            for py in range(y0, min(y0 + tile_size, height)):
                for px in range(x0, min(x0 + tile_size, width)):
                    pix = (cam * height + py) * width + px
                    end = stop[pix]
                    pcx = px + 0.5
                    pcy = py + 0.5
                    g_a = g_pix[pix, D]  # the alpha output is one more feature, constant 1
                    # sum_i w_i g.c_i over the whole list is g . (output features, alpha): no first walk needed.
                    total = g_a * out[pix, D]
                    for d in range(D):
                        total += g_pix[pix, d] * out[pix, d]
                    if total == 0.0 and g_a == 0.0:
                        nonzero = False
                        for d in range(D):
                            if g_pix[pix, d] != 0.0:
                                nonzero = True
                        if not nonzero:
                            continue
                    # gsplat's VJP front to back, behind_i = total - prefix_i.
                    T = 1.0
                    prefix = 0.0
                    for q in range(start, end):
                        dx = params[q, 0] - pcx
                        dy = params[q, 1] - pcy
                        a = params[q, 2]
                        b = params[q, 3]
                        c = params[q, 4]
                        o = params[q, 5]
                        raw = _raw_alpha(params, skip_sigma, q, dx, dy)
                        alpha = min(MAX_ALPHA, raw)
                        if alpha < ALPHA_THRESHOLD:
                            continue
                        next_T = T * (1.0 - alpha)
                        if next_T <= TRANSMITTANCE_MIN:
                            break
                        w = alpha * T
                        gc = g_a
                        for d in range(D):
                            gc += g_pix[pix, d] * colors[q, d]
                            g_q[q, 6 + d] += w * g_pix[pix, d]
                        prefix += w * gc
                        if raw < MAX_ALPHA:  # min(0.999, .) clamps: no gradient (gsplat)
                            g_alpha = T * gc - (total - prefix) / (1.0 - alpha)
                            g_sigma = -alpha * g_alpha
                            g_q[q, 0] += g_sigma * (a * dx + b * dy)
                            g_q[q, 1] += g_sigma * (b * dx + c * dy)
                            g_q[q, 2] += g_sigma * 0.5 * dx * dx
                            g_q[q, 3] += g_sigma * dx * dy
                            g_q[q, 4] += g_sigma * 0.5 * dy * dy
                            if o > 0.0:
                                g_q[q, 5] += g_alpha * alpha / o
                        T = next_T


def _skip_sigma(params: np.ndarray) -> np.ndarray:
    """Per list entry, the sigma above which ``opacity exp(-sigma) < 1/255`` for sure. [Q, 6] -> [Q] float64

    ``o e^-s < 1/255  <=>  s > log(255 o)``; the margin keeps rounding at the boundary to the exact
    test (the exp), so results are unchanged while most pairs of a tile skip the exp.
    """
    o = params[:, 5].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        thr = np.log(255.0 * o)
    thr = np.where(o > 0, thr, -np.inf) + 1e-6  # o <= 0: alpha = 0, always skipped
    return np.where(np.isnan(o), np.inf, thr)  # NaN opacity: never skipped early (the exact test decides)


class CompositeNumba(torch.autograd.Function):
    """Forward/backward through the compiled kernels; inputs in tile-list order (see :func:`composite`)."""

    @staticmethod
    def forward(ctx, params_q, colors_q, tile_ids, offsets, counts, width, height, n_cameras, tile_size, stats_out):
        set_threads()
        n_pix = n_cameras * height * width
        D = colors_q.shape[1]
        p = params_q.detach().cpu().contiguous().numpy()
        col = colors_q.detach().cpu().contiguous().numpy()
        tid, off, cnt = (x.cpu().contiguous().numpy() for x in (tile_ids, offsets, counts))
        out = np.zeros((n_pix, D + 1), np.float64)
        stop = np.zeros(n_pix, np.int64)
        counters = np.zeros((tid.shape[0], 2), np.int64)
        if tid.shape[0]:
            _forward_kernel(p, _skip_sigma(p), col, tid, off, cnt, width, height, tile_size, out, stop, counters)
        ctx.save_for_backward(params_q, colors_q)
        ctx.setup = (tid, off, stop, out, width, height, tile_size)
        if stats_out is not None:
            walked, used = counters.sum(0).tolist()
            stats_out.append((int(cnt.sum()), int(walked), int(used)))
        res = torch.from_numpy(out).to(device=params_q.device, dtype=params_q.dtype)
        return res[:, :D], res[:, D]

    @staticmethod
    def backward(ctx, g_color, g_alpha):
        params_q, colors_q = ctx.saved_tensors
        tid, off, stop, out, width, height, tile_size = ctx.setup
        set_threads()
        n_q, D = colors_q.shape
        n_pix = stop.shape[0]
        g_pix = np.zeros((n_pix, D + 1), np.float64)
        if g_color is not None:
            g_pix[:, :D] = g_color.detach().cpu().double().numpy()
        if g_alpha is not None:
            g_pix[:, D] = g_alpha.detach().cpu().double().numpy()
        g_q = np.zeros((n_q, 6 + D), np.float64)
        if tid.shape[0]:
            p = params_q.detach().cpu().contiguous().numpy()
            col = colors_q.detach().cpu().contiguous().numpy()
            _backward_kernel(p, _skip_sigma(p), col, tid, off, width, height, tile_size, stop, out, g_pix, g_q)
        g = torch.from_numpy(g_q).to(device=params_q.device, dtype=params_q.dtype)
        return g[:, :6], g[:, 6:], None, None, None, None, None, None, None, None
