"""The one PCA clamp (``clamp_coefficients``) and projection (``pca_project``) against a naive float64 oracle,
and every user of them: PosePCA (numpy and torch), the avatar's and the predictor's conditioning pose (the
same function), the predictor's per-anchor latent PCA."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.data_schema.pose_pca import PosePCA, clamp_coefficients, pca_project
from gsavatar.models.predictor import latent_pca_project


def naive_clamp(c: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Element by element: the nearest value of [-limit, limit]."""
    out = np.empty_like(c, dtype=np.float64)
    for idx in np.ndindex(c.shape):
        lim = float(limit[idx[-1]])
        out[idx] = min(max(float(c[idx]), -lim), lim)
    return out


def naive_project(x: np.ndarray, mean: np.ndarray, basis: np.ndarray, limit: np.ndarray) -> np.ndarray:
    return naive_clamp((x - mean) @ basis, limit) @ basis.T + mean


@pytest.fixture(scope="module")
def box():
    rng = np.random.default_rng(0)
    P, C = 7, 4
    basis, _ = np.linalg.qr(rng.normal(size=(P, C)))  # unit, orthogonal columns
    return rng.normal(size=P), basis, rng.uniform(0.1, 1.0, size=C), rng.normal(size=(20, P)) * 1.5


def test_clamp_against_the_oracle_values_and_gradient(box):
    _, _, limit, _ = box
    c = np.random.default_rng(1).normal(size=(20, 4)) * 2
    np.testing.assert_array_equal(clamp_coefficients(c, limit), naive_clamp(c, limit))
    ct = torch.from_numpy(c).requires_grad_(True)
    got = clamp_coefficients(ct, torch.from_numpy(limit))
    np.testing.assert_array_equal(got.detach().numpy(), naive_clamp(c, limit))
    got.sum().backward()
    np.testing.assert_array_equal(ct.grad.numpy(), (np.abs(c) < limit).astype(np.float64))  # 0 where clamped


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_project_against_the_oracle(box, dtype):
    mean, basis, limit, x = box
    want = naive_project(x, mean, basis, limit)
    np.testing.assert_allclose(pca_project(x, mean, basis, limit), want, rtol=0, atol=1e-12)
    t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    np.testing.assert_allclose(pca_project(t(x), t(mean), t(basis), t(limit)).double().numpy(), want, rtol=0, atol=tol)


def test_pose_pca_and_latent_pca_use_it(box):
    mean, basis, limit, x = box
    pca = PosePCA("global", mean, basis, limit / 2.0, np.zeros(4, np.int64), np.zeros(7, np.int64), clamp_sigma=2.0)
    want = naive_project(x, mean, basis, limit)
    np.testing.assert_array_equal(pca.project(x), pca_project(x, mean, basis, 2.0 * (limit / 2.0)))
    np.testing.assert_allclose(pca.project(torch.from_numpy(x)).numpy(), want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pca.clamp(x @ basis), clamp_coefficients(x @ basis, limit))
    # per-anchor latent PCA: anchor a's box is the same projection with its own mean / basis / limit
    t = torch.from_numpy
    lat = latent_pca_project(
        t(x)[:, None].expand(20, 3, 7), t(mean).expand(3, 7), t(basis).expand(3, 7, 4), t(limit).expand(3, 4)
    )
    for a in range(3):
        np.testing.assert_allclose(lat[:, a].numpy(), want, rtol=0, atol=1e-12)
