"""The one table of Gaussian properties (:data:`GAUSSIAN_PROPERTIES`).

Every per-Gaussian property the avatar learns is one :class:`GaussianProperty` row: its name, its values per
Gaussian, its activation, whether it has a bias, a corrective basis and per-anchor terms, its initial bias and
its learning rates. Built from the table, nowhere spelt out again:

- the avatar's parameters (``{bias}`` ``[G, *shape]``, ``{basis}`` ``[G, n_basis, *shape]``), their optimiser
  groups and parameter counts (:class:`~gsavatar.models.avatar.GaussianAvatar`);
- the packed layout of the bases and its offsets (:func:`packed_layout`, read by the compiled inference kernel
  :func:`~gsavatar.models.kernels.interpolated_deltas_fast`);
- the pose heads' deltas (:class:`~gsavatar.models.pose_heads.PoseDeltas`, keyed by row name), the anchor-MLP
  head's basis products and the UV decoder's output split (:mod:`gsavatar.models.pose_heads`);
- the activation step of :meth:`GaussianAvatar.forward <gsavatar.models.avatar.GaussianAvatar.forward>`.

Adding a property = one row (and its activation if new), e.g. a per-Gaussian roughness in (0, 1)::

    ROUGHNESS = GaussianProperty("roughness", (1,), activate_sigmoid, "roughness_bias", "roughness_basis",
                                 "opacity_bias", "scale_basis")
    class MyAvatar(GaussianAvatar):
        PROPERTIES = (*GAUSSIAN_PROPERTIES, ROUGHNESS)

``MyAvatar(...).evaluate(pose, ...)[1]["roughness"]`` is then ``[B, G, 1]``, trained with its bias and basis and
computed by both the torch and the compiled path (tests/models/test_properties.py). Properties the renderer
reads (:data:`RENDERED`) are the :class:`~gsavatar.models.avatar.AvatarOutput` fields; any other row's activated
value is in the second output of :meth:`GaussianAvatar.evaluate`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from gsavatar.models import gaussians as gm
from gsavatar.models.config import ModelConfig


class InitContext(NamedTuple):
    """What a property's initial bias may depend on."""

    config: ModelConfig
    num_gaussians: int
    log_scale: np.ndarray
    """Initial log-scales from the surface (:func:`~gsavatar.models.gaussians.init_gaussian_params`).  # [G, 3]"""
    quaternion: np.ndarray
    """Initial wxyz rotations aligned to the surface normal.  # [G, 4]"""


@dataclass(frozen=True)
class GaussianProperty:
    """One row of the property table (module docstring)."""

    name: str
    """Row name: the key of its :class:`~gsavatar.models.pose_heads.PoseDeltas` entry and of its value in the
    second output of ``GaussianAvatar.evaluate``."""
    shape: tuple[int, ...] | None
    """Values per Gaussian; ``None``: the higher SH bands, ``((sh_degree + 1)^2 - 1, 3)``, truncated to the SH
    degree asked for."""
    activation: Callable[[Tensor, ModelConfig], Tensor] | None
    """Pre-activation ``λ + Δ`` -> the property; None: used as it is (the position offset)."""
    bias: str | None
    """Parameter name of the bias ``λ`` ``[G, *shape]`` (None: no bias, the delta alone)."""
    basis: str | None
    """Parameter name of the corrective basis ``ΔΛ`` ``[G, n_basis, *shape]`` (None: bias only, no pose delta)."""
    lr_bias: str | None
    """Field of :class:`~gsavatar.models.config.LearningRates` for the bias."""
    lr_basis: str | None
    """Field of :class:`~gsavatar.models.config.LearningRates` for the basis."""
    anchor_terms: bool = False
    """Also gets the anchors' deltas (``ModelConfig.anchor_sh0`` / ``latent_sh0``), interpolated like ``w``."""
    init: Callable[[InitContext], np.ndarray] | None = None
    """Initial bias (None: zeros)."""
    bias_squeeze: bool = False
    """Bias stored as ``[G]`` for a one-value property (opacity: ``[G]`` logits, as checkpoints have it)."""

    def dims(self, config: ModelConfig) -> tuple[int, ...]:
        """Values per Gaussian for ``config``."""
        return self.shape if self.shape is not None else (config.num_sh - 1, 3)

    def width(self, config: ModelConfig) -> int:
        """Scalars per Gaussian (its slice of the packed bases)."""
        return int(np.prod(self.dims(config)))


def _scale(x: Tensor, cfg: ModelConfig) -> Tensor:
    return gm.activate_scale(x, cfg.scale_max)


def _quat(x: Tensor, cfg: ModelConfig) -> Tensor:
    return gm.activate_quat(x)


def _sh0(x: Tensor, cfg: ModelConfig) -> Tensor:
    return gm.activate_sh0(x)


def _shn(x: Tensor, cfg: ModelConfig) -> Tensor:
    return gm.activate_shn(x, cfg.shn_bound)


def activate_sigmoid(x: Tensor, cfg: ModelConfig) -> Tensor:
    """``sigmoid(x)``: a property in (0, 1) (opacity; the example in the module docstring)."""
    return torch.sigmoid(x)


