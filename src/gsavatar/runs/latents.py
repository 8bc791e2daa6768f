"""Statistics of a run's appearance latents, shared by evaluation and driving comparisons."""

from __future__ import annotations

import torch
from torch import Tensor

from gsavatar.data_schema.prepared import PreparedScene, TextureSource, frame_textures
from gsavatar.models.net import AvatarNet


@torch.no_grad()
def mean_train_latent(
    net: AvatarNet, scene: PreparedScene, device: torch.device, texture_source: TextureSource = "projected"
) -> Tensor:
    """Mean of the encoder's per-anchor latents (mu) over the training frames.  # [A, L]"""
    textures = frame_textures(scene, texture_source)
    frames = list(scene.capture.splits["train"].frames)
    net.eval()
    total = None
    for f in frames:
        tex = torch.from_numpy(textures.get(f)).permute(2, 0, 1).contiguous()[None].to(device)  # [1, 3, S, S]
        lat = net.latents(tex, None)[0][0]
        total = lat if total is None else total + lat
    return total / len(frames)
