"""Convolutional VAE appearance encoder (paper section 3.3, supp. D.2).

Input: the per-frame UV texture with the face region masked out, ``[B, 3, S, S]``
values in [0, 1] (row 0 = v = 1, OBJ convention), ``S`` a power of two >= 64
(paper: 1024). Five down-convolutions (k3, s2, p1), each followed by GroupNorm and
ReLU, with channels 8, 16, 32, 64, 128 (doubling from 8, capped at 128), give a
``[B, 128, S/32, S/32]`` grid (paper: 32x32). GroupNorm uses 8 groups (the paper's
"8-wide group normalization"; a layer with fewer than 8 channels would use one group
per channel). Two 3x3 convolutions predict ``mu`` and ``log sigma^2`` maps with
``N_l`` channels. ``logvar`` is clamped to ``[-30, 20]``. The latent map is ``mu`` unless the
caller passes VAE noise ``eps``, then the reparameterised sample ``mu + sigma * eps``
(:func:`reparameterize`, the one sampling path: the trainer draws ``eps`` per sample from its
seeded generators, so a step's noise does not depend on the batch layout or the number of ranks).
The KL term of the VAE is :func:`gsavatar.train.losses.kl_loss`.

The ``log sigma^2`` head starts with zero weights and bias ``logvar_init`` (default -6,
sigma = 0.05). With PyTorch's default init it would start near 0 (sigma = 1), noise 2.3x
larger than the initial ``mu`` (std 0.43 on a 512^2 texture), so training would start from
latents that carry almost nothing. (The trainer also holds the KL back until the
correctives are on; docs/train.md has the posterior-collapse measurements.)

Each anchor reads its local code by bilinear lookup at its UV (:func:`sample_at_uv`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gsavatar.models.config import LearningRates

LOGVAR_RANGE = (-30.0, 20.0)


class EncoderOutput(NamedTuple):
    latent_map: Tensor
    """Sampled latents (noise given) or ``mu``.  # [B, L, h, w]"""
    mu: Tensor
    """Posterior mean.  # [B, L, h, w]"""
    logvar: Tensor
    """Posterior log-variance, clamped to ``LOGVAR_RANGE``.  # [B, L, h, w]"""


def encoder_channels(n_down: int = 5, first: int = 8, max_channels: int = 128) -> list[int]:
    """Output channels of each down layer: ``first``, doubling, capped at ``max_channels``."""
    return [min(first * 2**i, max_channels) for i in range(n_down)]


def reparameterize(mu: Tensor, logvar: Tensor, eps: Tensor) -> Tensor:
    """The VAE sample ``mu + exp(logvar / 2) * eps``.

    Args:
        mu: Tensor  # [...] posterior mean
        logvar: Tensor  # [...] posterior log-variance; clamped above at ``LOGVAR_RANGE[1]`` (as the
            encoder's head is): exp(logvar / 2) overflows float32 for logvar > ~177, making the
            sample inf and its gradient NaN. Very negative values need no clamp (the noise vanishes).
        eps: Tensor  # [...] standard-normal noise, mu's shape

    Returns:
        Tensor  # [...]
    """
    if eps.shape != mu.shape or logvar.shape != mu.shape:
        raise ValueError(
            f"mu, logvar and eps must have one shape, got {tuple(mu.shape)}, {tuple(logvar.shape)}, {tuple(eps.shape)}"
        )
    return mu + torch.exp(0.5 * logvar.clamp(max=LOGVAR_RANGE[1])) * eps


