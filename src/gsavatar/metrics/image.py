"""Full-reference image metrics: PSNR and SSIM (batched, differentiable, torch).

Conventions:
  * images are ``[B, 3, H, W]`` (any channel count C >= 1 works) with values in
    ``[0, data_range]`` (default ``[0, 1]``);
  * every metric returns one value per image, ``Tensor [B]``; average over the
    batch yourself (so images from different batches weigh equally);
  * computations run in the inputs' dtype/device; pass float64 for reference-grade
    numbers.

SSIM follows Wang et al. 2004 exactly as ``skimage.metrics.structural_similarity(
gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)``:
11x11 Gaussian window (sigma 1.5, truncated at 3.5 sigma -> radius 5), K1=0.01,
K2=0.03, population (not sample) covariances, SSIM map averaged over the *valid*
region only (pixels at least 5 px from the border, i.e. no padding enters the
result), and per-channel maps averaged over channels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_SIGMA = 1.5
SSIM_TRUNCATE = 3.5  # scipy.ndimage.gaussian_filter / skimage default
SSIM_RADIUS = int(SSIM_TRUNCATE * SSIM_SIGMA + 0.5)  # 5 -> 11x11 window
SSIM_K1 = 0.01
SSIM_K2 = 0.03


def _check_pair(pred: Tensor, gt: Tensor) -> None:
    if pred.ndim != 4:
        raise ValueError(f"pred must be [B, C, H, W], got shape {tuple(pred.shape)}")
    if gt.shape != pred.shape:
        raise ValueError(f"gt must match pred's shape {tuple(pred.shape)}, got {tuple(gt.shape)}")
    if not pred.is_floating_point() or not gt.is_floating_point():
        raise ValueError(f"pred and gt must be floating point, got {pred.dtype} and {gt.dtype}")


def mse(pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> Tensor:
    """Per-image mean squared error, optionally restricted to a mask.

    Args:
        pred: Tensor  # [B, C, H, W]
        gt: Tensor  # [B, C, H, W]
        mask: Tensor | None  # [B, 1, H, W], [B, H, W] or [B, C, H, W]; bool or float
            # weights in [0, 1]

    Returns:
        Tensor  # [B]; with a mask: sum(mask * err^2) / sum(mask) with the mask
        # broadcast to [B, C, H, W] (so a [B, 1, H, W] mask counts each pixel C times
        # in both sums, i.e. the mean over masked pixels and channels). An image whose
        # mask is empty gives NaN (0/0); callers should filter it.
    """
    _check_pair(pred, gt)
    sq = (pred - gt).square()  # [B, C, H, W]
    if mask is None:
        return sq.flatten(1).mean(1)
    m = _check_mask(mask, pred).expand_as(sq)  # [B, C, H, W]
    return (sq * m).flatten(1).sum(1) / m.flatten(1).sum(1)


def _check_mask(mask: Tensor, like: Tensor) -> Tensor:
    """Validate a mask; return it as float [B, 1 or C, H, W] in ``like``'s dtype."""
    B, C, H, W = like.shape
    if mask.ndim == 3:
        mask = mask[:, None]
    if mask.ndim != 4 or mask.shape[0] != B or mask.shape[1] not in (1, C) or mask.shape[2:] != (H, W):
        raise ValueError(
            f"mask must be [B, 1, H, W], [B, H, W] or [B, C, H, W] with B={B}, C={C}, H={H}, W={W}, "
            f"got {tuple(mask.shape)}"
        )
    return mask.to(like.dtype)


