"""The model's one input: :class:`FrameBatch`, a batch of frames (pose, root motion, face, texture or latents)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import torch
from torch import Tensor


class FrameBatch(NamedTuple):
    """One batch of frames as :class:`~gsavatar.models.net.AvatarNet` takes it (a NamedTuple, so DDP and
    ``torch.utils.data`` move and collate it like a tuple of tensors).

    The appearance latents come either from ``latents`` (e.g. the appearance predictor's) or, when those
    are None and the net has an encoder, from encoding ``texture``.
    """

    pose: Tensor
    """Driving pose, radians, rig slot order.  # [B, P]"""
    root_rotation: Tensor
    """Root rotation, axis-angle (world_from_root).  # [B, 3]"""
    root_translation: Tensor
    """Root translation, metres.  # [B, 3]"""
    face: Tensor | None = None
    """Face embedding; None: zeros (or the model has none).  # [B, E]"""
    texture: Tensor | None = None
    """Encoder input: projected UV texture in [0, 1], face masked, row 0 = v = 1.  # [B, 3, S, S]"""
    latents: Tensor | None = None
    """Per-anchor appearance latents; given, they are used instead of encoding ``texture``.  # [B, A, L]"""

    @classmethod
    def from_dict(cls, items: Mapping[str, Tensor], latents: Tensor | None = None) -> FrameBatch:
        """From the frame inputs of :class:`~gsavatar.train.data.ViewDataset` items (batched: ``pose`` [B, P]).

        An empty ``face`` (``[B, 0]``: the capture has no face embedding) becomes None; ``texture`` is
        optional (datasets built without textures); other keys (image, mask, camera) are ignored.
        """
        face = items.get("face")
        return cls(
            items["pose"],
            items["root_rotation"],
            items["root_translation"],
            face if face is not None and face.numel() else None,
            items.get("texture"),
            latents,
        )

    @property
    def batch_size(self) -> int:
        """B, the number of frames."""
        return int(self.pose.shape[0])

    def to(self, device: torch.device | str) -> FrameBatch:
        """Every tensor on ``device`` (None stays None)."""
        return FrameBatch(*(None if t is None else t.to(device) for t in self))
