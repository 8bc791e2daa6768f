"""Compiled (numba) CPU kernels of the avatar's forward and backward, each with its torch oracle.

- :func:`basis_product`: per-point corrective products ``delta[b, n] = w[b, n] @ basis[n]``.
- :func:`polar_rotation_fast`: the nearest rotation of many 3x3 blends, with a closed-form backward.
- :func:`posed_quaternion_fast`: the posed rotation ``polar(M) R(q)`` as a quaternion, fused.
- :func:`sparse_interpolate_fast`: k-NN interpolation ``out[b] = W @ values[b]`` with a sparse ``W``.
- :func:`pose_lbs_fast`: inference only: LBS blend, posed centres and posed rotations in one pass.
- :func:`interpolated_deltas_fast`: inference only: the pose head's interpolation of the anchor
  coefficients and all five Gaussian basis products in one pass over the Gaussians.

Basis products:

``torch.einsum("bnk,nkd->bnd")`` runs these as ``bmm`` over N (43,690 at the ``small`` preset) tiny
``[B, K] x [K, D]`` matrices, forward and backward; with B = 2 and K = 16 the per-matrix overhead
dominates (~100 ms of a ~700 ms CPU step, docs/performance.md). A plain loop over points does the same
multiply-adds without that overhead. The einsum stays as the oracle (tests) and as the path on other
devices, for autograd's double backward, and when numba is missing.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from gsavatar.utils.compiled import CACHE, numba, set_threads

if TYPE_CHECKING:  # annotations only: properties -> gaussians -> kernels
    from gsavatar.models.properties import PackedLayout

_PATHS: dict[str, dict] = {}
"""Per fast path: how often the compiled kernel ran and how often its torch twin did, with the first reason."""


def _why_not(args: tuple) -> str:
    """Why a fast path declined: numba missing, or the inputs it saw (device, dtype, grad, layout)."""
    if numba is None:
        return "numba is not installed"
    parts = []
    for a in args:
        if torch.is_tensor(a):
            flags = [str(a.device), str(a.dtype).replace("torch.", ""), "x".join(map(str, a.shape)) or "scalar"]
            flags += ["requires_grad"] * a.requires_grad + ["non-contiguous"] * (not a.is_contiguous())
            flags += ["sparse"] * a.is_sparse
            parts.append(" ".join(flags))
    return "preconditions not met for inputs: " + "; ".join(parts) + f" (grad mode {torch.is_grad_enabled()})"


def visible_path(name: str):
    """Record which path a ``*_fast`` function took (it returns None when its torch twin must run instead):
    :func:`path_report` lists them, the trainer writes it into ``timing.json``, so a change that breaks a
    precondition shows up as a slower path instead of silently costing time."""

    def wrap(fn):
        @functools.wraps(fn)
        def inner(*args, **kwargs):
            out = fn(*args, **kwargs)
            e = _PATHS.setdefault(name, {"compiled": 0, "torch": 0, "why_torch": None})
            e["compiled" if out is not None else "torch"] += 1
            if out is None and e["why_torch"] is None:
                e["why_torch"] = _why_not(args)
            return out

        return inner

    return wrap


def path_report() -> dict[str, dict]:
    """``{kernel: {"compiled": calls, "torch": calls, "why_torch": first reason or None}}`` since the last
    :func:`reset_paths` (this process)."""
    return {k: dict(v) for k, v in sorted(_PATHS.items())}


def reset_paths() -> None:
    """Forget the recorded paths (e.g. before one configuration's benchmark)."""
    _PATHS.clear()


if numba is not None:
    # Accumulation in the inputs' dtype (``x * 0`` keeps it) lets LLVM vectorise the inner loops; the
    # sums have K or B terms, like einsum's.
    @numba.njit(parallel=True, cache=CACHE, fastmath=True)
    def _forward(coeffs, basis, out):  # [B, N, K], [N, K, D] -> out [B, N, D]
        B, N, K = coeffs.shape
        D = basis.shape[2]
        for n in numba.prange(N):
            for b in range(B):
                for d in range(D):
                    out[b, n, d] = 0
                for k in range(K):
                    ck = coeffs[b, n, k]
                    for d in range(D):
                        out[b, n, d] += ck * basis[n, k, d]

    @numba.njit(parallel=True, cache=CACHE, fastmath=True)
    def _backward(coeffs, basis, grad, g_coeffs, g_basis, need_coeffs, need_basis):
        B, N, K = coeffs.shape
        D = basis.shape[2]
        for n in numba.prange(N):
            for k in range(K):
                if need_coeffs:
                    for b in range(B):
                        acc = coeffs[b, n, k] * 0
                        for d in range(D):
                            acc += grad[b, n, d] * basis[n, k, d]
                        g_coeffs[b, n, k] = acc
                if need_basis:
                    for d in range(D):
                        g_basis[n, k, d] = coeffs[0, n, k] * grad[0, n, d]
                    for b in range(1, B):
                        cb = coeffs[b, n, k]
                        for d in range(D):
                            g_basis[n, k, d] += cb * grad[b, n, d]

    @numba.njit(cache=CACHE, inline="always")
    def _newton_polar(x, cof, tol, max_iters):
        # x [9] row-major 3x3 with det > 0, replaced by its orthogonal polar factor. Scaled Newton
        # X <- (g X + (g X)^-T) / 2, g = |det X|^(-1/3) (Higham 1986), float64. For 0.5 < |det| < 2 (LBS
        # blends, and every iterate near the end) g is three Newton steps of y -> y (4 - d y^3) / 3 from
        # y = 1 (within 0.4% of the cube root; the scale only speeds convergence, the limit is the same):
        # pow() was ~55% of the kernel's time (5.3 -> 3.6 ms for 43,690 blends, same iterations and result).
        for it in range(max_iters):
            cof[0] = x[4] * x[8] - x[5] * x[7]
            cof[1] = x[5] * x[6] - x[3] * x[8]
            cof[2] = x[3] * x[7] - x[4] * x[6]
            cof[3] = x[7] * x[2] - x[8] * x[1]
            cof[4] = x[8] * x[0] - x[6] * x[2]
            cof[5] = x[6] * x[1] - x[7] * x[0]
            cof[6] = x[1] * x[5] - x[2] * x[4]
            cof[7] = x[2] * x[3] - x[0] * x[5]
            cof[8] = x[0] * x[4] - x[1] * x[3]
            det = x[0] * cof[0] + x[1] * cof[1] + x[2] * cof[2]
            d = abs(det)
            if 0.5 < d < 2.0:
                g = (4.0 - d) * (1.0 / 3.0)
                g = g * (4.0 - d * g * g * g) * (1.0 / 3.0)
                g = g * (4.0 - d * g * g * g) * (1.0 / 3.0)
            else:
                g = max(d, 1e-30) ** (-1.0 / 3.0)
            a = 0.5 * g
            b = 0.5 / (g * det)
            delta = 0.0
            for i in range(9):
                v = a * x[i] + b * cof[i]
                delta = max(delta, abs(v - x[i]))
                x[i] = v
            if delta <= tol:
                break

    @numba.njit(cache=CACHE, inline="always")
    def _store_polar(x, M, n, R, S):
        # R[n] = x (the polar factor), S[n] = R^T M[n] (its symmetric partner, kept for the backward)
        for i in range(9):
            R[n, i] = x[i]
        for i in range(3):
            for j in range(3):
                S[n, 3 * i + j] = x[i] * M[n, j] + x[3 + i] * M[n, 3 + j] + x[6 + i] * M[n, 6 + j]

    @numba.njit(parallel=True, cache=CACHE)
    def _polar_forward(M, R, S, tol, max_iters):
        # M [N, 9] row-major blends with det > 0 -> R [N, 9] orthogonal polar factor, S [N, 9] = R^T M.
        for n in numba.prange(M.shape[0]):
            x = np.empty(9)
            cof = np.empty(9)
            for i in range(9):
                x[i] = M[n, i]
            _newton_polar(x, cof, tol, max_iters)
            _store_polar(x, M, n, R, S)

    @numba.njit(cache=CACHE, inline="always")
    def _polar_vjp(R, S, n, u0, u1, u2, out):
        # Given dL/dω = u for dR = R [ω]x, writes dL/dM = R [y]x, y = (tr(P) I - P)^-1 u, P = sym(S) (see
        # polar_rotation_fast), into out[n].
        p00 = S[n, 0]
        p11 = S[n, 4]
        p22 = S[n, 8]
        p01 = 0.5 * (S[n, 1] + S[n, 3])
        p02 = 0.5 * (S[n, 2] + S[n, 6])
        p12 = 0.5 * (S[n, 5] + S[n, 7])
        tr = p00 + p11 + p22
        k00 = tr - p00  # K = tr I - P: symmetric, positive definite for P > 0; solved by cofactors
        k11 = tr - p11
        k22 = tr - p22
        k01 = -p01
        k02 = -p02
        k12 = -p12
        c00 = k11 * k22 - k12 * k12
        c01 = k02 * k12 - k01 * k22
        c02 = k01 * k12 - k02 * k11
        c11 = k00 * k22 - k02 * k02
        c12 = k01 * k02 - k00 * k12
        c22 = k00 * k11 - k01 * k01
        det = k00 * c00 + k01 * c01 + k02 * c02
        if not (abs(det) > 1e-30):
            for i in range(9):
                out[n, i] = 0.0
            return
        y0 = (c00 * u0 + c01 * u1 + c02 * u2) / det
        y1 = (c01 * u0 + c11 * u1 + c12 * u2) / det
        y2 = (c02 * u0 + c12 * u1 + c22 * u2) / det
        for i in range(3):  # R [y]x, [y]x = [[0, -y2, y1], [y2, 0, -y0], [-y1, y0, 0]]
            r0 = R[n, 3 * i]
            r1 = R[n, 3 * i + 1]
            r2 = R[n, 3 * i + 2]
            out[n, 3 * i] = r1 * y2 - r2 * y1
            out[n, 3 * i + 1] = -r0 * y2 + r2 * y0
            out[n, 3 * i + 2] = r0 * y1 - r1 * y0

    @numba.njit(parallel=True, cache=CACHE)
    def _polar_backward(R, S, G, out):
        for n in numba.prange(R.shape[0]):
            # dL/dω = vee(R^T G - G^T R) for dR = R [ω]x
            w = np.empty(9)
            for i in range(3):
                for j in range(3):
                    w[3 * i + j] = R[n, i] * G[n, j] + R[n, 3 + i] * G[n, 3 + j] + R[n, 6 + i] * G[n, 6 + j]
            _polar_vjp(R, S, n, w[7] - w[5], w[2] - w[6], w[3] - w[1], out)

    @numba.njit(cache=CACHE, inline="always")
    def _compose_quat(x, C, n):
        # x [9] a rotation (row-major), C[n] a wxyz quaternion -> (q, p): q = ±quat(x) ⊗ C/|C| with q_w >= 0,
        # p = ±quat(x) with the same sign. Shepperd: the largest of 4w^2, 4x^2, 4y^2, 4z^2 decides the branch.
        t0 = 1.0 + x[0] + x[4] + x[8]
        t1 = 1.0 + x[0] - x[4] - x[8]
        t2 = 1.0 - x[0] + x[4] - x[8]
        t3 = 1.0 - x[0] - x[4] + x[8]
        if t0 >= t1 and t0 >= t2 and t0 >= t3:
            r = 2.0 * np.sqrt(max(t0, 1e-300))
            pw, px, py, pz = 0.25 * r, (x[7] - x[5]) / r, (x[2] - x[6]) / r, (x[3] - x[1]) / r
        elif t1 >= t2 and t1 >= t3:
            r = 2.0 * np.sqrt(max(t1, 1e-300))
            pw, px, py, pz = (x[7] - x[5]) / r, 0.25 * r, (x[1] + x[3]) / r, (x[2] + x[6]) / r
        elif t2 >= t3:
            r = 2.0 * np.sqrt(max(t2, 1e-300))
            pw, px, py, pz = (x[2] - x[6]) / r, (x[1] + x[3]) / r, 0.25 * r, (x[5] + x[7]) / r
        else:
            r = 2.0 * np.sqrt(max(t3, 1e-300))
            pw, px, py, pz = (x[3] - x[1]) / r, (x[2] + x[6]) / r, (x[5] + x[7]) / r, 0.25 * r
        cn = np.sqrt(C[n, 0] ** 2 + C[n, 1] ** 2 + C[n, 2] ** 2 + C[n, 3] ** 2)
        if cn > 1e-12:
            cw, cx, cy, cz = C[n, 0] / cn, C[n, 1] / cn, C[n, 2] / cn, C[n, 3] / cn
        else:  # zero quaternion -> identity (like quat_to_matrix)
            cw, cx, cy, cz = 1.0, 0.0, 0.0, 0.0
        qw = pw * cw - px * cx - py * cy - pz * cz
        qx = pw * cx + px * cw + py * cz - pz * cy
        qy = pw * cy - px * cz + py * cw + pz * cx
        qz = pw * cz + px * cy - py * cx + pz * cw
        sgn = -1.0 if qw < 0.0 else 1.0
        return sgn * qw, sgn * qx, sgn * qy, sgn * qz, sgn * pw, sgn * px, sgn * py, sgn * pz

    @numba.njit(parallel=True, cache=CACHE)
    def _posed_quat_forward(M, C, tol, max_iters, save, Q, P, R, S):
        # M [N, 9] blends (det > 0), C [N, 4] unit wxyz -> Q [N, 4] = ±quat(polar(M)) ⊗ C with Q_w >= 0;
        # ``save``: also P [N, 4] = ±quat(polar(M)) (the sign folded in), R [N, 9] polar factor, S [N, 9] = R^T M
        # (for the backward). Any float dtype in and out; float64 inside.
        for n in numba.prange(M.shape[0]):
            x = np.empty(9)
            cof = np.empty(9)
            for i in range(9):
                x[i] = M[n, i]
            _newton_polar(x, cof, tol, max_iters)
            if save:
                _store_polar(x, M, n, R, S)
            qw, qx, qy, qz, pw, px, py, pz = _compose_quat(x, C, n)
            Q[n, 0], Q[n, 1], Q[n, 2], Q[n, 3] = qw, qx, qy, qz
            if save:
                P[n, 0], P[n, 1], P[n, 2], P[n, 3] = pw, px, py, pz

    @numba.njit(parallel=True, cache=CACHE)
    def _pose_lbs(crow, col, val, T, X, C, tol, max_iters, min_det, means, Q):
        # Per point n of every frame b: A = sum_j val T[b, col] (the LBS blend, 3x4), means = A[:, :3] X + A[:, 3],
        # Q = ±quat(polar(A[:, :3])) ⊗ C (as _posed_quat_forward). Returns how many blends had det <= min_det
        # (those need the SVD path; their outputs are left unset).
        B = T.shape[0]
        N = crow.shape[0] - 1
        bad = 0
        for n in numba.prange(N):
            a = np.empty(12)
            x = np.empty(9)
            cof = np.empty(9)
            for b in range(B):
                for i in range(12):
                    a[i] = 0.0
                for j in range(crow[n], crow[n + 1]):
                    v = val[j]
                    m = col[j]
                    for i in range(12):
                        a[i] += v * T[b, m, i]
                c0, c1, c2 = X[b, n, 0], X[b, n, 1], X[b, n, 2]
                for i in range(3):
                    means[b, n, i] = a[4 * i] * c0 + a[4 * i + 1] * c1 + a[4 * i + 2] * c2 + a[4 * i + 3]
                for i in range(3):
                    for k in range(3):
                        x[3 * i + k] = a[4 * i + k]
                det = (
                    x[0] * (x[4] * x[8] - x[5] * x[7])
                    - x[1] * (x[3] * x[8] - x[5] * x[6])
                    + x[2] * (x[3] * x[7] - x[4] * x[6])
                )
                if not det > min_det:
                    bad += 1
                    continue
                _newton_polar(x, cof, tol, max_iters)
                qw, qx, qy, qz, pw, px, py, pz = _compose_quat(x, C[b], n)
                Q[b, n, 0], Q[b, n, 1], Q[b, n, 2], Q[b, n, 3] = qw, qx, qy, qz
        return bad

    @numba.njit(parallel=True, cache=CACHE)
    def _posed_quat_backward(C, P, R, S, G, g_M, g_C):
        # Q = P ⊗ C (bilinear); dP = P ⊗ (0, ω) / 2 for dR = R [ω]x; then the polar VJP.
        for n in numba.prange(C.shape[0]):
            gw, gx, gy, gz = G[n, 0], G[n, 1], G[n, 2], G[n, 3]
            cn = np.sqrt(C[n, 0] ** 2 + C[n, 1] ** 2 + C[n, 2] ** 2 + C[n, 3] ** 2)
            if cn > 1e-12:
                cw, cx, cy, cz = C[n, 0] / cn, C[n, 1] / cn, C[n, 2] / cn, C[n, 3] / cn
            else:
                cw, cx, cy, cz = 1.0, 0.0, 0.0, 0.0
            pw, px, py, pz = P[n, 0], P[n, 1], P[n, 2], P[n, 3]
            ew = gw * pw + gx * px + gy * py + gz * pz  # dL/d(C / |C|)
            ex = -gw * px + gx * pw + gy * pz - gz * py
            ey = -gw * py - gx * pz + gy * pw + gz * px
            ez = -gw * pz + gx * py - gy * px + gz * pw
            radial = ew * cw + ex * cx + ey * cy + ez * cz  # normalisation: keep the tangential part
            inv = 1.0 / cn if cn > 1e-12 else 0.0
            g_C[n, 0] = (ew - radial * cw) * inv
            g_C[n, 1] = (ex - radial * cx) * inv
            g_C[n, 2] = (ey - radial * cy) * inv
            g_C[n, 3] = (ez - radial * cz) * inv
            hw = gw * cw + gx * cx + gy * cy + gz * cz
            hx = -gw * cx + gx * cw - gy * cz + gz * cy
            hy = -gw * cy + gx * cz + gy * cw - gz * cx
            hz = -gw * cz - gx * cy + gy * cx + gz * cw
            u0 = 0.5 * (-hw * px + hx * pw + hy * pz - hz * py)
            u1 = 0.5 * (-hw * py - hx * pz + hy * pw + hz * px)
            u2 = 0.5 * (-hw * pz + hx * py - hy * px + hz * pw)
            _polar_vjp(R, S, n, u0, u1, u2, g_M)


if numba is not None:

    @numba.njit(parallel=True, cache=CACHE, fastmath=True)
    def _csr_rows(crow, col, val, values, out):  # out[b, n] = sum_j val[j] values[b, col[j]] over row n
        B = values.shape[0]
        D = values.shape[2]
        for n in numba.prange(crow.shape[0] - 1):
            for b in range(B):
                for d in range(D):
                    out[b, n, d] = 0
                for j in range(crow[n], crow[n + 1]):
                    w = val[j]
                    m = col[j]
                    for d in range(D):
                        out[b, n, d] += w * values[b, m, d]


def _csr_parts(matrix: Tensor) -> tuple:
    """(crow, col, val) of a coalesced sparse COO ``[N, M]`` matrix and of its transpose, as numpy arrays;
    computed once per matrix object (the avatar caches its interpolation matrices)."""
    parts = getattr(matrix, "_gsavatar_csr", None)
    if parts is None:
        idx = matrix.indices().numpy()
        val = matrix.values().detach().numpy()
        N, M = matrix.shape
        out = []
        for rows, cols, n in ((idx[0], idx[1], N), (idx[1], idx[0], M)):
            order = np.lexsort((cols, rows))
            crow = np.zeros(n + 1, np.int64)
            np.cumsum(np.bincount(rows, minlength=n), out=crow[1:])
            out.append((crow, np.ascontiguousarray(cols[order]), np.ascontiguousarray(val[order])))
        parts = (*out[0], *out[1])
        matrix._gsavatar_csr = parts
    return parts


class _SparseInterp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, values: Tensor, matrix: Tensor) -> Tensor:
        set_threads()
        crow, col, val, tcrow, tcol, tval = _csr_parts(matrix)
        v = values.detach().contiguous().numpy()
        out = np.empty((v.shape[0], crow.shape[0] - 1, v.shape[2]), v.dtype)
        _csr_rows(crow, col, val.astype(v.dtype, copy=False), v, out)
        ctx.parts = (tcrow, tcol, tval)
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        tcrow, tcol, tval = ctx.parts
        set_threads()
        g = grad.detach().contiguous().numpy()
        out = np.empty((g.shape[0], tcrow.shape[0] - 1, g.shape[2]), g.dtype)
        _csr_rows(tcrow, tcol, tval.astype(g.dtype, copy=False), g, out)  # W^T g: rows of the transpose
        return torch.from_numpy(out), None