def psnr(pred: Tensor, gt: Tensor, mask: Tensor | None = None, data_range: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB, per image.

    ``10 * log10(data_range^2 / MSE)``; with a mask, MSE is taken over masked
    pixels only (see :func:`mse`). Identical images give ``+inf``.

    Args:
        pred: Tensor  # [B, C, H, W] in [0, data_range]
        gt: Tensor  # [B, C, H, W] in [0, data_range]
        mask: Tensor | None  # [B, 1, H, W], [B, H, W] or [B, C, H, W], bool or float weights
        data_range: peak value (1.0 for [0, 1] images)

    Returns:
        Tensor  # [B] dB
    """
    if data_range <= 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    err = mse(pred, gt, mask)  # [B]
    return 10.0 * torch.log10(data_range**2 / err)


def gaussian_kernel1d(
    sigma: float = SSIM_SIGMA,
    radius: int = SSIM_RADIUS,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """Normalised 1D Gaussian taps ``exp(-x^2 / (2 sigma^2))``, x in [-radius, radius].

    Same taps as ``scipy.ndimage.gaussian_filter`` (which skimage's SSIM uses).

    Returns:
        Tensor  # [2 * radius + 1], sums to 1
    """
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).to(dtype=dtype, device=device)


def _filter_valid(x: Tensor, k1d: Tensor) -> Tensor:
    """Separable depthwise 'valid' filtering (no padding).

    Args:
        x: Tensor  # [N, C, H, W]
        k1d: Tensor  # [K]

    Returns:
        Tensor  # [N, C, H - K + 1, W - K + 1]
    """
    C = x.shape[1]
    K = k1d.shape[0]
    kh = k1d.view(1, 1, K, 1).expand(C, 1, K, 1)
    kw = k1d.view(1, 1, 1, K).expand(C, 1, 1, K)
    x = F.conv2d(x, kh, groups=C)
    return F.conv2d(x, kw, groups=C)


def ssim_map(pred: Tensor, gt: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-pixel, per-channel SSIM over the valid region.

    Args:
        pred: Tensor  # [B, C, H, W] in [0, data_range], H, W >= 11
        gt: Tensor  # [B, C, H, W]
        data_range: dynamic range of the pixel values

    Returns:
        Tensor  # [B, C, H - 10, W - 10] SSIM values in [-1, 1]
    """
    _check_pair(pred, gt)
    K = 2 * SSIM_RADIUS + 1
    H, W = pred.shape[-2:]
    if H < K or W < K:
        raise ValueError(f"ssim needs images of at least {K}x{K} pixels, got H={H}, W={W}")
    if data_range <= 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    B, C = pred.shape[:2]
    k1d = gaussian_kernel1d(dtype=pred.dtype, device=pred.device)  # [11]
    # Filter all five moment images in one depthwise conv call.
    stack = torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], dim=1)  # [B, 5C, H, W]
    mu_x, mu_y, e_xx, e_yy, e_xy = _filter_valid(stack, k1d).split(C, dim=1)
    var_x = e_xx - mu_x * mu_x
    var_y = e_yy - mu_y * mu_y
    cov_xy = e_xy - mu_x * mu_y
    c1 = (SSIM_K1 * data_range) ** 2
    c2 = (SSIM_K2 * data_range) ** 2
    num = (2.0 * mu_x * mu_y + c1) * (2.0 * cov_xy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)
    return num / den


def ssim(pred: Tensor, gt: Tensor, data_range: float = 1.0) -> Tensor:
    """Structural similarity (Wang et al. 2004), per image.

    Mean of :func:`ssim_map` over channels and valid pixels; matches
    ``skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=data_range, channel_axis=...)``.

    Args:
        pred: Tensor  # [B, C, H, W] in [0, data_range], H, W >= 11
        gt: Tensor  # [B, C, H, W]

    Returns:
        Tensor  # [B], 1.0 for identical images
    """
    return ssim_map(pred, gt, data_range).flatten(1).mean(1)


def psnr_from_mse(err: Tensor, data_range: float = 1.0) -> Tensor:
    """``10 log10(data_range^2 / err)`` for already-averaged errors (e.g. dataset MSE)."""
    return 10.0 * torch.log10(data_range**2 / err)


__all__ = ["gaussian_kernel1d", "mse", "psnr", "psnr_from_mse", "ssim", "ssim_map"]
