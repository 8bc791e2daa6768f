"""Pose heads: the pose-dependent part of the avatar, one small class per kind of network.

A pose head maps a batch of frames' conditioning (pose, face embedding, appearance latents)
to pre-activation deltas of the control-point and Gaussian properties (:class:`PoseDeltas`).
:class:`~gsavatar.models.avatar.GaussianAvatar` adds them to its per-Gaussian biases,
activates and skins; biases, interpolation weights and skinning are shared by every head. The
head is chosen once, when the avatar is built, from ``ModelConfig.variant``
(:data:`POSE_HEADS`):

=========  ===============  ==========================================  ===============================
variant    head             pose input                                  output
=========  ===============  ==========================================  ===============================
ours       AnchorMLPHead    per anchor: its localized slots (masks)     coefficients ``w`` -> ``<w, ΔΛ>``
mmlps      MMLPsHead        per anchor: the full pose, hands localized  coefficients ``w`` -> ``<w, ΔΛ>``
conv_uv    UVDecoderHead    the full pose, one decoder in UV space      per-Gaussian deltas (no bases)
=========  ===============  ==========================================  ===============================

A head gets ``(config, hierarchy, pose_dim, generator, properties)`` to build itself (``properties``: the
avatar's property table), says which pose
slots each anchor's input sees (:meth:`PoseHead.input_mask`) and how many corrective bases
the avatar allocates for it (``n_basis``, ``n_ctrl_basis``), and maps a batch to
:class:`PoseDeltas` in :meth:`PoseHead.forward`. Adding a variant: a head class here,
registered in :data:`POSE_HEADS`, and a row in :data:`gsavatar.models.config.VARIANTS` that
names it (docs/architecture.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor, nn

from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.models import gaussians as gm
from gsavatar.models.config import ModelConfig
from gsavatar.models.encoder import sample_at_uv
from gsavatar.models.kernels import interpolated_deltas_fast
from gsavatar.models.mlp import AnchorMLPs
from gsavatar.models.properties import GAUSSIAN_PROPERTIES, GaussianProperty
from gsavatar.models.uv_decoder import UVDecoder

if TYPE_CHECKING:  # the avatar holds its head; the head reads the avatar's bases and inputs when called
    from gsavatar.models.avatar import GaussianAvatar


class PoseDeltas:
    """Pose-dependent pre-activation deltas, added to the avatar's biases: ``ctrl`` (control-point
    displacement, metres, [B, C, 3]) and one per property of the table (:mod:`gsavatar.models.properties`) by
    row name, e.g. ``position`` (canonical offset, metres), ``scale`` (log), ``rotation`` (unnormalised wxyz),
    ``sh0`` (pre-tanh), ``shn`` (the first ``n_sh_rest`` higher SH bands): [B, G, *dims]. None / absent: no
    delta. ``PoseDeltas(scale=x).scale`` is ``x``, ``PoseDeltas(scale=x).sh0`` None."""

    __slots__ = ("ctrl", "gauss")

    def __init__(self, ctrl: Tensor | None = None, **gauss: Tensor | None) -> None:
        self.ctrl = ctrl
        self.gauss: dict[str, Tensor] = {k: v for k, v in gauss.items() if v is not None}

    def __getattr__(self, name: str) -> Tensor | None:  # a property's delta by attribute, None when absent
        if name.startswith("_"):
            raise AttributeError(name)
        return self.gauss.get(name)


class PoseHead(nn.Module):
    """Base of the pose heads (module docstring). Subclasses take ``(config, hierarchy, pose_dim, generator,
    properties)``."""

    n_basis: int = 0
    """Gaussian corrective bases the avatar allocates per Gaussian for this head (``ΔΛ`` [G, n_basis, ...])."""
    n_ctrl_basis: int = 0
    """Control-point corrective bases per control point (``ΔΛ^c`` [C, n_ctrl_basis, 3])."""

    @staticmethod
    def input_mask(localized: np.ndarray, hand_slots: np.ndarray) -> np.ndarray:
        """Pose slots each anchor's input sees when ``ModelConfig.local_pose`` is on (off: all of them).

        localized [A, P] bool (the localization masks), hand_slots [P] bool (hand/finger slots) -> [A, P] bool
        """
        return np.ones_like(np.asarray(localized, bool))

    def forward(
        self, avatar: GaussianAvatar, pose: Tensor, face: Tensor | None, latents: Tensor | None, n_sh_rest: int
    ) -> PoseDeltas:
        """Deltas of one batch of frames.

        Args:
            avatar: the avatar holding this head (conditioning, interpolation weights, corrective bases)
            pose: Tensor  # [B, P] radians, raw (each head applies the avatar's conditioning PCA itself)
            face: Tensor | None  # [B, E] face embedding; None -> zeros
            latents: Tensor | None  # [B, A, L] appearance latents; None -> zeros
            n_sh_rest: higher SH coefficients to output, ``(sh_degree + 1)^2 - 1`` (0: ``shn`` is None)

        Returns:
            PoseDeltas  # [B, ...] (see its fields)
        """
        raise NotImplementedError


class AnchorMLPHead(PoseHead):
    """Ours (supp. A): one MLP per anchor maps ``[θ̂_i, φ̂_i, l_i]`` to ``n_basis`` Gaussian and ``n_ctrl_basis``
    control-point coefficients ``w``; Gaussians and control points interpolate them from their 3 nearest
    anchors, and the deltas are ``<w, ΔΛ>`` with the avatar's corrective bases."""

    def __init__(
        self,
        config: ModelConfig,
        hierarchy: Hierarchy,
        pose_dim: int,
        generator: torch.Generator,
        properties: Sequence[GaussianProperty] = GAUSSIAN_PROPERTIES,
    ) -> None:
        super().__init__()
        self.n_basis, self.n_ctrl_basis = int(config.n_basis), int(config.n_ctrl_basis)
        self.center_correctives = bool(config.center_correctives)
        latent_dim = config.latent_dim if config.use_latent else 0
        self.mlp = AnchorMLPs(
            hierarchy.num_anchors,
            pose_dim + config.face_dim + latent_dim,
            self.n_basis + self.n_ctrl_basis,
            config.hidden,
            config.mlp_out_init_scale,
            generator,
            init=config.mlp_init,
        )

    @staticmethod
    def input_mask(localized: np.ndarray, hand_slots: np.ndarray) -> np.ndarray:
        """Each anchor sees the slots of its localization mask. [A, P], [P] -> [A, P] bool"""
        return np.asarray(localized, bool).copy()

    def coefficients(self, x: Tensor) -> Tensor:
        """Anchor-MLP coefficients ``w`` (``center_correctives``: minus those of the reference input).

        x: Tensor  # [B, A, D] anchor inputs (:meth:`GaussianAvatar.anchor_inputs`) -> [B, A, n_basis + n_ctrl_basis]
        """
        if not self.center_correctives:
            return self.mlp(x)
        # Reference = the standardised mean input (zeros); one extra row through the same batched MLPs.
        y = self.mlp(torch.cat([x, x.new_zeros(1, *x.shape[1:])], dim=0))
        return y[:-1] - y[-1:]

    def forward(
        self, avatar: GaussianAvatar, pose: Tensor, face: Tensor | None, latents: Tensor | None, n_sh_rest: int
    ) -> PoseDeltas:
        coeffs = self.coefficients(avatar.anchor_inputs(pose, face, latents))  # [B, A, Bg + Bc]
        dev, dt, Bg = coeffs.device, coeffs.dtype, self.n_basis
        w_c = gm.sparse_interpolate(coeffs[..., Bg:], avatar.sparse_weights("ctrl_anchor", dev, dt))  # [B, C, Bc]
        ctrl = gm.basis_delta(avatar.ctrl_basis, w_c)
        d_a = self.anchor_sh0(avatar, coeffs[..., :Bg], latents)  # [B, A, 3] or None, both paths use it
        props = [p for p in avatar.PROPERTIES if p.basis is not None and (p.shape is not None or n_sh_rest)]
        fast = interpolated_deltas_fast(  # inference on CPU: one pass, same numbers (tests)
            coeffs[..., :Bg],
            avatar.sparse_weights("gauss_anchor", dev, dt),
            [getattr(avatar, n) for n in avatar.packed_bases],
            avatar.packed_layout(),
            n_sh_rest,
            d_a,
        )
        if fast is not None:
            return PoseDeltas(ctrl=ctrl, **{p.name: fast[p.name] for p in props})
        w_g = gm.sparse_interpolate(coeffs[..., :Bg], avatar.sparse_weights("gauss_anchor", dev, dt))  # [B, G, Bg]
        deltas = {}
        for p in props:  # <w_g, ΔΛ> per property (SH bands: the first n_sh_rest)
            basis = getattr(avatar, p.basis)
            delta = gm.basis_delta(basis if p.shape is not None else basis[:, :, :n_sh_rest], w_g)
            deltas[p.name] = self.with_anchor_terms(avatar, delta, d_a) if p.anchor_terms else delta
        return PoseDeltas(ctrl=ctrl, **deltas)

    @staticmethod
    def with_anchor_terms(avatar: GaussianAvatar, delta: Tensor, d_a: Tensor | None) -> Tensor:
        """``delta`` plus the anchors' deltas ``d_a`` (:meth:`anchor_sh0`) interpolated to the Gaussians.
        delta [B, G, 3], d_a [B, A, 3] or None -> [B, G, 3]"""
        if d_a is None:
            return delta
        return delta + gm.sparse_interpolate(d_a, avatar.sparse_weights("gauss_anchor", d_a.device, d_a.dtype))

    @staticmethod
    def anchor_sh0(avatar: GaussianAvatar, coeffs_g: Tensor, latents: Tensor | None = None) -> Tensor | None:
        """The anchors' SH0 deltas ``<w_a, ΔΛ^a_sh0> + l_a @ Λ^l_a`` (None: the avatar has neither map).
        coeffs_g [B, A, Bg], latents [B, A, L] or None -> [B, A, 3] or None"""
        d_a = None
        if avatar.sh0_anchor_basis is not None:
            d_a = torch.einsum("bak,akd->bad", coeffs_g, avatar.sh0_anchor_basis)  # [B, A, 3]
        if avatar.sh0_latent_basis is not None and latents is not None:
            d_l = torch.einsum("bal,ald->bad", latents.to(coeffs_g.dtype), avatar.sh0_latent_basis)  # [B, A, 3]
            d_a = d_l if d_a is None else d_a + d_l
        return d_a


