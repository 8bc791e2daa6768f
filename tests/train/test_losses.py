"""Loss terms against hand-computed values on tiny tensors; robustness at extremes."""

from __future__ import annotations

import math

import pytest
import torch

from gsavatar.runs.config import LossWeights
from gsavatar.train.losses import (
    cpt_smoothness_loss,
    min_filter_mask,
    kl_loss,
    l1_loss,
    opacity_loss,
    scale_loss,
    total_loss,
)


def test_loss_weights_defaults_are_the_papers():
    w = LossWeights()
    assert w.as_dict() == {"l1": 1.0, "lpips": 0.1, "opac": 0.5, "scale": 1.0, "cpt": 0.5, "kl": 1e-6}
    with pytest.raises(ValueError, match="LossWeights.kl"):
        LossWeights(kl=-1.0)


def test_l1_hand_computed():
    pred = torch.tensor([[[[0.0, 1.0], [0.5, 0.25]]]])  # [1, 1, 2, 2]
    gt = torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]]])
    # |.| = 1, 0, 0.5, 0.25 -> mean 0.4375
    assert l1_loss(pred, gt).item() == pytest.approx(0.4375)
    with pytest.raises(ValueError, match="gt"):
        l1_loss(pred, gt[..., :1])


def test_erode_mask_hand_computed():
    m = torch.zeros(1, 1, 5, 6)
    m[..., 1:5, 1:6] = 1.0  # touches bottom and right image borders
    e = min_filter_mask(m, 1)
    expected = torch.zeros(1, 1, 5, 6)
    # 3x3 min-filter; outside the image does not erode -> rows 2..4, cols 2..5
    expected[..., 2:5, 2:6] = 1.0
    assert torch.equal(e, expected)
    assert torch.equal(min_filter_mask(m, 0), m)
    assert min_filter_mask(m > 0.5, 1).dtype == torch.float32
    assert torch.equal(min_filter_mask(m > 0.5, 1), expected)
    e3 = min_filter_mask(m, 3)  # 7x7 window: only pixels whose in-image window is all ones
    assert e3.nonzero().tolist() == [[0, 0, 4, 4], [0, 0, 4, 5]]
    soft = m * 0.5
    soft[..., 3, 3] = 0.2
    assert min_filter_mask(soft, 1)[0, 0, 3, 3].item() == pytest.approx(0.2)  # min-filter
    assert min_filter_mask(soft, 1)[0, 0, 4, 5].item() == pytest.approx(0.5)
    with pytest.raises(ValueError, match="px"):
        min_filter_mask(m, -1)
    with pytest.raises(ValueError, match="mask"):
        min_filter_mask(m[0], 1)


def test_opacity_loss_hand_computed():
    alpha = torch.tensor([[[[1.0, 0.5], [0.25, 0.0]]]])
    mask = torch.tensor([[[[1.0, 1.0], [1.0, 0.0]]]])
    # inside mask: 1-alpha = 0, 0.5, 0.75 -> mean 1.25 / 3
    assert opacity_loss(alpha, mask).item() == pytest.approx(1.25 / 3)
    # pooled over the batch, not a mean of per-image means
    a2 = torch.cat([alpha, torch.zeros_like(alpha)])
    m2 = torch.cat([mask, torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]]])])
    assert opacity_loss(a2, m2).item() == pytest.approx((1.25 + 1.0) / 4)


def test_opacity_loss_extremes_and_empty_mask():
    ones = torch.ones(2, 1, 4, 4)
    assert opacity_loss(ones, ones).item() == 0.0
    assert opacity_loss(torch.zeros_like(ones), ones).item() == 1.0
    assert opacity_loss(torch.zeros_like(ones), torch.zeros_like(ones)).item() == 0.0
    a = torch.zeros(2, 1, 4, 4, requires_grad=True)
    opacity_loss(a, ones).backward()
    assert torch.isfinite(a.grad).all()
    assert torch.allclose(a.grad, torch.full_like(a, -1.0 / 32))
    with pytest.raises(ValueError, match="eroded_mask"):
        opacity_loss(ones, ones[:, :, :2])


