"""PSNR / SSIM against naive float64 numpy references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from gsavatar.metrics.image import gaussian_kernel1d, mse, psnr, ssim, ssim_map


def _rand_pair(B=2, C=3, H=16, W=14, seed=0, noise=0.1):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(B, C, H, W, generator=g, dtype=torch.float64)
    y = (x + noise * torch.randn(B, C, H, W, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x, y


# ---------------------------------------------------------------------- PSNR


def _psnr_ref(x: np.ndarray, y: np.ndarray, m: np.ndarray | None = None) -> float:
    """x, y: [C, H, W]; m: [H, W] weights."""
    C, H, W = x.shape
    num = 0.0
    den = 0.0
    for c in range(C):
        for i in range(H):
            for j in range(W):
                w = 1.0 if m is None else float(m[i, j])
                num += w * (x[c, i, j] - y[c, i, j]) ** 2
                den += w
    return 10.0 * math.log10(1.0 / (num / den))


def test_psnr_matches_reference_without_mask():
    x, y = _rand_pair()
    got = psnr(x, y)
    assert got.shape == (2,)
    for b in range(2):
        assert got[b].item() == pytest.approx(_psnr_ref(x[b].numpy(), y[b].numpy()), abs=1e-10)


@pytest.mark.parametrize("layout", ["b1hw", "bhw", "bchw", "soft"])
def test_psnr_masked_matches_reference(layout):
    x, y = _rand_pair(seed=1)
    g = torch.Generator().manual_seed(5)
    m = torch.rand(2, 1, 16, 14, generator=g) > 0.4
    if layout == "soft":
        m = torch.rand(2, 1, 16, 14, generator=g, dtype=torch.float64)
    mask = {"b1hw": m, "soft": m, "bhw": m[:, 0], "bchw": m.expand(2, 3, 16, 14)}[layout]
    got = psnr(x, y, mask=mask)
    for b in range(2):
        ref = _psnr_ref(x[b].numpy(), y[b].numpy(), m[b, 0].double().numpy())
        assert got[b].item() == pytest.approx(ref, abs=1e-10)


def test_psnr_mask_restricts_error_region():
    x = torch.zeros(1, 3, 8, 8)
    y = x.clone()
    y[..., :4] = 0.5  # error only in the left half
    right = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    right[..., 4:] = True
    assert torch.isinf(psnr(x, y, mask=right)).all()
    assert psnr(x, y, mask=~right).item() == pytest.approx(10 * math.log10(1 / 0.25), abs=1e-4)
    assert psnr(x, y).item() == pytest.approx(10 * math.log10(1 / 0.125), abs=1e-4)


def test_psnr_identical_is_inf_and_data_range():
    x, y = _rand_pair()
    assert torch.isinf(psnr(x, x)).all()
    assert torch.allclose(psnr(255 * x, 255 * y, data_range=255.0), psnr(x, y))
    assert torch.allclose(mse(x, y), ((x - y) ** 2).flatten(1).mean(1))


def test_psnr_rejects_bad_shapes():
    x, y = _rand_pair()
    with pytest.raises(ValueError, match="gt"):
        psnr(x, y[:, :2])
    with pytest.raises(ValueError, match="mask"):
        psnr(x, y, mask=torch.ones(2, 2, 16, 14))
    with pytest.raises(ValueError, match="pred"):
        psnr(x[0], y[0])
    with pytest.raises(ValueError, match="data_range"):
        psnr(x, y, data_range=0)


# ---------------------------------------------------------------------- SSIM


def _gauss_window_ref(sigma=1.5, radius=5) -> np.ndarray:
    w = np.zeros((2 * radius + 1, 2 * radius + 1))
    for i in range(-radius, radius + 1):
        for j in range(-radius, radius + 1):
            w[i + radius, j + radius] = math.exp(-(i * i + j * j) / (2 * sigma * sigma))
    return w / w.sum()


def _ssim_ref(x: np.ndarray, y: np.ndarray) -> float:
    """Naive SSIM: explicit loop over every valid 11x11 window, float64. x, y: [C, H, W]."""
    w = _gauss_window_ref()
    c1, c2 = (0.01 * 1.0) ** 2, (0.03 * 1.0) ** 2
    C, H, W = x.shape
    vals = []
    for c in range(C):
        for i in range(H - 10):
            for j in range(W - 10):
                px = x[c, i : i + 11, j : j + 11]
                py = y[c, i : i + 11, j : j + 11]
                mx = (w * px).sum()
                my = (w * py).sum()
                vx = (w * (px - mx) ** 2).sum()
                vy = (w * (py - my) ** 2).sum()
                cxy = (w * (px - mx) * (py - my)).sum()
                vals.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


def _ssim_skimage_algorithm(x: np.ndarray, y: np.ndarray) -> float:
    """skimage.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1), re-stated with scipy (x, y: [C, H, W])."""
    per_channel = []
    for c in range(x.shape[0]):
        f = lambda a: gaussian_filter(a, sigma=1.5, truncate=3.5)  # noqa: E731
        ux, uy = f(x[c]), f(y[c])
        vx = f(x[c] * x[c]) - ux * ux
        vy = f(y[c] * y[c]) - uy * uy
        vxy = f(x[c] * y[c]) - ux * uy
        c1, c2 = 0.01**2, 0.03**2
        s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
        per_channel.append(s[5:-5, 5:-5].mean())
    return float(np.mean(per_channel))


def test_gaussian_kernel_matches_scipy_taps():
    k = gaussian_kernel1d(dtype=torch.float64).numpy()
    impulse = np.zeros(31)
    impulse[15] = 1.0
    ref = gaussian_filter(impulse, sigma=1.5, truncate=3.5)[10:21]
    assert k.shape == (11,)
    np.testing.assert_allclose(k, ref, atol=1e-15)


def test_ssim_matches_naive_window_loop():
    x, y = _rand_pair(B=2, C=3, H=16, W=14, seed=2, noise=0.2)
    got = ssim(x, y)
    assert got.shape == (2,)
    for b in range(2):
        assert got[b].item() == pytest.approx(_ssim_ref(x[b].numpy(), y[b].numpy()), abs=1e-12)


def test_ssim_matches_skimage_algorithm_on_structured_image():
    H, W = 48, 41
    yy, xx = np.meshgrid(np.linspace(0, 1, H), np.linspace(0, 1, W), indexing="ij")
    base = np.stack([xx, yy, 0.5 + 0.5 * np.sin(12 * xx * yy)])  # [3, H, W]
    rng = np.random.default_rng(0)
    noisy = np.clip(base + 0.05 * rng.standard_normal(base.shape), 0, 1)
    got = ssim(torch.from_numpy(base)[None], torch.from_numpy(noisy)[None]).item()
    assert got == pytest.approx(_ssim_skimage_algorithm(base, noisy), abs=1e-12)
    # float32 path agrees to float32 precision
    got32 = ssim(torch.from_numpy(base)[None].float(), torch.from_numpy(noisy)[None].float()).item()
    assert got32 == pytest.approx(got, abs=1e-5)


def test_ssim_identity_symmetry_and_range():
    x, y = _rand_pair(H=20, W=20, seed=3)
    assert torch.allclose(ssim(x, x), torch.ones(2, dtype=x.dtype), atol=1e-12)
    assert torch.allclose(ssim(x, y), ssim(y, x), atol=1e-14)
    s = ssim(x, y)
    assert ((s < 1) & (s > -1)).all()
    const = torch.full((1, 3, 12, 12), 0.3, dtype=torch.float64)
    assert ssim(const, const).item() == pytest.approx(1.0)
    assert ssim_map(x, y).shape == (2, 3, 10, 10)


def test_ssim_is_differentiable():
    x, y = _rand_pair(B=1, C=1, H=12, W=12, seed=4)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a: ssim(a, y), (x,))
    x32 = x.detach().float().requires_grad_(True)
    (1 - ssim(x32, y.float())).sum().backward()
    assert torch.isfinite(x32.grad).all() and x32.grad.abs().sum() > 0


def test_ssim_rejects_small_or_mismatched_images():
    x, y = _rand_pair(H=10, W=20)
    with pytest.raises(ValueError, match="11x11"):
        ssim(x, y)
    x, y = _rand_pair()
    with pytest.raises(ValueError, match="gt"):
        ssim(x, y[..., :-1])