class MMLPsHead(AnchorMLPHead):
    """MMLPs-dagger (paper section 4): the anchor MLPs of :class:`AnchorMLPHead`, each fed the full pose except
    the hand/finger parameters, which stay localized ("augmented with our localized face embedding and
    localized hand/finger pose conditioning")."""

    @staticmethod
    def input_mask(localized: np.ndarray, hand_slots: np.ndarray) -> np.ndarray:
        """All slots, the hand/finger ones localized. [A, P], [P] -> [A, P] bool"""
        localized = np.asarray(localized, bool)
        out = np.ones_like(localized)
        hand = np.asarray(hand_slots, bool)
        out[:, hand] = localized[:, hand]
        return out


class UVDecoderHead(PoseHead):
    """nRFGCA-dagger (paper section 4): one convolutional decoder of the full pose (and face) in UV space
    (:class:`~gsavatar.models.uv_decoder.UVDecoder`); every Gaussian reads its deltas of position, scale,
    rotation and SH at its own UV coordinate. No anchors, no corrective bases, no control-point deltas."""

    def __init__(
        self,
        config: ModelConfig,
        hierarchy: Hierarchy,
        pose_dim: int,
        generator: torch.Generator,
        properties: Sequence[GaussianProperty] = GAUSSIAN_PROPERTIES,
    ) -> None:
        super().__init__()
        uv = hierarchy.gaussians.uv
        if uv is None:
            raise ValueError(
                f"variant {config.variant!r} (nRFGCA-dagger) needs UV coordinates of the Gaussians; "
                "the hierarchy has none (template without UVs?)"
            )
        self.face_dim = int(config.face_dim)
        self.register_buffer("gauss_uv", torch.as_tensor(np.asarray(uv), dtype=torch.float32))  # [G, 2] OBJ convention
        # one output channel per value of every property with a correction (position, scale, rotation, SH0, SH)
        self.outputs = [(p.name, p.dims(config), p.shape is None) for p in properties if p.basis is not None]
        self.split_sizes = [int(np.prod(dims)) for _, dims, _ in self.outputs]
        self.uv_decoder = UVDecoder(
            pose_dim + self.face_dim,
            sum(self.split_sizes),
            config.uv_decoder_size,
            first_channels=config.uv_decoder_channels,
        )

    def forward(
        self, avatar: GaussianAvatar, pose: Tensor, face: Tensor | None, latents: Tensor | None, n_sh_rest: int
    ) -> PoseDeltas:
        x = avatar.conditioning_pose(pose)  # [B, P]
        if self.face_dim:
            x = torch.cat([x, face.to(x.dtype) if face is not None else x.new_zeros(x.shape[0], self.face_dim)], 1)
        vals = sample_at_uv(self.uv_decoder(x), self.gauss_uv)  # [B, G, n_out]
        deltas = {}
        for (name, dims, sh_bands), v in zip(self.outputs, vals.split(self.split_sizes, dim=-1)):
            if sh_bands:  # [B, G, n_sh_rest, 3]
                deltas[name] = v.reshape(*v.shape[:2], *dims)[:, :, :n_sh_rest] if n_sh_rest else None
            else:
                deltas[name] = v if len(dims) == 1 else v.reshape(*v.shape[:2], *dims)
        return PoseDeltas(ctrl=None, **deltas)


POSE_HEADS: dict[str, type[PoseHead]] = {"ours": AnchorMLPHead, "mmlps": MMLPsHead, "conv_uv": UVDecoderHead}
"""The pose head of each ``ModelConfig.variant`` (every head named in :data:`gsavatar.models.config.VARIANTS`)."""


def pose_head_class(variant: str) -> type[PoseHead]:
    """The head class of a ``ModelConfig.variant``; ValueError naming the registered ones otherwise."""
    if variant not in POSE_HEADS:
        raise ValueError(f"no pose head for variant {variant!r}; registered: {sorted(POSE_HEADS)}")
    return POSE_HEADS[variant]
