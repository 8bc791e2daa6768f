from __future__ import annotations

import pytest
import torch

from gsavatar.models.encoder import AppearanceEncoder, encoder_channels, mask_texture, reparameterize, sample_at_uv


def test_channels_and_grid_size():
    assert encoder_channels() == [8, 16, 32, 64, 128]
    enc = AppearanceEncoder(latent_dim=16)
    for S in (64, 128):
        x = torch.rand(2, 3, S, S)
        h = enc.features(x)
        assert h.shape == (2, 128, S // 32, S // 32)
        out = enc.eval()(x)
        assert out.mu.shape == out.logvar.shape == out.latent_map.shape == (2, 16, S // 32, S // 32)
    norms = [m for m in enc.trunk if isinstance(m, torch.nn.GroupNorm)]
    assert [m.num_groups for m in norms] == [8] * 5
    assert len([m for m in enc.trunk if isinstance(m, torch.nn.Conv2d)]) == 5


def test_mu_without_noise_and_the_one_sampling_path_with_it():
    torch.manual_seed(0)
    enc = AppearanceEncoder(latent_dim=4)
    x = torch.rand(1, 3, 64, 64)
    for mode in (enc.eval, enc.train):  # the mode does not decide: the caller's noise does
        mode()
        out = enc(x)
        assert torch.equal(out.latent_map, out.mu)
    eps = torch.randn(1, 4, 2, 2, generator=torch.Generator().manual_seed(3))
    a = enc(x, eps)
    assert torch.equal(a.latent_map, reparameterize(a.mu, a.logvar, eps))
    assert not torch.allclose(a.latent_map, a.mu)
    assert a.logvar.min() >= -30 and a.logvar.max() <= 20
    # float64 oracle of the sample: mu + sigma * eps
    want = a.mu.double() + torch.exp(0.5 * a.logvar.double()) * eps.double()
    torch.testing.assert_close(a.latent_map.double(), want, rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="eps"):
        enc(x, eps[..., :1])


@pytest.mark.parametrize("shape", [(1, 3, 32, 32), (1, 3, 96, 96), (1, 1, 64, 64), (3, 64, 64)])
def test_bad_texture_shapes(shape):
    with pytest.raises(ValueError, match="texture"):
        AppearanceEncoder()(torch.rand(*shape))


def _manual_bilinear(m, uv):
    """Reference lookup with border clamping: texel (r, c) centre at u=(c+.5)/w, v=1-(r+.5)/h."""
    B, L, h, w = m.shape
    out = torch.empty(B, len(uv), L, dtype=m.dtype)
    for i, (u, v) in enumerate(uv.tolist()):
        x = min(max(u * w - 0.5, 0.0), w - 1.0)
        y = min(max((1.0 - v) * h - 0.5, 0.0), h - 1.0)
        x0, y0 = int(x), int(y)
        x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
        fx, fy = x - x0, y - y0
        out[:, i] = (
            m[:, :, y0, x0] * (1 - fx) * (1 - fy)
            + m[:, :, y0, x1] * fx * (1 - fy)
            + m[:, :, y1, x0] * (1 - fx) * fy
            + m[:, :, y1, x1] * fx * fy
        )
    return out


def test_sample_at_uv_texel_centres_corners_and_random():
    torch.manual_seed(0)
    h, w = 4, 5
    m = torch.randn(2, 3, h, w, dtype=torch.float64)
    rr, cc = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    cc, rr = cc.flatten().double(), rr.flatten().double()
    uv = torch.stack([(cc + 0.5) / w, 1 - (rr + 0.5) / h], -1)
    got = sample_at_uv(m, uv)  # [B, h*w, L]
    assert got.shape == (2, h * w, 3)
    torch.testing.assert_close(got, m.flatten(2).transpose(1, 2), rtol=0, atol=1e-12)
    corners = torch.tensor([[0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    got = sample_at_uv(m, corners)
    want = torch.stack([m[:, :, h - 1, 0], m[:, :, 0, w - 1], m[:, :, 0, 0], m[:, :, h - 1, w - 1]], 1)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    rnd = torch.rand(50, 2, dtype=torch.float64)
    torch.testing.assert_close(sample_at_uv(m, rnd), _manual_bilinear(m, rnd), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="uv"):
        sample_at_uv(m, torch.rand(5, 3))


def test_mask_texture():
    tex = torch.rand(2, 3, 64, 64)
    mask = torch.zeros(8, 8, dtype=torch.bool)
    mask[:2, :4] = True  # top-left quarter-width strip (v near 1, u < 0.5)
    out = mask_texture(tex, mask)
    assert (out[:, :, :16, :32] == 0).all()
    assert torch.equal(out[:, :, 16:], tex[:, :, 16:])
    assert torch.equal(out[:, :, :, 32:], tex[:, :, :, 32:])
