"""Model assembly: the avatar and its appearance encoder behind one module, built from a prepared scene.

Training (:mod:`gsavatar.train.trainer`), run loading (:mod:`gsavatar.runs`) and driving all hold an
:class:`AvatarNet`; :func:`build_net` is the one place that turns a prepared dataset and a model config
into one.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from gsavatar.data_schema.prepared import PreparedScene
from gsavatar.models.avatar import AvatarOutput, GaussianAvatar
from gsavatar.models.batch import FrameBatch
from gsavatar.models.config import ModelConfig
from gsavatar.models.encoder import AppearanceEncoder, LatentNorm, sample_at_uv


class NetOutput(NamedTuple):
    avatar: AvatarOutput
    mu: Tensor | None  # [B, L, h, w] posterior mean of the latent map (None without latents)
    logvar: Tensor | None  # [B, L, h, w]


class AvatarNet(nn.Module):
    """Avatar + appearance encoder behind one forward, so DDP sees every parameter."""

    def __init__(self, avatar: GaussianAvatar, encoder: AppearanceEncoder | None, anchor_uv: Tensor) -> None:
        super().__init__()
        self.avatar = avatar
        self.encoder = encoder
        self.register_buffer("anchor_uv", anchor_uv)  # [A, 2] OBJ convention
        self.latent_norm = None
        if encoder is not None and avatar.config.latent_norm:
            self.latent_norm = LatentNorm(anchor_uv.shape[0], encoder.latent_dim)

    def latents(self, texture: Tensor, eps: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """texture [B,3,S,S] -> per-anchor latents [B,A,L], mu, logvar. eps [B,L,h,w] = VAE noise (None: use mu).

        With ``latent_norm`` the latents are standardised per anchor and channel over frames (the running
        statistics update in training mode); every consumer (avatar, predictor targets, driving) sees that space.
        """
        enc = self.encoder(texture, eps)
        lat = sample_at_uv(enc.latent_map, self.anchor_uv)
        if self.latent_norm is not None:
            lat = self.latent_norm(lat)
        return lat, enc.mu, enc.logvar

    def forward(
        self, batch: FrameBatch, *, sh_degree: int | None = None, correctives: bool = True, eps: Tensor | None = None
    ) -> NetOutput:
        """Posed Gaussians of a batch of frames, and the encoder's posterior when it ran.

        Args:
            batch: FrameBatch  # [B, ...]; ``batch.latents`` given: used as they are; else, with an
                encoder, ``batch.texture`` is encoded (required then)
            sh_degree: SH degree to output (<= the model's; None: the model's)
            correctives: evaluate the pose head; False: bias terms only (early training)
            eps: Tensor | None  # [B, L, h, w] VAE noise of the encoder's sample; None: the posterior mean

        Returns:
            NetOutput  # mu / logvar None when the encoder did not run
        """
        latents, mu, logvar = batch.latents, None, None
        if self.encoder is not None and latents is None:
            if batch.texture is None:
                raise ValueError(
                    "batch.texture is required: the model encodes its appearance latents from it "
                    "(or give batch.latents)"
                )
            latents, mu, logvar = self.latents(batch.texture, eps)
        out = self.avatar(
            batch.pose,
            batch.root_rotation,
            batch.root_translation,
            batch.face,
            latents,
            sh_degree=sh_degree,
            correctives=correctives,
        )
        return NetOutput(out, mu, logvar)


def build_net(scene: PreparedScene, mcfg: ModelConfig, seed: int) -> AvatarNet:
    torch.manual_seed(seed)
    avatar = GaussianAvatar(
        scene.hierarchy,
        scene.masks,
        scene.capture.rig,
        scene.pca_local,
        scene.pca_global,
        mcfg,
        face_dim=scene.face_dim,
        seed=seed,
    )
    if avatar.config.input_norm:
        m = scene.capture.motion
        frames = scene.capture.splits["train"].frames
        face = torch.from_numpy(m.face[frames]).float() if m.face is not None else None
        avatar.set_input_stats(torch.from_numpy(m.pose[frames]).float(), face)
    encoder = AppearanceEncoder(latent_dim=mcfg.latent_dim) if mcfg.use_latent else None
    uv = torch.from_numpy(scene.hierarchy.anchors.uv).float()
    return AvatarNet(avatar, encoder, uv)