@visible_path("sparse_interpolate_fast")
def sparse_interpolate_fast(values: Tensor, matrix: Tensor) -> Tensor | None:
    """``out[b] = matrix @ values[b]`` for a coalesced sparse COO ``[N, M]`` matrix (constant: no gradient),
    compiled row loops forward and over the transpose's rows backward; None where it does not apply
    (not CPU float32/float64 or numba missing: use ``torch.sparse.mm``, its oracle).

    values [B, M, D] -> [B, N, D]
    """
    if (
        numba is None
        or values.device.type != "cpu"
        or values.dtype not in (torch.float32, torch.float64)
        or matrix.layout != torch.sparse_coo
        or not matrix.is_coalesced()
        or matrix.requires_grad
        or values.shape[0] == 0
    ):
        return None
    return _SparseInterp.apply(values, matrix)


if numba is not None:

    @numba.njit(parallel=True, cache=CACHE, fastmath=True)
    def _interp_deltas_packed(crow, col, val, coeffs, extra, basis, sh0_at, out):
        # basis [N, K, D]: every property's basis side by side (GaussianAvatar.pack_bases_); the row
        # product runs over D contiguous floats (vectorised); the anchors' SH0 delta lands at sh0_at.
        B, _, K = coeffs.shape
        N = crow.shape[0] - 1
        D = basis.shape[2]
        zero = coeffs.dtype.type(0)
        for blk in numba.prange((N + 255) // 256):
            w = np.empty(K, coeffs.dtype)
            acc = np.empty(D, coeffs.dtype)
            for n in range(blk * 256, min(N, blk * 256 + 256)):
                for b in range(B):
                    for k in range(K):
                        w[k] = zero
                    for d in range(D):
                        acc[d] = zero
                    for j in range(crow[n], crow[n + 1]):
                        v = val[j]
                        a = col[j]
                        for k in range(K):
                            w[k] += v * coeffs[b, a, k]
                        for c in range(3):
                            acc[sh0_at + c] += v * extra[b, a, c]
                    for k in range(K):
                        wk = w[k]
                        for d in range(D):
                            acc[d] += wk * basis[n, k, d]
                    for d in range(D):
                        out[b, n, d] = acc[d]


@visible_path("packed_bases")
def packed_bases(bases: Sequence[Tensor], layout: PackedLayout) -> Tensor | None:
    """The ``[G, K, D]`` tensor the bases are views of (side by side in the columns of ``layout``, as
    :meth:`~gsavatar.models.avatar.GaussianAvatar.pack_bases_` lays them out), or None if they are not."""
    if not bases:
        return None
    first = bases[0]
    G, K = first.shape[:2]
    D = layout.size
    base = first.storage_offset()
    for t, offset in zip(bases, layout.offsets):
        want = (K * D, D, *_inner_strides(t.shape[2:]))
        if (
            t.untyped_storage().data_ptr() != first.untyped_storage().data_ptr()
            or t.shape[:2] != (G, K)
            or (t.numel() and (t.stride() != want or t.storage_offset() != base + offset))
        ):
            return None
    return first.as_strided((G, K, D), (K * D, D, 1), base)


def _inner_strides(dims: Sequence[int]) -> tuple[int, ...]:
    """Row-major strides of the trailing ``dims`` of one Gaussian's slice (``(3,)`` -> ``(1,)``,
    ``(R, 3)`` -> ``(3, 1)``)."""
    out, step = [], 1
    for d in reversed(tuple(dims)):
        out.append(step)
        step *= int(d)
    return tuple(reversed(out))


@visible_path("interpolated_deltas_fast")
def interpolated_deltas_fast(
    coeffs: Tensor,
    matrix: Tensor,
    bases: Sequence[Tensor],
    layout: PackedLayout,
    n_sh_rest: int,
    anchor_terms: Tensor | None = None,
) -> dict[str, Tensor] | None:
    """Inference only: the Gaussians' pose-dependent deltas in one compiled pass over the Gaussians.

    Per Gaussian ``n`` and frame ``b``: ``w = (W @ coeffs[b])[n]`` (its anchors' coefficients
    interpolated), then ``<w, ΔΛ[n]>`` for every basis of the property table (the SH bands' first
    ``n_sh_rest``), and the row with anchor terms also gets ``(W @ anchor_terms[b])[n]``. The bases must lie
    side by side in one tensor (:func:`packed_bases`, as :meth:`GaussianAvatar.pack_bases_` lays them out):
    each Gaussian's products then run over 22 contiguous floats for the default table (vectorised; one pass
    over five separate bases measured 9.7 ms against 5-7 ms, the five products 17.5 ms). The same numbers as
    :func:`sparse_interpolate_fast` followed by one :func:`basis_product` per basis (their oracle, up to
    summation order), without materialising ``w``. No autograd: None while gradients are enabled, for
    unpacked bases, and where the compiled path does not apply (not CPU, dtypes differ or not
    float32/float64, numba missing, ``matrix`` not a coalesced sparse COO matrix).

    Args:
        coeffs: Tensor  # [B, A, K] anchor coefficients
        matrix: sparse COO  # [G, A] interpolation weights
        bases: Tensor per row of ``layout``  # [G, K, *dims] (the SH bands [G, K, R, 3], R >= n_sh_rest)
        layout: the packed columns (:func:`gsavatar.models.properties.packed_layout`)
        anchor_terms: Tensor | None  # [B, A, width] per-anchor deltas of the row at ``layout.anchor_at``

    Returns:
        row name -> [B, G, *dims] (SH bands [B, G, n_sh_rest, 3]; left out when ``n_sh_rest`` is 0)
    """
    tensors = (coeffs, *bases) + ((anchor_terms,) if anchor_terms is not None else ())
    sh_rows = [t.shape[2] for t, sh in zip(bases, layout.sh_bands) if sh]
    anchor_width = layout.widths[layout.offsets.index(layout.anchor_at)] if layout.anchor_at >= 0 else 3
    if (
        torch.is_grad_enabled()
        or numba is None
        or matrix.layout != torch.sparse_coo
        or not matrix.is_coalesced()
        or any(t.device.type != "cpu" or t.dtype != coeffs.dtype for t in tensors)
        or coeffs.dtype not in (torch.float32, torch.float64)
        or 0 in coeffs.shape
        or len(bases) != len(layout.names)
        or any(not 0 <= n_sh_rest <= r for r in sh_rows)
        or (anchor_terms is not None and layout.anchor_at < 0)
        or anchor_width != 3  # the kernel adds 3 anchor values (a colour)
    ):
        return None
    packed = packed_bases(bases, layout)
    if packed is None:
        return None
    set_threads()
    crow, col, val, *_ = _csr_parts(matrix)
    B, G = coeffs.shape[0], crow.shape[0] - 1
    c = coeffs.detach().contiguous().numpy()
    extra = (
        anchor_terms.detach().contiguous().numpy()
        if anchor_terms is not None
        else np.zeros((B, c.shape[1], 3), c.dtype)
    )
    out = torch.empty(B, G, packed.shape[2], dtype=coeffs.dtype)
    at = max(layout.anchor_at, 0)  # no anchor row: zeros added to the first columns
    _interp_deltas_packed(
        crow, col, val.astype(c.dtype, copy=False), c, extra, packed.detach().numpy(), at, out.numpy()
    )
    deltas = {}
    for t, name, offset, w, sh in zip(bases, layout.names, layout.offsets, layout.widths, layout.sh_bands):
        if sh:  # the SH bands: the first n_sh_rest of them
            if n_sh_rest:
                deltas[name] = out[..., offset : offset + 3 * n_sh_rest].unflatten(-1, (n_sh_rest, 3))
            continue
        deltas[name] = out[..., offset : offset + w].unflatten(-1, tuple(t.shape[2:]))
    return deltas


class _BasisProduct(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs: Tensor, basis: Tensor) -> Tensor:
        set_threads()
        c, m = coeffs.detach().numpy(), basis.detach().numpy()
        out = np.empty((c.shape[0], c.shape[1], m.shape[2]), c.dtype)
        _forward(c, m, out)
        ctx.save_for_backward(coeffs, basis)
        return torch.from_numpy(out)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        coeffs, basis = ctx.saved_tensors
        need_c, need_b = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        set_threads()
        c, m = coeffs.detach().numpy(), basis.detach().numpy()
        g = grad.detach().contiguous().numpy()
        g_c = np.empty(c.shape, c.dtype) if need_c else np.empty((0, 0, 0), c.dtype)
        g_b = np.empty(m.shape, m.dtype) if need_b else np.empty((0, 0, 0), m.dtype)
        _backward(c, m, g, g_c, g_b, need_c, need_b)
        return (torch.from_numpy(g_c) if need_c else None), (torch.from_numpy(g_b) if need_b else None)


def basis_product(coeffs: Tensor, basis: Tensor) -> Tensor:
    """``einsum("bnk,nkd->bnd", coeffs, basis)``: the numba loop on CPU float tensors, einsum elsewhere.

    coeffs [B, N, K], basis [N, K, D] (may be a strided view) -> [B, N, D]
    """
    fast = (
        numba is not None
        and coeffs.device.type == "cpu"
        and basis.device.type == "cpu"
        and coeffs.dtype == basis.dtype
        and coeffs.dtype in (torch.float32, torch.float64)
        and coeffs.shape[0] > 0
        and coeffs.shape[1] > 0
        and basis.shape[1] > 0
    )
    if not fast:
        return torch.einsum("bnk,nkd->bnd", coeffs, basis)
    return _BasisProduct.apply(coeffs, basis)


class _PolarRotation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, M: Tensor, tol: float, max_iters: int) -> Tensor:
        set_threads()
        m = M.detach().reshape(-1, 9).to(torch.float64).numpy()
        R = np.empty_like(m)
        S = np.empty_like(m)
        _polar_forward(m, R, S, tol, max_iters)
        ctx.rs = (R, S)  # float64 numpy, not tensors: backward needs the exact iterate
        return torch.from_numpy(R).to(M.dtype).reshape(M.shape)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        R, S = ctx.rs
        set_threads()
        out = np.empty_like(R)
        _polar_backward(R, S, grad.detach().reshape(-1, 9).to(torch.float64).numpy(), out)
        return torch.from_numpy(out).to(grad.dtype).reshape(grad.shape), None, None


