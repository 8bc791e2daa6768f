"""The compiled kernels against their torch oracles: basis products vs ``einsum``, polar factor vs the torch
iteration (values, closed-form gradients); tests/models/test_recipe.py checks both against the SVD."""

from __future__ import annotations

import pytest
import torch

from gsavatar.models import gaussians as gm

from gsavatar.models import kernels as bp


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("B,N,K,D", [(2, 500, 16, 3), (1, 77, 5, 4), (3, 64, 16, 13)])
def test_values_and_grads_match_einsum(dtype, B, N, K, D):
    g = torch.Generator().manual_seed(B * N + D)
    c = torch.randn(B, N, K, generator=g, dtype=dtype, requires_grad=True)
    m = torch.randn(N, K, D, generator=g, dtype=dtype, requires_grad=True)
    w = torch.randn(B, N, D, generator=g, dtype=dtype)
    got = bp.basis_product(c, m)
    want = torch.einsum("bnk,nkd->bnd", c, m)
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    torch.testing.assert_close(got, want, **tol)
    torch.testing.assert_close(
        torch.autograd.grad((got * w).sum(), (c, m)), torch.autograd.grad((want * w).sum(), (c, m)), **tol
    )


def test_strided_view_and_partial_grads():
    # The SH-band basis is used through a slice [N, K, :n_rest, 3] viewed as [N, K, n_rest * 3].
    g = torch.Generator().manual_seed(0)
    full = torch.randn(50, 8, 15, 3, generator=g, dtype=torch.float64, requires_grad=True)
    c = torch.randn(2, 50, 8, generator=g, dtype=torch.float64)
    view = full[:, :, :3].reshape(50, 8, -1)
    assert not view.is_contiguous()
    got = bp.basis_product(c, view)
    torch.testing.assert_close(got, torch.einsum("bnk,nkd->bnd", c, view))
    (grad,) = torch.autograd.grad(got.square().sum(), full)
    (want,) = torch.autograd.grad(torch.einsum("bnk,nkd->bnd", c, view).square().sum(), full)
    torch.testing.assert_close(grad, want)
    assert not grad[:, :, 3:].any()