def sample_at_uv(latent_map: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of per-anchor codes at UV coordinates.

    Texture convention: row 0 is v = 1 (OBJ, v up), column 0 is u = 0; texel ``(r, c)``
    covers ``u in [c/w, (c+1)/w]``. ``grid_sample`` with ``align_corners=False``,
    ``x = 2u - 1``, ``y = 1 - 2v``; outside the texel-centre range the border texel is
    repeated (``padding_mode="border"``).

    Args:
        latent_map: Tensor  # [B, L, h, w]
        uv: Tensor  # [A, 2] (u, v) in [0, 1]

    Returns:
        Tensor  # [B, A, L]
    """
    if latent_map.ndim != 4:
        raise ValueError(f"latent_map must be [B, L, h, w], got {tuple(latent_map.shape)}")
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv must be [A, 2], got {tuple(uv.shape)}")
    B = latent_map.shape[0]
    uv = uv.to(device=latent_map.device, dtype=latent_map.dtype)
    grid = torch.stack([2.0 * uv[:, 0] - 1.0, 1.0 - 2.0 * uv[:, 1]], dim=-1)  # [A, 2]
    grid = grid[None, None].expand(B, 1, -1, 2)  # [B, 1, A, 2]
    out = F.grid_sample(latent_map, grid, mode="bilinear", padding_mode="border", align_corners=False)  # [B, L, 1, A]
    return out[:, :, 0].transpose(1, 2)  # [B, A, L]


def mask_texture(texture: Tensor, face_uv_mask: Tensor, fill: float = 0.0) -> Tensor:
    """Blank the face region of UV textures before encoding.

    Args:
        texture: Tensor  # [B, 3, S, S] values in [0, 1], row 0 = v = 1
        face_uv_mask: Tensor  # [h, w] bool (row 0 = v = 1), nearest-resized to S x S
        fill: value written inside the face region

    Returns:
        Tensor  # [B, 3, S, S]
    """
    if texture.ndim != 4 or face_uv_mask.ndim != 2:
        raise ValueError(
            f"texture must be [B, C, S, S] and face_uv_mask [h, w], "
            f"got {tuple(texture.shape)}, {tuple(face_uv_mask.shape)}"
        )
    m = face_uv_mask.to(device=texture.device, dtype=torch.float32)[None, None]
    m = F.interpolate(m, size=texture.shape[-2:], mode="nearest")[0, 0] > 0.5  # [S, S]
    return torch.where(m, torch.as_tensor(fill, dtype=texture.dtype, device=texture.device), texture)


class AppearanceEncoder(nn.Module):
    """CNN VAE: UV texture ``[B, 3, S, S]`` -> latent map ``[B, N_l, S/32, S/32]``."""

    def __init__(
        self,
        latent_dim: int = 16,
        in_channels: int = 3,
        n_down: int = 5,
        first_channels: int = 8,
        max_channels: int = 128,
        gn_groups: int = 8,
        logvar_init: float = -6.0,
    ) -> None:
        super().__init__()
        self.latent_dim = int(latent_dim)
        self.in_channels = int(in_channels)
        self.n_down = int(n_down)
        layers: list[nn.Module] = []
        c_in = in_channels
        for c in encoder_channels(n_down, first_channels, max_channels):
            layers += [
                nn.Conv2d(c_in, c, 3, stride=2, padding=1),
                nn.GroupNorm(min(gn_groups, c), c),
                nn.ReLU(inplace=True),
            ]
            c_in = c
        self.trunk = nn.Sequential(*layers)
        self.feature_channels = c_in
        self.mu_head = nn.Conv2d(c_in, latent_dim, 3, padding=1)
        self.logvar_head = nn.Conv2d(c_in, latent_dim, 3, padding=1)
        nn.init.zeros_(self.logvar_head.weight)
        nn.init.constant_(self.logvar_head.bias, float(logvar_init))

    @property
    def downsample(self) -> int:
        """Spatial reduction factor ``2^n_down`` (paper: 32)."""
        return 2**self.n_down

    def grid_size(self, size: int) -> int:
        """Latent grid side for a texture of side ``size``."""
        return size // self.downsample

    def _check(self, texture: Tensor) -> None:
        if texture.ndim != 4 or texture.shape[1] != self.in_channels:
            raise ValueError(f"texture must be [B, {self.in_channels}, S, S], got {tuple(texture.shape)}")
        for s in texture.shape[-2:]:
            if s < 2 * self.downsample or s & (s - 1):
                raise ValueError(
                    f"texture sides must be powers of two >= {2 * self.downsample}, got {tuple(texture.shape[-2:])}"
                )

    def features(self, texture: Tensor) -> Tensor:
        """Trunk output. texture [B, 3, S, S] -> [B, 128, S/32, S/32]"""
        self._check(texture)
        return self.trunk(texture)

    def forward(self, texture: Tensor, eps: Tensor | None = None) -> EncoderOutput:
        """Posterior of the latent map, and the map itself.

        Args:
            texture: Tensor  # [B, 3, S, S] in [0, 1], face masked
            eps: Tensor | None  # [B, L, S/32, S/32] VAE noise (standard normal); None: the map is ``mu``

        Returns:
            EncoderOutput  # maps [B, L, S/32, S/32]
        """
        h = self.features(texture)
        mu = self.mu_head(h)
        logvar = self.logvar_head(h).clamp(*LOGVAR_RANGE)
        return EncoderOutput(mu if eps is None else reparameterize(mu, logvar, eps), mu, logvar)

    def param_groups(self, lrs: LearningRates | None = None) -> list[dict]:
        """One AdamW group ``encoder``: ``lrs.encoder`` and ``lrs.encoder_weight_decay`` (supp. D.2: 5e-4, 1e-3)."""
        lrs = lrs or LearningRates()
        return [
            {
                "name": "encoder",
                "params": list(self.parameters()),
                "lr": lrs.encoder,
                "weight_decay": lrs.encoder_weight_decay,
            }
        ]


def standardize(x: Tensor, mean: Tensor, var: Tensor, floor: float) -> Tensor:
    """``(x - mean) / max(sqrt(var), floor)``. x [B, A, L], mean/var [A, L] -> [B, A, L]"""
    return (x - mean.to(x.dtype)) / var.to(x.dtype).sqrt().clamp_min(floor)


class LatentNorm(nn.Module):
    """Running per-anchor, per-channel standardisation of appearance latents over frames.

    Training mode updates the running mean and variance from each batch (detached; the first
    ``1 / momentum`` updates are a cumulative average, then an EMA with ``momentum``) and uses them;
    eval mode only uses them. The encoder's frame-to-frame change is small next to its spatial
    variation (std over frames 0.005 vs mean magnitude 0.1 on the ``small`` capture), so without
    this the MLPs see almost constant latents. Latents everywhere downstream (predictor targets,
    the mean latent, driving) are in this standardised space.
    """

    def __init__(self, num_anchors: int, latent_dim: int, momentum: float = 0.01, std_floor: float = 1e-4) -> None:
        super().__init__()
        if not 0 < momentum <= 1:
            raise ValueError(f"momentum must be in (0, 1], got {momentum}")
        self.momentum, self.std_floor = float(momentum), float(std_floor)
        self.register_buffer("mean", torch.zeros(num_anchors, latent_dim))  # [A, L]
        self.register_buffer("var", torch.ones(num_anchors, latent_dim))  # [A, L]
        self.register_buffer("count", torch.zeros((), dtype=torch.long))  # updates so far

    @torch.no_grad()
    def update(self, x: Tensor) -> None:
        """Fold a batch of latents into the running statistics. x: Tensor  # [B, A, L]"""
        x = x.detach().to(self.mean.dtype)
        m = max(1.0 / float(self.count + 1), self.momentum)
        bm = x.mean(0)
        if int(self.count) == 0:
            self.mean.copy_(bm)
            self.var.copy_(((x - bm) ** 2).mean(0))
        else:
            d = x - self.mean
            self.mean.add_(m * (bm - self.mean))
            self.var.mul_(1 - m).add_(m * (d * d).mean(0))
        self.count += 1

    def forward(self, x: Tensor) -> Tensor:
        """x: Tensor  # [B, A, L] raw latents -> standardised [B, A, L] (updates the stats in training mode)."""
        if self.training:
            self.update(x)
        return standardize(x, self.mean, self.var, self.std_floor)
