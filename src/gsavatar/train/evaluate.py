"""Evaluation of a trained avatar: PSNR / SSIM / LPIPS on held-out cameras and frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gsavatar.metrics.image import psnr, ssim
from gsavatar.metrics.protocols import ag_scores, on_white
from gsavatar.models.batch import FrameBatch
from gsavatar.models.net import AvatarNet
from gsavatar.runs.views import render_views
from gsavatar.train.data import ViewDataset
from gsavatar.train.losses import min_filter_mask
from gsavatar.utils.io import write_image
from gsavatar.utils.paths import output_path


def select_frames(frames: list[int], n: int) -> list[int]:
    """``n`` evenly spaced frames of ``frames`` (all if n <= 0 or n >= len)."""
    if n <= 0 or n >= len(frames):
        return list(frames)
    idx = np.linspace(0, len(frames) - 1, n).round().astype(int)
    return [frames[i] for i in idx]


@torch.no_grad()
def evaluate_views(
    net: AvatarNet,
    data: ViewDataset,
    device: torch.device,
    sh_degree: int,
    backend: str = "auto",
    lpips=None,
    latents_fn=None,
    save_dir: Path | None = None,
    max_images: int = 4,
    ag_lpips: dict | None = None,
) -> dict:
    """Render every (frame, camera) of ``data`` on a black background and score it.

    ``latents_fn(frame) -> [A, L]`` overrides the encoder (e.g. the appearance predictor).
    Returns the means of: ``psnr`` (full image), ``psnr_fg`` (inside the mask), ``psnr_interior`` (inside the mask
    eroded by 2 px: what the silhouette's edge costs is the difference), ``ssim``, ``lpips`` (protocol ``ours``),
    and ``ag_psnr``, ``ag_ssim``, ``ag_lpips_<net>``: the field's protocol (:mod:`gsavatar.metrics.protocols`;
    LPIPS with the ``ag_lpips`` nets).
    """
    net.eval()
    rows: dict[str, list[float]] = {"psnr": [], "psnr_fg": [], "psnr_interior": [], "ssim": []}
    if lpips is not None:
        rows["lpips"] = []
    saved = 0
    for i in range(len(data)):
        b = {k: (v[None].to(device) if torch.is_tensor(v) else v) for k, v in data[i].items()}
        latents = None
        if latents_fn is not None:
            latents = latents_fn(int(b["frame"])).to(device)[None]
        out = net(FrameBatch.from_dict(b, latents), sh_degree=sh_degree)
        H, W = b["image"].shape[-2:]
        bg = torch.zeros(1, 3, device=device)
        pred, alpha = render_views(out.avatar, b["viewmat"], b["K"], W, H, bg, sh_degree, backend)
        pred = pred.clamp(0, 1)
        gt = b["image"] * b["mask"]
        for k, v in ag_scores(
            on_white(pred[0], alpha[0]).clamp(0, 1), on_white(gt[0], b["mask"][0]), b["mask"][0], ag_lpips
        ).items():
            rows.setdefault(f"ag_{k}", []).append(v)
        rows["psnr"].append(float(psnr(pred, gt)[0]))
        rows["psnr_fg"].append(float(psnr(pred, gt, mask=(b["mask"] > 0.5).expand_as(gt))[0]))
        rows["psnr_interior"].append(float(psnr(pred, gt, mask=(min_filter_mask(b["mask"], 2) > 0.5).expand_as(gt))[0]))
        rows["ssim"].append(float(ssim(pred, gt)[0]))
        if lpips is not None:
            rows["lpips"].append(float(lpips(pred, gt).mean()))
        if save_dir is not None and saved < max_images:
            err = (pred - gt).abs().mean(1, keepdim=True).expand_as(pred) * 4
            panel = torch.cat([gt[0], pred[0], err[0].clamp(0, 1)], dim=2).permute(1, 2, 0).cpu().numpy()
            frame, cam = data.items[i]
            write_image(output_path(save_dir, f"eval_{frame:08d}_{cam}.png"), panel)
            saved += 1
    # nanmean: a view whose eroded mask is empty (tiny images) has no interior PSNR
    return {k: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for k, v in rows.items()} | {
        "views": len(data)
    }