def test_gradcheck_and_fallbacks():
    g = torch.Generator().manual_seed(1)
    c = torch.randn(2, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    m = torch.randn(6, 3, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(bp.basis_product, (c, m))
    # mixed dtypes and empty batches take the einsum path
    out = bp.basis_product(c.detach().float(), m.detach().float())
    assert out.dtype == torch.float32
    assert bp.basis_product(c[:0], m).shape == (0, 6, 2)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_polar_closed_form_backward_matches_autograd_of_the_iteration(dtype):
    g = torch.Generator().manual_seed(2)
    M = torch.eye(3, dtype=torch.float64) + 0.4 * torch.randn(300, 3, 3, generator=g, dtype=torch.float64)
    M = M[torch.det(M) > 0.05].to(dtype)  # the compiled path handles det > 0; the caller routes the rest
    G = torch.randn(M.shape, generator=g, dtype=dtype)
    a, b = M.clone().requires_grad_(), M.clone().requires_grad_()
    Qa, Qb = gm.polar_rotation(a, compiled=True), gm.polar_rotation(b, compiled=False)
    tol = {"rtol": 1e-12, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-5}
    torch.testing.assert_close(Qa, Qb, **tol)
    (Qa * G).sum().backward()
    (Qb * G).sum().backward()
    scale = b.grad.abs().max()
    torch.testing.assert_close(a.grad / scale, b.grad / scale, rtol=0, atol=1e-10 if dtype == torch.float64 else 1e-4)
    assert torch.autograd.gradcheck(lambda x: gm.polar_rotation(x, compiled=True), (M[:5].double().requires_grad_(),))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_posed_quaternion_matches_the_torch_composition(dtype):
    from gsavatar.geometry.rotations import axis_angle_to_matrix

    g = torch.Generator().manual_seed(4)
    n = 400
    R3 = axis_angle_to_matrix(torch.randn(3, n, 3, generator=g, dtype=torch.float64) * 1.5)
    w = torch.rand(n, 3, generator=g, dtype=torch.float64)
    A = torch.einsum("nk,knij->nij", w / w.sum(1, keepdim=True), R3)  # LBS-like blends
    A = A * (0.5 + torch.rand(n, 1, 1, generator=g, dtype=torch.float64))  # and a scale
    A = A[torch.det(A) > 1e-2]
    affine = torch.cat([A, torch.randn(A.shape[0], 3, 1, generator=g, dtype=torch.float64)], -1).to(dtype)
    q = torch.nn.functional.normalize(torch.randn(A.shape[0], 4, generator=g, dtype=torch.float64), dim=-1).to(dtype)
    c = torch.randn(A.shape[0], 3, generator=g, dtype=dtype)
    G = torch.randn(A.shape[0], 4, generator=g, dtype=dtype)
    outs = {}
    for compiled in (True, False):
        a, qq = affine.clone().requires_grad_(), q.clone().requires_grad_()
        means, quats = gm.pose_gaussians(c, qq, a, compiled=compiled)
        outs[compiled] = (means, quats, *torch.autograd.grad((quats * G).sum() + means.sum(), (a, qq)))
    tol = {"rtol": 1e-10, "atol": 1e-10} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 2e-5}
    assert (outs[True][1][:, 0] >= 0).all()
    for x, y, name in zip(outs[True], outs[False], ("means", "quats", "d affine", "d quats")):
        torch.testing.assert_close(x, y, **tol, msg=name)


def test_posed_quaternion_zero_and_singular_inputs():
    I = torch.eye(3, dtype=torch.float64)
    affine = torch.cat(
        [
            torch.stack([I, 2 * I, 0.5 * (I + torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)))]),
            torch.zeros(3, 3, 1, dtype=torch.float64),
        ],
        -1,
    ).requires_grad_()
    q = torch.tensor([[0.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [1.0, 0, 0, 0]], dtype=torch.float64).requires_grad_()
    c = torch.zeros(3, 3, dtype=torch.float64)
    a_means, a_quats = gm.pose_gaussians(c, q, affine, compiled=True)  # a singular blend: the SVD path for all
    _, b_quats = gm.pose_gaussians(c, q, affine, compiled=False)
    torch.testing.assert_close(a_quats, b_quats)
    _, ok = gm.pose_gaussians(c[:2], q[:2], affine[:2], compiled=True)  # the compiled path, zero quaternion
    torch.testing.assert_close(ok[0], torch.tensor([1.0, 0, 0, 0], dtype=torch.float64))
    ok.sum().backward()
    assert torch.isfinite(q.grad).all() and torch.isfinite(affine.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sparse_interpolation_matches_torch_sparse_mm(dtype):
    g = torch.Generator().manual_seed(6)
    N, M, k, B, D = 700, 40, 3, 2, 5
    idx = torch.randint(0, M, (N, k), generator=g)
    idx[:5] = idx[:5, :1]  # repeated sources add up
    w = torch.rand(N, k, generator=g, dtype=torch.float64).to(dtype)
    mat = gm.interpolation_matrix(idx, w, M + 3)  # 3 sources no row uses: empty rows of the transpose
    vals = torch.randn(B, M + 3, D, generator=g, dtype=dtype)
    G = torch.randn(B, N, D, generator=g, dtype=dtype)
    outs = []
    for compiled in (True, False):
        v = vals[:, :, :].clone().requires_grad_()
        out = gm.sparse_interpolate(v, mat, compiled=compiled)
        outs.append((out, *torch.autograd.grad((out * G).sum(), v)))
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    for a, b in zip(*outs):
        torch.testing.assert_close(a, b, **tol)
    # and against the gather oracle
    torch.testing.assert_close(outs[0][0], gm.interpolate(vals, idx, w), **tol)
    # a strided view (a slice of the coefficients) gives the same
    wide = torch.randn(B, M + 3, 2 * D, generator=g, dtype=dtype)
    torch.testing.assert_close(
        gm.sparse_interpolate(wide[..., :D], mat), gm.sparse_interpolate(wide[..., :D], mat, compiled=False), **tol
    )
