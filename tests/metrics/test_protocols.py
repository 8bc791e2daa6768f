"""The field's ``ag`` protocol against hand-computed cases."""

from __future__ import annotations

import math

import torch

from gsavatar.metrics.protocols import ag_scores, mask_bbox, on_white, square_crop


def test_on_white_recomposites_black_and_grey_backgrounds():
    img = torch.tensor([0.2, 0.4, 0.6]).reshape(3, 1, 1).expand(3, 2, 2).clone()
    cov = torch.tensor([[1.0, 0.0], [0.5, 0.25]])[None]
    # a render of colour c with alpha a on black is a c; on white it is a c + (1 - a)
    out = on_white(img * cov, cov, 0.0)
    torch.testing.assert_close(out, img * cov + (1 - cov))
    grey = torch.tensor([0.5, 0.5, 0.5])
    out2 = on_white(img * cov + grey.reshape(3, 1, 1) * (1 - cov), cov, grey)
    torch.testing.assert_close(out2, out)


def test_square_crop_pads_the_short_side_with_white_and_centres():
    img = torch.zeros(3, 10, 10)
    img[:, 2:8, 4:6] = torch.arange(12.0).reshape(6, 2) / 12  # a 6 x 2 box
    mask = torch.zeros(1, 10, 10)
    mask[:, 2:8, 4:6] = 1
    box = mask_bbox(mask)
    assert box == (2, 8, 4, 6)
    sq = square_crop(img, box, size=6)  # 6 x 6 square at its own size: no resampling
    torch.testing.assert_close(sq[:, :, 2:4], img[:, 2:8, 4:6])  # (6 - 2) // 2 = 2 columns of white before
    assert torch.all(sq[:, :, :2] == 1) and torch.all(sq[:, :, 4:] == 1)
    assert mask_bbox(torch.zeros(1, 4, 4)) is None


def test_ag_psnr_and_ssim_over_the_full_white_image():
    H = W = 16
    gt = torch.ones(3, H, W)
    mask = torch.zeros(1, H, W)
    mask[:, 4:12, 4:12] = 1
    gt[:, 4:12, 4:12] = 0.5
    pred = gt.clone()
    pred[:, 4:12, 4:12] = 0.6  # error 0.1 on 64 of 256 pixels: MSE = 0.01 * 64 / 256
    s = ag_scores(pred, gt, mask)
    assert math.isclose(s["psnr"], -10 * math.log10(0.01 * 64 / 256), rel_tol=1e-5)
    assert 0 < s["ssim"] < 1
    assert ag_scores(gt, gt, mask)["ssim"] > 0.9999


class _MeanAbs(torch.nn.Module):
    """A stand-in LPIPS: mean |a - b| of what it is given, and the shape it saw."""

    def __init__(self):
        super().__init__()
        self.w = torch.nn.Parameter(torch.zeros(1))
        self.seen = None

    def forward(self, a, b):
        self.seen = tuple(a.shape)
        return (a - b).abs().mean((1, 2, 3))


def test_ag_lpips_sees_the_square_crop_at_512():
    H, W = 40, 60
    gt = torch.ones(3, H, W)
    mask = torch.zeros(1, H, W)
    mask[:, 10:30, 20:30] = 1
    gt[:, 10:30, 20:30] = 0.0
    pred = gt.clone()
    pred[:, 10:30, 20:30] = 0.5  # inside the box only: the crop's error is 0.5 on the box's share of the square
    net = _MeanAbs()
    s = ag_scores(pred, gt, mask, {"vgg": net})
    assert net.seen == (1, 3, 512, 512)
    assert math.isclose(s["lpips_vgg"], 0.5 * (10 / 20), rel_tol=2e-2)  # box 20 x 10 in a 20 x 20 square
    assert math.isnan(ag_scores(pred, gt, torch.zeros(1, H, W), {"vgg": net})["lpips_vgg"])


def test_sequence_metrics_refuse_a_non_positive_ag_lpips_stride():
    import pytest

    from gsavatar.drive.metrics import SequenceMetrics

    with pytest.raises(ValueError, match="ag_lpips_every"):
        SequenceMetrics(ag_lpips_every=0)
