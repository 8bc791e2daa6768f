"""The compiled per-pixel compositor against the batched torch one (its oracle) on the same tile lists."""

from __future__ import annotations

import pytest
import torch

from gsavatar.render import compositor_numba
from gsavatar.render.compositor import composite

pytestmark = pytest.mark.skipif(not compositor_numba.available(), reason="needs numba")


def splats(n, width, height, n_cams, seed, dtype=torch.float64, opaque=False):
    """Random projected 2D Gaussians (some off-screen, some nearly opaque), radii at 3 sigma."""
    g = torch.Generator().manual_seed(seed)
    means2d = (torch.rand(n, 2, generator=g, dtype=dtype) * 1.2 - 0.1) * torch.tensor([width, height], dtype=dtype)
    L = torch.randn(n, 2, 2, generator=g, dtype=dtype)
    cov = (L @ L.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dtype)) * (
        1 + 6 * torch.rand(n, 1, 1, generator=g, dtype=dtype)
    )
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    opac = (0.9 + 0.1 * torch.rand(n, generator=g, dtype=dtype)) if opaque else torch.rand(n, generator=g, dtype=dtype)
    if opaque:
        opac[: n // 6] = 1.0  # exercises the 0.999 clamp
    colors = torch.rand(n, 4, generator=g, dtype=dtype)
    depths = torch.rand(n, generator=g, dtype=dtype)
    r = (3 * torch.linalg.eigvalsh(cov)[:, 1].sqrt()).ceil().long()
    radii = torch.stack([r, r], 1)
    cams = torch.randint(0, n_cams, (n,), generator=g)
    return means2d, conics, opac, colors, depths, radii, cams


@pytest.mark.parametrize("tile_size", [4, 8, 16])
@pytest.mark.parametrize("opaque", [False, True], ids=["translucent", "opaque"])
def test_numba_equals_dense_values_and_grads(tile_size, opaque):
    width, height, n_cams = 45, 31, 2  # partial tiles on both axes
    inputs = splats(2500 if opaque else 600, width, height, n_cams, seed=tile_size + 10 * opaque, opaque=opaque)
    results = {}
    for method in ("dense", "numba"):
        leaves = [t.clone().requires_grad_(i < 4) for i, t in enumerate(inputs)]
        stats: list = []
        color, alpha = composite(*leaves, n_cams, width, height, tile_size=tile_size, method=method, stats_out=stats)
        g = torch.Generator().manual_seed(3)
        loss = (color * torch.randn(color.shape, generator=g, dtype=color.dtype)).sum() + (
            alpha * torch.randn(alpha.shape, generator=g, dtype=alpha.dtype)
        ).sum()
        results[method] = (color, alpha, torch.autograd.grad(loss, leaves[:4]), stats[0])
    (c0, a0, g0, s0), (c1, a1, g1, s1) = results["dense"], results["numba"]
    torch.testing.assert_close(c1, c0, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(a1, a0, rtol=1e-10, atol=1e-12)
    for name, x, y in zip(("means2d", "conics", "opacities", "colors"), g1, g0):
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-10, msg=name)
    assert s1.n_tile_pairs == s0.n_tile_pairs and s1.n_contributing == s0.n_contributing
    if opaque:
        assert (a0 > 0.999).any(), "the scene should reach the transmittance stop"


def test_numba_float32_close_to_float64():
    width, height = 40, 28
    inputs = splats(400, width, height, 1, seed=5)
    c64, a64 = composite(*inputs, 1, width, height, method="numba")
    c32, a32 = composite(*[t.float() if t.is_floating_point() else t for t in inputs], 1, width, height, method="numba")
    assert c32.dtype == torch.float32
    assert (c32.double() - c64).abs().max() < 1e-4 and (a32.double() - a64).abs().max() < 1e-4


def test_no_instances_and_unknown_method():
    empty = [t[:0] for t in splats(4, 8, 8, 1, seed=0)]
    color, alpha = composite(*empty, 1, 8, 8, method="numba")
    assert color.shape == (1, 8, 8, 4) and not color.any() and not alpha.any()
    with pytest.raises(ValueError, match="method"):
        composite(*empty, 1, 8, 8, method="cuda")
