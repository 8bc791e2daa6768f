"""The field's image-quality protocol next to ours, so our numbers can sit beside published ones.

Two protocols, each named in every metrics JSON (:data:`PROTOCOLS`):

- ``ours``: the render on a black background against the ground truth composited onto black; PSNR over
  the full image and inside the mask, SSIM over the full image, LPIPS over the full image.
- ``ag``: Animatable Gaussians' ``eval/comparison_body_only_avatars.py``, which MMLPs copies: the ground
  truth is set to **white outside its mask** and the render composited onto white; PSNR and SSIM over the
  **full image**; LPIPS (VGG, and Alex as a second number) on the mask's bounding box, padded with white to
  a square centred on it and resized to 512 x 512 (bilinear) in both images (:func:`square_crop`).

The LPIPS weights are stated next to the scores (``lpips_nets``): offline we have the ST-LPIPS weights of
``stlpips-pytorch``; the official LPIPS v0.1 weights can be converted with
:func:`gsavatar.metrics.lpips.convert_official_lpips` and passed as files.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import Tensor

from gsavatar.metrics.image import psnr, ssim
from gsavatar.metrics.lpips import LPIPS

AG_PATCH = 512
"""Side of the square LPIPS crop of the ``ag`` protocol (pixels)."""

PROTOCOLS = {
    "ours": "black background; PSNR full image and inside the mask (psnr_fg), SSIM and LPIPS full image",
    "ag": "GT white outside its mask, render on white; PSNR and SSIM full image; LPIPS vgg and alex on the mask's "
    f"bounding box padded with white to a square and resized to {AG_PATCH} (Animatable Gaussians' "
    "comparison_body_only_avatars.py, as MMLPs)",
}
"""Protocol name -> what it measures (written next to the scores)."""


def on_white(image: Tensor, coverage: Tensor, background: Tensor | float = 0.0) -> Tensor:
    """An image composited onto ``background`` re-composited onto white: ``image + (1 - coverage) (1 - bg)``.

    image [..., 3, H, W] in [0, 1]; coverage [..., 1, H, W]: the render's alpha or the ground truth's mask
    (0..1); background: scalar or [3]. -> [..., 3, H, W]
    """
    bg = torch.as_tensor(background, dtype=image.dtype, device=image.device).reshape(-1, 1, 1)
    return image + (1 - coverage.to(image)) * (1 - bg)


def mask_bbox(mask: Tensor) -> tuple[int, int, int, int] | None:
    """Inclusive-exclusive bounding box ``(y0, y1, x0, x1)`` of ``mask > 0.5`` ([H, W] or [1, H, W]); None if empty."""
    m = mask.reshape(mask.shape[-2:]) > 0.5
    ys, xs = torch.nonzero(m.any(1)).flatten(), torch.nonzero(m.any(0)).flatten()
    if ys.numel() == 0:
        return None
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1


def square_crop(image: Tensor, box: tuple[int, int, int, int], size: int = AG_PATCH) -> Tensor:
    """The box of ``image`` [3, H, W] centred in a white square of its longer side, resized to ``size``.

    The shorter side is padded by ``(longer - shorter) // 2`` before and the rest after (the reference
    code's centring). -> [3, size, size]
    """
    y0, y1, x0, x1 = box
    h, w = y1 - y0, x1 - x0
    s = max(h, w)
    sq = torch.ones(image.shape[0], s, s, dtype=image.dtype, device=image.device)
    oy, ox = (s - h) // 2, (s - w) // 2
    sq[:, oy : oy + h, ox : ox + w] = image[:, y0:y1, x0:x1]
    return F.interpolate(sq[None], size=(size, size), mode="bilinear", align_corners=False)[0]


def ag_scores(
    pred_white: Tensor,
    gt_white: Tensor,
    mask: Tensor,
    lpips_nets: Mapping[str, torch.nn.Module] | None = None,
    size: int = AG_PATCH,
) -> dict[str, float]:
    """The ``ag`` protocol on one view (module docstring).

    pred_white, gt_white [3, H, W] in [0, 1], both on white (:func:`on_white`); mask [1, H, W] (the GT's).
    ``lpips_nets``: ``{"vgg": net, "alex": net}`` (any subset) -> ``lpips_vgg`` / ``lpips_alex`` on the
    square crop; NaN for an empty mask. -> ``{"psnr", "ssim", "lpips_<net>"...}``
    """
    p, g = pred_white[None].float(), gt_white[None].float().to(pred_white.device)
    out = {"psnr": float(psnr(p, g)[0]), "ssim": float(ssim(p, g)[0])}
    if lpips_nets:
        box = mask_bbox(mask)
        for name, net in lpips_nets.items():
            if box is None:
                out[f"lpips_{name}"] = float("nan")
                continue
            dev = next(net.parameters()).device
            pc, gc = (square_crop(x[0], box, size)[None].to(dev) for x in (p, g))
            out[f"lpips_{name}"] = float(net(pc, gc).mean())
    return out


def load_ag_lpips(device: torch.device | str, mode: str = "auto") -> tuple[dict[str, torch.nn.Module], dict[str, str]]:
    """The ``ag`` protocol's LPIPS networks (VGG and Alex, ST-LPIPS weights) -> (nets, names).

    ``mode``: ``on``, ``off`` or ``auto`` = on when ``device`` is CUDA (on the 2-core CPU box one VGG LPIPS at
    512 x 512 takes 5-15 s, more than rendering the view). A network whose weights are not installed is left
    out and named ``off (unavailable: ...)``.
    """
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"ag_lpips must be 'auto', 'on' or 'off', got {mode!r}")
    enabled = mode == "on" or (mode == "auto" and torch.device(device).type == "cuda")
    nets, names = {}, {}
    for net in ("vgg", "alex"):
        if not enabled:
            names[net] = "off"
            continue
        try:
            nets[net] = LPIPS(net=net).to(device)
            names[net] = nets[net].lpips_name
        except Exception as e:  # noqa: BLE001 - missing weights wheel or file
            names[net] = f"off (unavailable: {type(e).__name__})"
    return nets, names