def test_scale_loss_hand_computed():
    scales = torch.tensor([[[0.01, 0.02, 0.03], [0.10, 0.01, 0.01]], [[0.05, 0.06, 0.01], [0.0, 0.0, 0.0]]])
    # max axis: 0.03, 0.10, 0.06, 0.0 ; threshold 0.05 -> 0, 0.05, 0.01, 0 -> mean 0.015
    assert scale_loss(scales, 0.05).item() == pytest.approx(0.015)
    assert scale_loss(scales, 1.0).item() == 0.0
    s = scales.clone().requires_grad_(True)
    scale_loss(s, 0.05).backward()
    g = torch.zeros_like(scales)
    g[0, 1, 0] = g[1, 0, 1] = 0.25  # only the largest axis of the offending Gaussians
    assert torch.allclose(s.grad, g)
    with pytest.raises(ValueError, match="scales"):
        scale_loss(scales[..., :2], 0.05)
    with pytest.raises(ValueError, match="threshold"):
        scale_loss(scales, -0.1)


def test_cpt_smoothness_hand_computed():
    disp = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]])  # [1, 3, 3]
    neighbors = torch.tensor([[1, 2], [0, 2], [0, 1]])  # [3, 2]
    # squared distances: 0-1: 1, 0-2: 4, 1-2: 1 + 4 = 5; each pair counted from both sides
    # rows: (1 + 4), (1 + 5), (4 + 5) -> total 20 over 6 pairs
    assert cpt_smoothness_loss(disp, neighbors).item() == pytest.approx(20 / 6)
    # a rigid translation costs nothing
    assert cpt_smoothness_loss(torch.ones(2, 3, 3) * 5.0, neighbors).item() == 0.0
    with pytest.raises(ValueError, match="neighbors"):
        cpt_smoothness_loss(disp, neighbors[:2])
    with pytest.raises(ValueError, match="neighbors"):
        cpt_smoothness_loss(disp, neighbors.float())
    with pytest.raises(ValueError, match="ctrl_disp"):
        cpt_smoothness_loss(disp[..., :2], neighbors)


def test_kl_hand_computed():
    mu = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    logvar = torch.tensor([[0.0, math.log(2.0)], [0.0, 0.0]])
    # sample 0: 0.5*(1 + 1 - 1 - 0) + 0.5*(0 + 2 - 1 - ln2) = 0.5 + 0.5*(1 - ln2)
    # sample 1: 0.5*(0) + 0.5*(4) = 2
    s0 = 0.5 + 0.5 * (1 - math.log(2.0))
    assert kl_loss(mu, logvar).item() == pytest.approx((s0 + 2.0) / 2, rel=1e-6)
    z = torch.zeros(3, 4, 2, 2)
    assert kl_loss(z, z).item() == 0.0
    with pytest.raises(ValueError, match="logvar"):
        kl_loss(mu, logvar[:, :1])


@pytest.mark.parametrize("lv", [-50.0, 50.0])
def test_kl_finite_at_extreme_logvar(lv):
    mu = torch.zeros(2, 16, 4, 4, requires_grad=True)
    logvar = torch.full((2, 16, 4, 4), lv, requires_grad=True)
    v = kl_loss(mu, logvar)
    v.backward()
    assert torch.isfinite(v) and v.item() > 0
    assert torch.isfinite(logvar.grad).all() and torch.isfinite(mu.grad).all()


