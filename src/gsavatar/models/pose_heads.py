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

A head gets ``(config, hierarchy, pose_dim, generator)`` to build itself, says which pose
slots each anchor's input sees (:meth:`PoseHead.input_mask`) and how many corrective bases
the avatar allocates for it (``n_basis``, ``n_ctrl_basis``), and maps a batch to
:class:`PoseDeltas` in :meth:`PoseHead.forward`. Adding a variant: a head class here,
registered in :data:`POSE_HEADS`, and a row in :data:`gsavatar.models.config.VARIANTS` that
names it (docs/architecture.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.models import gaussians as gm
from gsavatar.models.config import ModelConfig
from gsavatar.models.encoder import sample_at_uv
from gsavatar.models.kernels import interpolated_deltas_fast
from gsavatar.models.mlp import AnchorMLPs
from gsavatar.models.uv_decoder import UVDecoder

if TYPE_CHECKING:  # the avatar holds its head; the head reads the avatar's bases and inputs when called
    from gsavatar.models.avatar import GaussianAvatar


class PoseDeltas(NamedTuple):
    """Pose-dependent pre-activation deltas, added to the avatar's biases (None: no delta)."""

    ctrl: Tensor | None = None
    """Control-point displacement, metres.  # [B, C, 3]"""
    position: Tensor | None = None
    """Canonical Gaussian offset, metres.  # [B, G, 3]"""
    scale: Tensor | None = None
    """Log-scale.  # [B, G, 3]"""
    rotation: Tensor | None = None
    """Unnormalised wxyz quaternion.  # [B, G, 4]"""
    sh0: Tensor | None = None
    """SH band 0, pre-tanh.  # [B, G, 3]"""
    shn: Tensor | None = None
    """The first ``n_sh_rest`` higher SH coefficients, pre-tanh.  # [B, G, n_sh_rest, 3]"""


class PoseHead(nn.Module):
    """Base of the pose heads (module docstring). Subclasses take ``(config, hierarchy, pose_dim, generator)``."""

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

    def __init__(self, config: ModelConfig, hierarchy: Hierarchy, pose_dim: int, generator: torch.Generator) -> None:
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
        fast = interpolated_deltas_fast(  # inference on CPU: one pass, same numbers (tests)
            coeffs[..., :Bg],
            avatar.sparse_weights("gauss_anchor", dev, dt),
            avatar.gauss_pos_basis,
            avatar.scale_basis,
            avatar.rotation_basis,
            avatar.sh0_basis,
            avatar.shn_basis,
            n_sh_rest,
            d_a,
        )
        if fast is not None:
            pos, scale, rot, sh0, shn = fast
            return PoseDeltas(
                ctrl=ctrl, position=pos, scale=scale, rotation=rot, sh0=sh0, shn=shn if n_sh_rest else None
            )
        w_g = gm.sparse_interpolate(coeffs[..., :Bg], avatar.sparse_weights("gauss_anchor", dev, dt))  # [B, G, Bg]
        return PoseDeltas(
            ctrl=ctrl,
            position=gm.basis_delta(avatar.gauss_pos_basis, w_g),
            scale=gm.basis_delta(avatar.scale_basis, w_g),
            rotation=gm.basis_delta(avatar.rotation_basis, w_g),
            sh0=self.sh0_delta(avatar, w_g, d_a),
            shn=gm.basis_delta(avatar.shn_basis[:, :, :n_sh_rest], w_g) if n_sh_rest else None,
        )

    @staticmethod
    def sh0_delta(avatar: GaussianAvatar, w_g: Tensor, d_a: Tensor | None) -> Tensor:
        """``<w_g, ΔΛ_sh0>`` per Gaussian, plus the anchors' SH0 deltas ``d_a`` (:meth:`anchor_sh0`) interpolated
        to the Gaussians. w_g [B, G, Bg], d_a [B, A, 3] or None -> [B, G, 3]"""
        d = gm.basis_delta(avatar.sh0_basis, w_g)
        if d_a is None:
            return d
        return d + gm.sparse_interpolate(d_a, avatar.sparse_weights("gauss_anchor", d_a.device, d_a.dtype))

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

    def __init__(self, config: ModelConfig, hierarchy: Hierarchy, pose_dim: int, generator: torch.Generator) -> None:
        super().__init__()
        uv = hierarchy.gaussians.uv
        if uv is None:
            raise ValueError(
                f"variant {config.variant!r} (nRFGCA-dagger) needs UV coordinates of the Gaussians; "
                "the hierarchy has none (template without UVs?)"
            )
        self.face_dim = int(config.face_dim)
        self.register_buffer("gauss_uv", torch.as_tensor(np.asarray(uv), dtype=torch.float32))  # [G, 2] OBJ convention
        self.split_sizes = [3, 3, 4, 3, (config.num_sh - 1) * 3]  # position, scale, rotation, SH0, higher SH
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
        pos, scale, rot, sh0, shn = vals.split(self.split_sizes, dim=-1)
        shn = shn.reshape(*shn.shape[:2], -1, 3)[:, :, :n_sh_rest] if n_sh_rest else None  # [B, G, n_sh_rest, 3]
        return PoseDeltas(ctrl=None, position=pos, scale=scale, rotation=rot, sh0=sh0, shn=shn)


POSE_HEADS: dict[str, type[PoseHead]] = {"ours": AnchorMLPHead, "mmlps": MMLPsHead, "conv_uv": UVDecoderHead}
"""The pose head of each ``ModelConfig.variant`` (every head named in :data:`gsavatar.models.config.VARIANTS`)."""


def pose_head_class(variant: str) -> type[PoseHead]:
    """The head class of a ``ModelConfig.variant``; ValueError naming the registered ones otherwise."""
    if variant not in POSE_HEADS:
        raise ValueError(f"no pose head for variant {variant!r}; registered: {sorted(POSE_HEADS)}")
    return POSE_HEADS[variant]