@visible_path("polar_rotation_fast")
def polar_rotation_fast(M: Tensor, tol: float, max_iters: int = 12) -> Tensor | None:
    """Orthogonal polar factor of 3x3 matrices with ``det > 0``, compiled; None where it does not apply
    (not CPU float32/float64, or numba missing: use the torch iteration).

    Forward: the scaled Newton iteration of :func:`~gsavatar.models.gaussians.polar_rotation`, per
    matrix until its own update is below ``tol``, in float64. Backward in closed form: with
    ``M = R P`` (P symmetric positive definite), ``R^T dM - dM^T R = Ω P + P Ω`` for ``Ω = R^T dR``;
    for skew ``[ω]x`` and symmetric P, ``P [ω]x + [ω]x P = [(tr(P) I - P) ω]x``, so
    ``dL/dM = R [y]x`` with ``y = (tr(P) I - P)^-1 vee(R^T G - G^T R)``. Tested against autograd
    through the torch iteration and against the SVD.

    M [..., 3, 3] -> R [..., 3, 3]
    """
    if numba is None or M.device.type != "cpu" or M.dtype not in (torch.float32, torch.float64) or M.numel() == 0:
        return None
    return _PolarRotation.apply(M, float(tol), int(max_iters))


class _PosedQuat(torch.autograd.Function):
    @staticmethod
    def forward(ctx, M: Tensor, C: Tensor, tol: float, max_iters: int) -> Tensor:
        set_threads()
        m = M.detach().reshape(-1, 9).to(torch.float64).numpy()
        c = C.detach().reshape(-1, 4).to(torch.float64).numpy()
        n = m.shape[0]
        Q, P = np.empty((n, 4)), np.empty((n, 4))
        R, S = np.empty((n, 9)), np.empty((n, 9))
        _posed_quat_forward(m, c, tol, max_iters, True, Q, P, R, S)
        ctx.saved = (c, P, R, S)
        return torch.from_numpy(Q).to(C.dtype).reshape(C.shape)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        c, P, R, S = ctx.saved
        set_threads()
        g_M, g_C = np.empty_like(R), np.empty_like(c)
        _posed_quat_backward(c, P, R, S, grad.detach().reshape(-1, 4).to(torch.float64).numpy(), g_M, g_C)
        shape_m = (*grad.shape[:-1], 3, 3)
        return (
            torch.from_numpy(g_M).to(grad.dtype).reshape(shape_m),
            torch.from_numpy(g_C).to(grad.dtype).reshape(grad.shape),
            None,
            None,
        )