def test_kl_against_float64_oracle():
    # The one KL of the code base (the encoder has none): per sample the sum over every latent element, then
    # the mean over the batch, the scale the paper's 1e-6 weight is applied to in training.
    g = torch.Generator().manual_seed(0)
    mu, logvar = torch.randn(3, 16, 4, 4, generator=g), torch.randn(3, 16, 4, 4, generator=g) * 3
    m, lv = mu.double(), logvar.double()
    want = (0.5 * (m * m + lv.exp() - 1.0 - lv)).flatten(1).sum(1).mean()
    torch.testing.assert_close(kl_loss(mu, logvar).double(), want, rtol=1e-6, atol=0)
    # one element: 0.5 * (mu^2 + e^lv - 1 - lv); a 1-D input is one sample per element
    assert kl_loss(torch.tensor([1.0]), torch.tensor([0.0])).item() == pytest.approx(0.5, abs=1e-7)
    for lv in (1e4, -1e4):  # finite value and gradient far outside the encoder's clamped range
        x = torch.full((2, 4, 3, 3), lv, requires_grad=True)
        kl_loss(mu[:2, :4, :3, :3], x).backward()
        assert torch.isfinite(x.grad).all()


def test_total_loss_weights_and_logs():
    w = LossWeights()
    terms = {
        "l1": torch.tensor(0.2, requires_grad=True),
        "lpips": torch.tensor(0.5),
        "opac": torch.tensor(0.1),
        "scale": torch.tensor(0.01),
        "cpt": torch.tensor(0.02),
        "kl": torch.tensor(1000.0),
    }
    total, logs = total_loss(terms, w)
    expected = 0.2 + 0.1 * 0.5 + 0.5 * 0.1 + 1.0 * 0.01 + 0.5 * 0.02 + 1e-6 * 1000.0
    assert total.item() == pytest.approx(expected, rel=1e-6)
    assert set(logs) == set(terms) | {"total"}
    assert all(isinstance(v, float) for v in logs.values())
    assert logs["kl"] == pytest.approx(1000.0) and logs["total"] == pytest.approx(expected, rel=1e-6)
    total.backward()
    assert terms["l1"].grad.item() == 1.0


def test_total_loss_skips_absent_and_zero_weighted_terms():
    terms = {"l1": torch.tensor(0.3), "kl": torch.tensor(float("nan"))}
    total, logs = total_loss(terms, LossWeights(kl=0.0))
    assert total.item() == pytest.approx(0.3)
    assert math.isnan(logs["kl"])
    with pytest.raises(ValueError, match="unknown"):
        total_loss({"l2": torch.tensor(1.0)}, LossWeights())
    with pytest.raises(ValueError, match="scalar"):
        total_loss({"l1": torch.ones(2)}, LossWeights())


def test_end_to_end_extremes_are_finite():
    """All terms together at alpha in {0, 1}, logvar = +-50: finite loss and grads."""
    B, H, W = 2, 8, 8
    pred = torch.rand(B, 3, H, W, requires_grad=True)
    gt = torch.rand(B, 3, H, W)
    alpha = torch.zeros(B, 1, H, W)
    alpha[1] = 1.0
    alpha.requires_grad_(True)
    mask = torch.ones(B, 1, H, W)
    scales = torch.rand(B, 10, 3, requires_grad=True)
    disp = torch.randn(B, 6, 3, requires_grad=True)
    nb = torch.randint(0, 6, (6, 5))
    mu = torch.zeros(B, 4, requires_grad=True)
    logvar = torch.tensor([[-50.0] * 4, [50.0] * 4], requires_grad=True)
    terms = {
        "l1": l1_loss(pred, gt),
        "opac": opacity_loss(alpha, min_filter_mask(mask, 1)),
        "scale": scale_loss(scales, 0.5),
        "cpt": cpt_smoothness_loss(disp, nb),
        "kl": kl_loss(mu, logvar),
    }
    total, logs = total_loss(terms, LossWeights())
    total.backward()
    assert math.isfinite(total.item()) and all(math.isfinite(v) for v in logs.values())
    for t in (pred, alpha, scales, disp, mu, logvar):
        assert torch.isfinite(t.grad).all()
