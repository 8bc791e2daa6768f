"""Render a posed avatar from cameras: per-item views of a batch, and orbit cameras around a subject.

Shared by training (loss renders), evaluation, turntables and the driver, so every consumer rasterizes
the same way.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from gsavatar.geometry.camera import look_at
from gsavatar.models.avatar import AvatarOutput
from gsavatar.render import rasterize


def render_views(
    out: AvatarOutput,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    backgrounds: Tensor,
    sh_degree: int,
    backend: str,
) -> tuple[Tensor, Tensor]:
    """Render item i of the batch from its own camera. -> colors [B,3,h,w], alphas [B,1,h,w]."""
    cols, alps = [], []
    for i in range(out.means.shape[0]):
        r = rasterize(
            out.means[i],
            out.quats[i],
            out.scales[i],
            out.opacities[i],
            out.sh[i],
            viewmats[i : i + 1],
            Ks[i : i + 1],
            width,
            height,
            backgrounds=backgrounds[i : i + 1],
            sh_degree=sh_degree,
            backend=backend,
        )
        cols.append(r.colors[0].permute(2, 0, 1))
        alps.append(r.alphas[0].permute(2, 0, 1))
    return torch.stack(cols), torch.stack(alps)


def orbit_cameras(
    center: np.ndarray, radius: float, height: float, n: int, width: int, height_px: int, fov_deg: float = 40.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` cameras on a horizontal circle looking at ``center``. -> viewmats [n,4,4], Ks [n,3,3]."""
    f = 0.5 * height_px / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, width / 2 - 0.5], [0, f, height_px / 2 - 0.5], [0, 0, 1]], np.float32)
    vms = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = center + np.array([radius * np.sin(a), height, radius * np.cos(a)])
        R, T = look_at(eye, center)
        M = np.eye(4, dtype=np.float32)
        M[:3, :3], M[:3, 3] = R, T
        vms.append(M)
    return torch.from_numpy(np.stack(vms)), torch.from_numpy(np.repeat(K[None], n, 0))