@visible_path("posed_quaternion_fast")
def posed_quaternion_fast(M: Tensor, quats: Tensor, tol: float, max_iters: int = 12) -> Tensor | None:
    """``matrix_to_quat(polar(M) @ quat_to_matrix(quats))`` fused and compiled; None where it does not apply
    (not CPU float32/float64, numba missing, or a blend with ``det <= min_det`` that needs the SVD path).

    The posed rotation is the quaternion product ``quat(polar(M)) ⊗ quats`` (sign chosen so ``w >= 0``,
    like :func:`~gsavatar.geometry.rotations.matrix_to_quat`), one Shepperd branch per matrix instead
    of evaluating all four. Backward in closed form: the product is bilinear; ``dR = R [ω]x`` moves the
    polar factor's quaternion by ``p ⊗ (0, ω) / 2``; :func:`polar_rotation_fast` gives ``dL/dM`` from
    ``dL/dω``. Tested against autograd through the torch composition.

    M [..., 3, 3] with det > 0, quats [..., 4] wxyz (normalised inside; zero -> identity) -> [..., 4] unit wxyz
    """
    if (
        numba is None
        or M.device.type != "cpu"
        or M.dtype not in (torch.float32, torch.float64)
        or quats.dtype != M.dtype
        or M.numel() == 0
    ):
        return None
    if torch.is_grad_enabled() and (M.requires_grad or quats.requires_grad):
        return _PosedQuat.apply(M, quats, float(tol), int(max_iters))
    # No autograd: the inputs' dtype straight in and out, nothing saved for a backward.
    set_threads()
    Q = torch.empty(quats.shape, dtype=quats.dtype)
    none = np.empty((0, 0), np.float64)
    _posed_quat_forward(
        M.detach().reshape(-1, 9).contiguous().numpy(),
        quats.detach().reshape(-1, 4).contiguous().numpy(),
        float(tol),
        int(max_iters),
        False,
        Q.numpy().reshape(-1, 4),
        none,
        none,
        none,
    )
    return Q


