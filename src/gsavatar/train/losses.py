"""Training losses of the avatar model (paper Sec. 3.1, "Losses").

    L = L_1 + 0.1 L_lpips + 0.5 L_opac + 1.0 L_scale + 0.5 L_cpt + 1e-6 L_KL

Every term is a pure function returning a scalar tensor (differentiable,
device-agnostic); :func:`total_loss` applies :class:`LossWeights`. The LPIPS term
comes from :class:`gsavatar.metrics.LPIPS` (``lpips(pred, gt).mean()``).

Choices the paper leaves open (stated here, used consistently):

* ``opacity_loss``: mean of ``1 - alpha`` over the pixels of the *eroded*
  foreground mask, pooled over the whole batch (one mean, not a mean of
  per-image means).
* ``scale_loss``: mean over Gaussians of ``relu(max_axis_scale - threshold)``
  (linear hinge on the largest axis; Gaussians below the threshold cost nothing).
* ``cpt_smoothness_loss``: mean over (batch, control point, neighbour) of the
  squared Euclidean distance between displacements ``||d_i - d_j||^2``.
* ``kl_loss``: KL(N(mu, exp(logvar)) || N(0, I)) summed over all latent elements
  of a sample and averaged over the batch (the standard VAE convention; with the
  paper's 1e-6 weight the term is small but not negligible for large latents). The
  one KL of the code base: the encoder only returns ``mu`` and ``logvar``.
* ``min_filter_mask``: a (2 px + 1)^2 square min-filter; pixels outside the image do
  *not* erode (foreground touching the image border stays foreground).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from gsavatar.runs.config import LossWeights

# Guards 0/0 when a mask is empty (the loss is then 0, not NaN).
_MASK_EPS = 1e-8
# kl_loss continues exp(logvar) linearly above this (value and slope match): exact for
# every logvar the encoder can emit (it clamps to <= 20), finite with a positive
# gradient beyond (exp overflows float32 above ~88, giving inf loss and NaN steps).
_KL_LOGVAR_LINEAR = 50.0


def _reduce_dtype(t: Tensor) -> Tensor:
    """float16/bfloat16 -> float32 (sums over ~1e5 elements overflow float16's 65504)."""
    return t.float() if t.is_floating_point() and t.element_size() < 4 else t


def _check_same_shape(name_a: str, a: Tensor, name_b: str, b: Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{name_b} must match {name_a}'s shape {tuple(a.shape)}, got {tuple(b.shape)}")


def l1_loss(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean absolute error over all elements.

    Args:
        pred: Tensor  # [B, 3, H, W] rendered image in [0, 1]
        gt: Tensor  # [B, 3, H, W] ground truth in [0, 1]

    Returns:
        Tensor  # [] scalar
    """
    _check_same_shape("pred", pred, "gt", gt)
    return (_reduce_dtype(pred) - _reduce_dtype(gt)).abs().mean()


def min_filter_mask(mask: Tensor, px: int) -> Tensor:
    """Erode a foreground mask by ``px`` pixels (square (2 px + 1)^2 min-filter). Not prep's ``erode_mask``
    (project_uv: threshold, then a kernel of side ``erode_px``), hence the other name.

    Implemented as ``1 - maxpool(1 - mask)``; max-pool pads with -inf, so the image
    border does not erode. Soft masks are min-filtered. Not differentiable in any
    useful sense (masks are data).

    Args:
        mask: Tensor  # [B, 1, H, W], bool or float in [0, 1]
        px: erosion radius in pixels, >= 0 (0 returns the mask as float)

    Returns:
        Tensor  # [B, 1, H, W] float (mask's dtype if floating, else float32)
    """
    if mask.ndim != 4 or mask.shape[1] != 1:
        raise ValueError(f"mask must be [B, 1, H, W], got {tuple(mask.shape)}")
    if not isinstance(px, int) or px < 0:
        raise ValueError(f"px must be an int >= 0, got {px!r}")
    m = mask if mask.is_floating_point() else mask.float()
    if px == 0:
        return m
    return 1.0 - F.max_pool2d(1.0 - m, kernel_size=2 * px + 1, stride=1, padding=px)


def opacity_loss(alpha: Tensor, eroded_mask: Tensor) -> Tensor:
    """Encourage opaqueness in non-boundary foreground: mean of ``1 - alpha`` inside the mask.

    ``sum(mask * (1 - alpha)) / sum(mask)`` pooled over the batch; 0 when the mask is empty.

    Args:
        alpha: Tensor  # [B, 1, H, W] accumulated opacity in [0, 1]
        eroded_mask: Tensor  # [B, 1, H, W] in [0, 1] (see :func:`min_filter_mask`)

    Returns:
        Tensor  # [] scalar in [0, 1]
    """
    if alpha.ndim != 4 or alpha.shape[1] != 1:
        raise ValueError(f"alpha must be [B, 1, H, W], got {tuple(alpha.shape)}")
    _check_same_shape("alpha", alpha, "eroded_mask", eroded_mask)
    alpha = _reduce_dtype(alpha)
    m = eroded_mask.to(alpha.dtype)
    return (m * (1.0 - alpha)).sum() / m.sum().clamp_min(_MASK_EPS)


def scale_loss(scales: Tensor, threshold: float) -> Tensor:
    """Discourage overly large Gaussians: mean over Gaussians of ``relu(max_axis - threshold)``.

    Args:
        scales: Tensor  # [B, G, 3] (or [..., 3]) activated scales (std devs, metres), > 0
        threshold: largest scale that is free of charge (metres), >= 0

    Returns:
        Tensor  # [] scalar >= 0
    """
    if scales.ndim < 2 or scales.shape[-1] != 3:
        raise ValueError(f"scales must be [B, G, 3] (or [..., 3]), got {tuple(scales.shape)}")
    if not threshold >= 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    return F.relu(_reduce_dtype(scales).amax(dim=-1) - threshold).mean()


def cpt_smoothness_loss(ctrl_disp: Tensor, neighbors: Tensor) -> Tensor:
    """Smooth deformations: ``mean_{b,i,j in N(i)} ||d_{b,i} - d_{b,j}||^2``.

    Args:
        ctrl_disp: Tensor  # [B, C, 3] control-point displacements (metres)
        neighbors: Tensor  # [C, n] int, indices of each control point's n neighbours

    Returns:
        Tensor  # [] scalar >= 0
    """
    if ctrl_disp.ndim != 3 or ctrl_disp.shape[-1] != 3:
        raise ValueError(f"ctrl_disp must be [B, C, 3], got {tuple(ctrl_disp.shape)}")
    C = ctrl_disp.shape[1]
    if neighbors.ndim != 2 or neighbors.shape[0] != C:
        raise ValueError(f"neighbors must be [C, n] with C={C}, got {tuple(neighbors.shape)}")
    if neighbors.dtype.is_floating_point or neighbors.dtype == torch.bool:
        raise ValueError(f"neighbors must be an integer tensor, got {neighbors.dtype}")
    nb = neighbors.to(device=ctrl_disp.device, dtype=torch.long)
    ctrl_disp = _reduce_dtype(ctrl_disp)
    diff = ctrl_disp[:, :, None, :] - ctrl_disp[:, nb, :]  # [B, C, n, 3]
    return diff.square().sum(-1).mean()


def kl_loss(mu: Tensor, logvar: Tensor) -> Tensor:
    """KL(N(mu, diag(exp(logvar))) || N(0, I)), summed per sample, averaged over the batch.

    ``0.5 * sum(mu^2 + exp(logvar) - 1 - logvar)``. Not clamped (clamping would
    hide the gradient): above ``logvar = 50`` exp is continued linearly instead
    (same value and slope there), so loss and gradient stay finite for any finite
    input (tested to ±1e4). float16/bfloat16 inputs are reduced in float32.

    Args:
        mu: Tensor  # [B, ...] posterior means
        logvar: Tensor  # [B, ...] posterior log-variances

    Returns:
        Tensor  # [] scalar >= 0
    """
    _check_same_shape("mu", mu, "logvar", logvar)
    if mu.ndim < 1 or mu.shape[0] == 0:
        raise ValueError(f"mu must be [B, ...] with B >= 1, got {tuple(mu.shape)}")
    mu, logvar = _reduce_dtype(mu), _reduce_dtype(logvar)
    lv_capped = logvar.clamp(max=_KL_LOGVAR_LINEAR)
    var = lv_capped.exp() * (1.0 + (logvar - lv_capped))  # exp(logvar) up to the cap, then linear
    kl = 0.5 * (mu.square() + var - 1.0 - logvar)  # [B, ...]
    return kl.flatten(1).sum(1).mean() if kl.ndim > 1 else kl.mean()


def total_loss(terms: dict[str, Tensor], w: LossWeights) -> tuple[Tensor, dict[str, float]]:
    """Weighted sum of the loss terms present in ``terms``.

    Args:
        terms: name -> scalar tensor; names are ``LossWeights`` fields
            (``l1, lpips, opac, scale, cpt, kl``); absent terms are skipped (e.g. no
            ``kl`` without an encoder), terms whose weight is 0 are skipped too
            (so a NaN in a disabled term cannot leak into the total).
        w: the weights.

    Returns:
        (total: Tensor  # [] differentiable,
         logs: dict[str, float]  # unweighted value of every given term + "total";
                                  # one device sync for all values)
    """
    weights = w.as_dict()
    unknown = sorted(set(terms) - set(weights))
    if unknown:
        raise ValueError(f"terms has unknown names {unknown}; expected a subset of {sorted(weights)}")
    if not terms:
        raise ValueError("terms must hold at least one loss term, got an empty dict")
    for k, v in terms.items():
        if not isinstance(v, Tensor) or v.numel() != 1:
            shape = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
            raise ValueError(f"terms[{k!r}] must be a scalar tensor, got {shape}")
    names = list(terms)
    active = [k for k in names if weights[k] != 0.0]
    ref = terms[names[0]]
    total = torch.zeros((), dtype=ref.dtype, device=ref.device)
    for k in active:
        total = total + weights[k] * terms[k].reshape(())
    vals = torch.stack([terms[k].detach().reshape(()).float() for k in names] + [total.detach().float()])
    logs = dict(zip(names + ["total"], vals.tolist()))
    return total, logs


__all__ = [
    "cpt_smoothness_loss",
    "min_filter_mask",
    "kl_loss",
    "l1_loss",
    "opacity_loss",
    "scale_loss",
    "total_loss",
]