def _opacity_init(ctx: InitContext) -> np.ndarray:
    o = ctx.config.init_opacity
    return np.full(ctx.num_gaussians, float(np.log(o / (1 - o))), np.float32)


GAUSSIAN_PROPERTIES: tuple[GaussianProperty, ...] = (
    # canonical offset of the centre, metres: no bias ("-/1e-4"), added to the control-point displacement
    GaussianProperty("position", (3,), None, None, "gauss_pos_basis", None, "gauss_pos_basis"),
    # min(exp(x), scale_max) metres
    GaussianProperty(
        "scale", (3,), _scale, "scale_bias", "scale_basis", "scale_bias", "scale_basis", init=lambda c: c.log_scale
    ),
    # normalised wxyz
    GaussianProperty(
        "rotation",
        (4,),
        _quat,
        "rotation_bias",
        "rotation_basis",
        "rotation_bias",
        "rotation_basis",
        init=lambda c: c.quaternion,
    ),
    # sigmoid, bias only (no opacity correctives)
    GaussianProperty(
        "opacity",
        (1,),
        activate_sigmoid,
        "opacity_bias",
        None,
        "opacity_bias",
        None,
        init=_opacity_init,
        bias_squeeze=True,
    ),
    # tanh(x) * 0.5 / C0: colour = SH0 * C0 + 0.5
    GaussianProperty("sh0", (3,), _sh0, "sh0_bias", "sh0_basis", "sh0_bias", "sh0_basis", anchor_terms=True),
    # shn_bound * tanh(x), the first (deg + 1)^2 - 1 bands of the degree asked for
    GaussianProperty("shn", None, _shn, "shn_bias", "shn_basis", "shn_bias", "shn_basis"),
)
"""The avatar's Gaussian properties (supp. A: ``p = h(λ + <w, ΔΛ>)``), in the order of the packed bases and the
UV decoder's output channels. Parameters are registered rows with a bias first, then the bias-less rows' bases
(:func:`registration_order`)."""


def registration_order(properties: Sequence[GaussianProperty]) -> list[GaussianProperty]:
    """The rows in the order the avatar registers their parameters and optimiser groups: rows with a bias first
    (bias, then basis), then the bias-less rows (their basis), each part in table order. It is the order of the
    parameters before the table existed (position's basis after the SH), so seeded initialisations that walk
    ``named_parameters()`` and checkpoints' optimiser states stay as they were."""
    return [p for p in properties if p.bias is not None] + [p for p in properties if p.bias is None]


RENDERED = ("position", "scale", "rotation", "opacity", "sh0", "shn")
"""Rows the renderer reads (AvatarOutput's fields); the other rows' values are the second output of
``GaussianAvatar.evaluate``."""


class PackedLayout(NamedTuple):
    """Where each basis lies in the packed ``[G, n_basis, D]`` tensor (:func:`packed_layout`)."""

    names: tuple[str, ...]
    """Rows with a basis, in table order."""
    offsets: tuple[int, ...]
    """First column of each row."""
    widths: tuple[int, ...]
    """Columns of each row."""
    anchor_at: int
    """First column of the row with the anchors' deltas (-1: none)."""
    sh_bands: tuple[bool, ...]
    """Per row: the higher SH bands (truncated to the degree asked for)."""

    @property
    def size(self) -> int:
        """D, the packed width."""
        return self.offsets[-1] + self.widths[-1] if self.names else 0


def packed_layout(properties: Sequence[GaussianProperty], config: ModelConfig) -> PackedLayout:
    """The packed bases' columns for a property table: every row with a basis side by side in table order."""
    names, offsets, widths, sh_bands, anchor_at, at = [], [], [], [], -1, 0
    for p in properties:
        if p.basis is None:
            continue
        if p.anchor_terms:
            anchor_at = at
        names.append(p.name)
        offsets.append(at)
        widths.append(p.width(config))
        sh_bands.append(p.shape is None)
        at += widths[-1]
    return PackedLayout(tuple(names), tuple(offsets), tuple(widths), anchor_at, tuple(sh_bands))


def check_table(properties: Sequence[GaussianProperty]) -> None:
    """Refuse a table the avatar cannot build: duplicate names, a row with neither bias nor basis, more than one
    row for the anchors' deltas, learning rates missing for the parameters a row has. ValueError."""
    names = [p.name for p in properties]
    if len(set(names)) != len(names):
        raise ValueError(f"property names must be unique, got {names}")
    if sum(p.anchor_terms for p in properties) > 1:
        raise ValueError("at most one property takes the anchors' deltas (anchor_terms)")
    for p in properties:
        if p.bias is None and p.basis is None:
            raise ValueError(f"property {p.name!r} has neither a bias nor a basis")
        if (p.bias is None) != (p.lr_bias is None) or (p.basis is None) != (p.lr_basis is None):
            raise ValueError(f"property {p.name!r}: a learning-rate field per parameter (bias / basis)")
        if p.anchor_terms and p.basis is None:
            raise ValueError(f"property {p.name!r}: anchor terms need a basis (they are interpolated like w)")
