"""Compiled (numba) CPU kernels of the avatar's forward and backward, each with its torch oracle.

- :func:`basis_product`: per-point corrective products ``delta[b, n] = w[b, n] @ basis[n]``.
- :func:`polar_rotation_fast`: the nearest rotation of many 3x3 blends, with a closed-form backward.

Basis products:

``torch.einsum("bnk,nkd->bnd")`` runs these as ``bmm`` over N (43,690 at the ``small`` preset) tiny
``[B, K] x [K, D]`` matrices, forward and backward; with B = 2 and K = 16 the per-matrix overhead
dominates (~100 ms of a ~700 ms CPU step, docs/performance.md). A plain loop over points does the same
multiply-adds without that overhead. The einsum stays as the oracle (tests) and as the path on other
devices, for autograd's double backward, and when numba is missing.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

try:
    import numba
except ImportError:  # pragma: no cover - numba is a declared dependency; einsum stands in
    numba = None


if numba is not None:

    # Accumulation in the inputs' dtype (``x * 0`` keeps it) lets LLVM vectorise the inner loops; the
    # sums have K or B terms, like einsum's.
    @numba.njit(parallel=True, cache=False, fastmath=True)
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

    @numba.njit(parallel=True, cache=False, fastmath=True)
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


    @numba.njit(parallel=True, cache=False)
    def _polar_forward(M, R, S, tol, max_iters):
        # M [N, 9] row-major blends with det > 0 -> R [N, 9] orthogonal polar factor, S [N, 9] = R^T M.
        # Scaled Newton X <- (g X + (g X)^-T) / 2, g = |det X|^(-1/3) (Higham 1986), float64 inside.
        x = np.empty(9)
        cof = np.empty(9)
        for n in numba.prange(M.shape[0]):
            for i in range(9):
                x[i] = M[n, i]
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
                g = max(abs(det), 1e-30) ** (-1.0 / 3.0)
                a = 0.5 * g
                b = 0.5 / (g * det)
                delta = 0.0
                for i in range(9):
                    v = a * x[i] + b * cof[i]
                    delta = max(delta, abs(v - x[i]))
                    x[i] = v
                if delta <= tol:
                    break
            for i in range(9):
                R[n, i] = x[i]
            for i in range(3):  # S = R^T M
                for j in range(3):
                    S[n, 3 * i + j] = x[i] * M[n, j] + x[3 + i] * M[n, 3 + j] + x[6 + i] * M[n, 6 + j]

    @numba.njit(parallel=True, cache=False)
    def _polar_backward(R, S, G, out):
        # dL/dM = R [y]x, y = (tr(P) I - P)^-1 vee(R^T G - G^T R), P = sym(S) (derivation in polar_rotation_fast).
        for n in numba.prange(R.shape[0]):
            # W = R^T G
            w = np.empty(9)
            for i in range(3):
                for j in range(3):
                    w[3 * i + j] = R[n, i] * G[n, j] + R[n, 3 + i] * G[n, 3 + j] + R[n, 6 + i] * G[n, 6 + j]
            u0 = w[7] - w[5]  # vee(W - W^T) = (W21 - W12, W02 - W20, W10 - W01)
            u1 = w[2] - w[6]
            u2 = w[3] - w[1]
            p00 = S[n, 0]
            p11 = S[n, 4]
            p22 = S[n, 8]
            p01 = 0.5 * (S[n, 1] + S[n, 3])
            p02 = 0.5 * (S[n, 2] + S[n, 6])
            p12 = 0.5 * (S[n, 5] + S[n, 7])
            tr = p00 + p11 + p22
            # K = tr I - P (symmetric, positive definite for P > 0): solve K y = u by cofactors
            k00 = tr - p00
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
                continue
            y0 = (c00 * u0 + c01 * u1 + c02 * u2) / det
            y1 = (c01 * u0 + c11 * u1 + c12 * u2) / det
            y2 = (c02 * u0 + c12 * u1 + c22 * u2) / det
            # [y]x = [[0, -y2, y1], [y2, 0, -y0], [-y1, y0, 0]]; out = R [y]x
            for i in range(3):
                r0 = R[n, 3 * i]
                r1 = R[n, 3 * i + 1]
                r2 = R[n, 3 * i + 2]
                out[n, 3 * i] = r1 * y2 - r2 * y1
                out[n, 3 * i + 1] = -r0 * y2 + r2 * y0
                out[n, 3 * i + 2] = r0 * y1 - r1 * y0


def _threads() -> None:
    numba.set_num_threads(max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)))


class _BasisProduct(torch.autograd.Function):
    @staticmethod
    def forward(ctx, coeffs: Tensor, basis: Tensor) -> Tensor:
        _threads()
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
        _threads()
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
    fast = (numba is not None and coeffs.device.type == "cpu" and basis.device.type == "cpu"
            and coeffs.dtype == basis.dtype and coeffs.dtype in (torch.float32, torch.float64)
            and coeffs.shape[0] > 0 and coeffs.shape[1] > 0 and basis.shape[1] > 0)
    if not fast:
        return torch.einsum("bnk,nkd->bnd", coeffs, basis)
    return _BasisProduct.apply(coeffs, basis)


class _PolarRotation(torch.autograd.Function):
    @staticmethod
    def forward(ctx, M: Tensor, tol: float, max_iters: int) -> Tensor:
        _threads()
        m = M.detach().reshape(-1, 9).to(torch.float64).numpy()
        R = np.empty_like(m)
        S = np.empty_like(m)
        _polar_forward(m, R, S, tol, max_iters)
        ctx.rs = (R, S)
        return torch.from_numpy(R).to(M.dtype).reshape(M.shape)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        R, S = ctx.rs
        _threads()
        out = np.empty_like(R)
        _polar_backward(R, S, grad.detach().reshape(-1, 9).to(torch.float64).numpy(), out)
        return torch.from_numpy(out).to(grad.dtype).reshape(grad.shape), None, None


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