@visible_path("pose_lbs_fast")
def pose_lbs_fast(
    transforms: Tensor,
    skin_matrix: Tensor,
    canonical: Tensor,
    quats: Tensor,
    tol: float,
    min_det: float,
    max_iters: int = 12,
) -> tuple[Tensor, Tensor] | None:
    """Inference only: LBS blend, posed centres and posed rotations in one compiled pass over the points.

    The same numbers as :func:`~gsavatar.models.gaussians.blend_affine` with the sparse skin matrix followed
    by :func:`~gsavatar.models.gaussians.pose_gaussians` (their oracle; the blend is summed in float64 here),
    without the ``[B, N, 3, 4]`` blends in memory. None while gradients are enabled, where it does not apply
    (not CPU, dtypes differ or not float32/float64, numba missing, ``skin_matrix`` not a coalesced sparse
    COO matrix) and when any blend has ``det <= min_det`` (those take the SVD path).

    Args:
        transforms: Tensor  # [B, J, 4, 4] posed_from_rest per joint
        skin_matrix: sparse COO  # [N, J] skinning weights
        canonical: Tensor  # [B, N, 3] rest-space centres
        quats: Tensor  # [B, N, 4] wxyz canonical rotations (normalised inside)

    Returns:
        (means [B, N, 3], quats [B, N, 4] unit wxyz, w >= 0)
    """
    dt = canonical.dtype
    if (
        torch.is_grad_enabled()
        or numba is None
        or dt not in (torch.float32, torch.float64)
        or any(t.device.type != "cpu" or t.dtype != dt for t in (transforms, canonical, quats))
        or skin_matrix.layout != torch.sparse_coo
        or not skin_matrix.is_coalesced()
        or 0 in canonical.shape
    ):
        return None
    set_threads()
    crow, col, val, *_ = _csr_parts(skin_matrix)
    B, N = canonical.shape[:2]
    T = transforms[:, :, :3, :].reshape(B, -1, 12).contiguous().numpy()
    means, Q = torch.empty(B, N, 3, dtype=dt), torch.empty(B, N, 4, dtype=dt)
    bad = _pose_lbs(
        crow,
        col,
        val.astype(np.float64),
        T,
        canonical.detach().contiguous().numpy(),
        quats.detach().contiguous().numpy(),
        float(tol),
        int(max_iters),
        float(min_det),
        means.numpy(),
        Q.numpy(),
    )
    return None if bad else (means, Q)
