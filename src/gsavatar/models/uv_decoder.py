"""Convolutional UV-space decoder of the nRFGCA-dagger baseline (paper section 4).

The paper compares against "a convolutional decoder baseline similar to a non-relightable
version of the Relightable Full-Body Gaussian Codec Avatar (RFGCA)" without further
detail; this is our reading of it. The full (global) pose vector, concatenated with the
face embedding, goes through a linear layer to a small ``[C0, s0, s0]`` feature grid,
then ``n`` blocks of (nearest x2 upsampling, 3x3 conv, LeakyReLU 0.2) and a final 3x3
conv to an ``[n_out, S, S]`` map in UV space (row 0 = v = 1, OBJ convention, like the
projected textures). Every Gaussian reads its per-frame property deltas by bilinear
lookup at its own UV coordinate (:func:`gsavatar.models.encoder.sample_at_uv`); the
deltas are added to the same per-Gaussian biases the anchor-MLP model uses, so only the
pose-dependent part differs between the two models. The last conv starts at zero, so
the decoder starts as the bias-only avatar (as the zero-initialised corrective bases do).

There is no localization: every texel sees every pose parameter, which is what lets the
baseline pick up train-only correlations between distant body parts.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn


def decoder_channels(first: int, last: int, n_up: int) -> list[int]:
    """Channels after the linear layer and after each up block: ``first`` halving down to ``last``.  # n_up + 1"""
    return [max(first >> i, last) for i in range(n_up + 1)]


class UVDecoder(nn.Module):
    """Pose (+ face) vector ``[B, D]`` -> UV property map ``[B, n_out, S, S]``."""

    def __init__(
        self,
        in_dim: int,
        out_channels: int,
        size: int = 128,
        start_size: int = 8,
        first_channels: int = 128,
        last_channels: int = 32,
    ) -> None:
        super().__init__()
        if in_dim <= 0 or out_channels <= 0:
            raise ValueError(f"in_dim and out_channels must be > 0, got {in_dim}, {out_channels}")
        if size < start_size or size % start_size or (size // start_size) & (size // start_size - 1):
            raise ValueError(f"size must be start_size ({start_size}) times a power of two, got {size}")
        n_up = (size // start_size).bit_length() - 1
        chans = decoder_channels(first_channels, last_channels, n_up)
        self.size, self.start_size, self.out_channels = int(size), int(start_size), int(out_channels)
        self.fc = nn.Linear(in_dim, chans[0] * start_size * start_size)
        self.blocks = nn.ModuleList(nn.Conv2d(a, b, 3, padding=1) for a, b in zip(chans[:-1], chans[1:]))
        self.head = nn.Conv2d(chans[-1], out_channels, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: Tensor) -> Tensor:
        """x: Tensor  # [B, D] -> Tensor  # [B, n_out, S, S]"""
        if x.ndim != 2 or x.shape[1] != self.fc.in_features:
            raise ValueError(f"decoder input must be [B, {self.fc.in_features}], got {tuple(x.shape)}")
        s = self.start_size
        h = F.leaky_relu(self.fc(x), 0.2).view(x.shape[0], -1, s, s)
        for conv in self.blocks:
            h = F.leaky_relu(conv(F.interpolate(h, scale_factor=2, mode="nearest")), 0.2)
        return self.head(h)
