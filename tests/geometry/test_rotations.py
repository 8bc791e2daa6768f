"""quat_to_matrix, the one quaternion -> rotation of the code base (the model's posed rotations and the
renderer's covariances), against roma when it is installed and an independent float64 oracle otherwise."""

from __future__ import annotations

import pytest
import torch

from gsavatar.geometry.rotations import matrix_to_quat, quat_to_matrix
from gsavatar.render.projection import covariance_factor

TOL = {torch.float64: dict(rtol=1e-12, atol=1e-12), torch.float32: dict(rtol=1e-5, atol=1e-6)}
"""Forward and gradient tolerances against the float64 oracle, per input dtype."""


def hamilton(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Quaternion product a * b, wxyz. [..., 4] x [..., 4] -> [..., 4]"""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def oracle(q: torch.Tensor) -> torch.Tensor:
    """R(q) column by column: ``q e_i q* / |q|^2`` by quaternion products, float64. [..., 4] -> [..., 3, 3]"""
    q = q.double()
    conj = q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)
    cols = []
    for i in range(3):
        e = torch.zeros(*q.shape[:-1], 4, dtype=q.dtype)
        e[..., i + 1] = 1.0
        cols.append(hamilton(hamilton(q, e), conj)[..., 1:] / (q * q).sum(-1, keepdim=True))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_quat_to_matrix_against_the_oracle_forward_and_gradient(dtype):
    g = torch.Generator().manual_seed(0)
    q = torch.randn(64, 4, generator=g, dtype=torch.float64) * torch.logspace(-3, 3, 64, dtype=torch.float64)[:, None]
    w = torch.randn(64, 3, 3, generator=g, dtype=torch.float64)
    x = q.to(dtype).requires_grad_(True)
    R = quat_to_matrix(x)
    (gx,) = torch.autograd.grad((R * w.to(dtype)).sum(), x)
    q64 = x.detach().double().requires_grad_(True)
    R64 = oracle(q64)
    (g64,) = torch.autograd.grad((R64 * w).sum(), q64)
    torch.testing.assert_close(R.double(), R64, **TOL[dtype])
    scale = q64.detach().norm(dim=-1, keepdim=True)  # the gradient scales as 1 / |q|
    torch.testing.assert_close(gx.double() * scale, g64 * scale, **TOL[dtype])
    # rotations: orthonormal with det +1, any norm; zero -> identity
    eye = torch.eye(3, dtype=dtype).expand(64, 3, 3)
    torch.testing.assert_close(R.detach() @ R.detach().mT, eye, **TOL[dtype])
    torch.testing.assert_close(torch.linalg.det(R.detach()), torch.ones(64, dtype=dtype), **TOL[dtype])
    assert torch.equal(quat_to_matrix(torch.zeros(2, 4, dtype=dtype)), torch.eye(3, dtype=dtype).expand(2, 3, 3))
    torch.testing.assert_close(
        matrix_to_quat(R.detach()).abs(), (x / x.norm(dim=-1, keepdim=True)).detach().abs(), **TOL[dtype]
    )


def test_quat_to_matrix_matches_roma():
    roma = pytest.importorskip("roma")
    q = torch.randn(100, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    want = roma.unitquat_to_rotmat(q[:, [1, 2, 3, 0]])  # roma is xyzw
    torch.testing.assert_close(quat_to_matrix(q), want, rtol=0, atol=1e-14)


def test_the_renderer_uses_it():
    q = torch.randn(5, 4, generator=torch.Generator().manual_seed(2))
    s = torch.rand(5, 3) + 0.1
    assert torch.equal(covariance_factor(q, s), quat_to_matrix(q) * s[:, None, :])
