"""The drivable Gaussian avatar: a pose head + per-Gaussian biases and corrective bases (supp. A).

:class:`GaussianAvatar` only holds parameters and constant buffers; the math lives
in :mod:`gsavatar.models.gaussians`, the pose-dependent part in its pose head
(:mod:`gsavatar.models.pose_heads`, chosen once from ``ModelConfig.variant``).

Per frame (pose head ``ours``), every anchor MLP maps ``[θ̂_i, φ̂_i, l_i]`` (masked conditioning pose,
masked face embedding, appearance latent) to ``n_basis`` Gaussian and
``n_ctrl_basis`` control-point coefficients. Gaussians and control points
interpolate them from their 3 nearest anchors. Gaussian properties
``p = h(λ + <w, ΔΛ>)``, one row each of the property table
(:data:`gsavatar.models.properties.GAUSSIAN_PROPERTIES`, which builds the parameters below):

==================  ======  =====================  ===================================
property            dims    basis                  activation h
==================  ======  =====================  ===================================
scale               3       [G, n_basis, 3]        ``min(exp(x), scale_max)`` metres
rotation            4       [G, n_basis, 4]        normalise (wxyz)
opacity             1       none (bias only)       sigmoid
SH band 0           3       [G, n_basis, 3]        ``tanh(x) * 0.5 / C0``
SH bands 1..        (K-1)x3 [G, n_basis, K-1, 3]   ``shn_bound * tanh(x)``
position offset     3       [G, n_basis, 3]        none, no bias ("-/1e-4")
==================  ======  =====================  ===================================

Control points: displacement ``λ^c + <w^c, ΔΛ^c>`` ([C, 3], [C, n_ctrl_basis, 3]).
Canonical Gaussian centre = rest position + 3-NN interpolated control displacement
+ Gaussian offset; then LBS with the Gaussians' transferred skin weights and the
*raw* driving pose (PCA only shapes the MLP input). Posed rotation =
``polar(blended 3x3) @ R(q)``.

Every pose head outputs pre-activation deltas (:class:`~gsavatar.models.pose_heads.PoseDeltas`),
added to the same biases: ``<w, ΔΛ>`` for the anchor-MLP heads (``ours``, ``mmlps``); the
``conv_uv`` head (nRFGCA-dagger) has no anchor MLPs and no bases, its convolutional UV decoder
of the full pose gives every Gaussian its deltas of position, scale, rotation and SH directly.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.data_schema.localization import LocalizationMasks
from gsavatar.data_schema.pose_pca import PosePCA, pca_project
from gsavatar.data_schema.rig import BODY_GROUPS, Rig
from gsavatar.geometry.lbs import RigTensors, skinning_transforms
from gsavatar.models import gaussians as gm
from gsavatar.models.config import INPUT_STD_FLOOR, LearningRates, ModelConfig
from gsavatar.models.pose_heads import PoseDeltas, PoseHead, pose_head_class
from gsavatar.models.properties import (
    GAUSSIAN_PROPERTIES,
    RENDERED,
    GaussianProperty,
    InitContext,
    PackedLayout,
    check_table,
    packed_layout,
    registration_order,
)


class AvatarOutput(NamedTuple):
    means: Tensor
    """Posed world centres, metres.  # [B, G, 3]"""
    quats: Tensor
    """Posed world rotations, unit wxyz.  # [B, G, 4]"""
    scales: Tensor
    """Activated scales (standard deviations), metres.  # [B, G, 3]"""
    opacities: Tensor
    """Activated opacities in (0, 1).  # [B, G]"""
    sh: Tensor
    """SH coefficients, K = (sh_degree + 1)^2 of the requested degree; colour = SH·Y + 0.5.  # [B, G, K, 3]"""
    ctrl_disp: Tensor
    """Canonical control-point displacements, metres.  # [B, C, 3]"""
    canonical_means: Tensor
    """Canonical (rest-space) centres incl. offsets.  # [B, G, 3]"""


def _check(name: str, t: Tensor | None, shape: tuple) -> None:
    if t is None:
        raise ValueError(f"{name} is required, expected shape {shape}")
    if t.ndim != len(shape) or any(e is not None and e != a for e, a in zip(shape, t.shape)):
        pretty = "[" + ", ".join("B" if e is None else str(e) for e in shape) + "]"
        raise ValueError(f"{name} must be {pretty}, got {list(t.shape)}")


class GaussianAvatar(nn.Module):
    """Pose head + per-Gaussian biases and corrective bases over a prepared hierarchy (see module docstring)."""

    def __init__(
        self,
        hierarchy: Hierarchy,
        masks: LocalizationMasks,
        rig: Rig,
        pca_local: PosePCA | None,
        pca_global: PosePCA | None,
        config: ModelConfig,
        face_dim: int | None = None,
        seed: int = 0,
    ) -> None:
        super().__init__()
        cfg = config if face_dim is None else config.replace(face_dim=int(face_dim))
        self.config = cfg
        self.rig = rig
        A, C, G, P = hierarchy.num_anchors, hierarchy.num_control, hierarchy.num_gaussians, rig.pose_dim
        if masks.pose.shape != (A, P) or masks.face.shape != (A,):
            raise ValueError(f"masks must be pose [{A}, {P}] / face [{A}], got {masks.pose.shape} / {masks.face.shape}")
        needs = {"local": ["local"], "global": ["global"], "global_test_only": ["global"], "none": []}[cfg.pca]
        for kind, pca in (("local", pca_local), ("global", pca_global)):
            if kind in needs and pca is None:
                raise ValueError(f"config.pca={cfg.pca!r} needs pca_{kind}")
            if pca is not None:
                pca.check_rig(rig)
        self.num_anchors, self.num_control, self.num_gaussians, self.pose_dim = A, C, G, P
        self._rig_cache: dict = {}
        self._sparse_cache: dict = {}

        # --- constant buffers ---------------------------------------------------------
        f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        i64 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.long)  # noqa: E731
        g = hierarchy.gaussians
        self.register_buffer("rest_means", f32(g.position))  # [G, 3] rest positions, metres
        self.register_buffer("skin_indices", i64(g.skin_indices))  # [G, K]
        self.register_buffer("skin_weights", f32(g.skin_weights))  # [G, K]
        self.register_buffer("gauss_anchor_idx", i64(hierarchy.gauss_anchor_idx))  # [G, 3]
        self.register_buffer("gauss_anchor_w", f32(hierarchy.gauss_anchor_w))  # [G, 3]
        self.register_buffer("ctrl_anchor_idx", i64(hierarchy.ctrl_anchor_idx))  # [C, 3]
        self.register_buffer("ctrl_anchor_w", f32(hierarchy.ctrl_anchor_w))  # [C, 3]
        self.register_buffer("gauss_ctrl_idx", i64(hierarchy.gauss_ctrl_idx))  # [G, 3]
        self.register_buffer("gauss_ctrl_w", f32(hierarchy.gauss_ctrl_w))  # [G, 3]
        self.register_buffer("ctrl_neighbors", i64(hierarchy.ctrl_neighbors))  # [C, n] (smoothness loss)
        self.register_buffer("ctrl_rest", f32(hierarchy.control.position))  # [C, 3]
        auv = hierarchy.anchors.uv if hierarchy.anchors.uv is not None else np.zeros((A, 2))
        self.register_buffer("anchor_uv", f32(auv))  # [A, 2] OBJ convention (v up)
        head_cls = pose_head_class(cfg.variant)
        hand_slots = np.isin(rig.slot_groups(), [BODY_GROUPS.index(h) for h in gm.HAND_GROUP_NAMES])  # [P]
        # local_pose=False (ablation "w/o local pose"): every anchor sees every pose slot, whatever the head
        pm = head_cls.input_mask(masks.pose, hand_slots) if cfg.local_pose else np.ones_like(masks.pose, bool)
        self.register_buffer("pose_mask", f32(pm))  # [A, P] 0/1
        self.register_buffer("face_mask", f32(masks.face))  # [A] 0/1
        for kind, pca in (("local", pca_local), ("global", pca_global)):
            for name, arr in (
                ("mean", None if pca is None else pca.mean),
                ("basis", None if pca is None else pca.basis),
                ("limit", None if pca is None else pca.clamp_sigma * pca.sigma),
            ):
                self.register_buffer(f"pca_{kind}_{name}", None if arr is None else f32(arr))

        if cfg.input_norm:  # filled by set_input_stats (else identity); saved with the checkpoint
            self.register_buffer("pose_in_mean", torch.zeros(P))  # [P] conditioning pose, train frames
            self.register_buffer("pose_in_std", torch.ones(P))  # [P]
            self.register_buffer("face_in_mean", torch.zeros(cfg.face_dim))  # [E]
            self.register_buffer("face_in_std", torch.ones(cfg.face_dim))  # [E]

        # --- parameters ------------------------------------------------------------------
        gen = torch.Generator().manual_seed(seed)
        self.latent_in = cfg.latent_dim if cfg.use_latent else 0
        self.pose_head: PoseHead = head_cls(cfg, hierarchy, P, gen, self.PROPERTIES)
        Bg, Bc = self.pose_head.n_basis, self.pose_head.n_ctrl_basis  # 0: the head outputs its deltas directly
        log_s, q = gm.init_gaussian_params(g.position, g.normal, cfg.scale_max, cfg.init_normal_scale_ratio)
        z = lambda *s: nn.Parameter(torch.zeros(*s))  # noqa: E731
        check_table(self.PROPERTIES)
        ctx = InitContext(cfg, G, log_s, q)
        for prop in registration_order(self.PROPERTIES):  # {bias} [G, *dims] (opacity: [G]), {basis} [G, Bg, *dims]
            dims = prop.dims(cfg)
            if prop.bias is not None:
                shape = (G,) if prop.bias_squeeze else (G, *dims)
                init = None if prop.init is None else prop.init(ctx)
                setattr(self, prop.bias, z(*shape) if init is None else nn.Parameter(f32(init).reshape(shape)))
            if prop.basis is not None:
                setattr(self, prop.basis, z(G, Bg, *dims))
        self.ctrl_bias = z(C, 3)  # [C, 3] metres
        self.ctrl_basis = z(C, Bc, 3)
        # the anchors' deltas of the row with anchor_terms (SH0), interpolated to the Gaussians like ``w``:
        # ModelConfig.anchor_sh0: a basis per anchor; ModelConfig.latent_sh0: latent -> delta per anchor
        at = next((p for p in self.PROPERTIES if p.anchor_terms), None)
        da = () if at is None else at.dims(cfg)
        self.sh0_anchor_basis = z(A, Bg, *da) if at and cfg.anchor_sh0 and Bg else None  # [A, Bg, 3] pre-tanh
        self.sh0_latent_basis = z(A, self.latent_in, *da) if at and cfg.latent_sh0 and self.latent_in else None

    # --- helpers -------------------------------------------------------------------------
    PROPERTIES: tuple[GaussianProperty, ...] = GAUSSIAN_PROPERTIES
    """The Gaussian properties this avatar learns (models/properties.py; a subclass may add rows)."""

    @property
    def packed_bases(self) -> tuple[str, ...]:
        """The Gaussian corrective bases :meth:`pack_bases_` lays side by side: the table's rows with a basis."""
        return tuple(p.basis for p in self.PROPERTIES if p.basis is not None)

    def packed_layout(self) -> PackedLayout:
        """Columns of each basis in the packed tensor (:func:`~gsavatar.models.properties.packed_layout`)."""
        return packed_layout(self.PROPERTIES, self.config)

    def pack_bases_(self) -> bool:
        """Store the Gaussian corrective bases side by side in one ``[G, Bg, 13 + 3(K-1)]`` tensor, each
        parameter a view of it (values, shapes and parameter objects unchanged), so inference reads them
        as one stream (:func:`~gsavatar.models.kernels.interpolated_deltas_fast`, ~1.5x faster on CPU).
        For inference (:func:`~gsavatar.runs.load.load_run` calls it); training works on the views too.
        ``.to()`` and the like unpack them again. Returns whether there was anything to pack."""
        params = [getattr(self, n) for n in self.packed_bases]
        G, Bg = params[0].shape[:2]
        if Bg == 0 or G == 0:
            return False
        with torch.no_grad():
            packed = torch.cat([p.detach().reshape(G, Bg, -1) for p in params], dim=2)
        offset = 0
        for p in params:
            width = int(np.prod(p.shape[2:]))
            p.data = packed[:, :, offset : offset + width].unflatten(2, p.shape[2:])
            offset += width
        return True

    _LEGACY_HEAD_KEYS = ("mlp.", "uv_decoder.", "gauss_uv")
    """State-dict keys of the pose network before it moved into ``pose_head`` (checkpoints of earlier runs)."""

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        legacy = [k for k in state_dict if k.startswith(prefix) and k[len(prefix) :].startswith(self._LEGACY_HEAD_KEYS)]
        for key in legacy:
            state_dict[f"{prefix}pose_head.{key[len(prefix) :]}"] = state_dict.pop(key)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def sparse_weights(self, name: str, device: torch.device, dtype: torch.dtype) -> Tensor:
        """Interpolation weights as a sparse matrix, built once per device/dtype from the index/weight buffers:
        ``gauss_anchor`` [G, A], ``ctrl_anchor`` [C, A], ``gauss_ctrl`` [G, C], ``skin`` [G, J]."""
        key = (name, device, dtype)
        if key not in self._sparse_cache:
            idx, w, m = {
                "gauss_anchor": (self.gauss_anchor_idx, self.gauss_anchor_w, self.num_anchors),
                "ctrl_anchor": (self.ctrl_anchor_idx, self.ctrl_anchor_w, self.num_anchors),
                "gauss_ctrl": (self.gauss_ctrl_idx, self.gauss_ctrl_w, self.num_control),
                "skin": (self.skin_indices, self.skin_weights, self.rig.num_joints),
            }[name]
            self._sparse_cache[key] = gm.interpolation_matrix(idx.to(device), w.to(device, dtype), m)
        return self._sparse_cache[key]

    def _apply(self, fn, recurse=True):  # .to()/.double() etc.: rebuild the sparse matrices lazily
        self._sparse_cache = {}
        return super()._apply(fn, recurse)

    def rig_tensors(self, device: torch.device, dtype: torch.dtype) -> RigTensors:
        key = (device, dtype)
        if key not in self._rig_cache:
            self._rig_cache[key] = RigTensors(self.rig, device, dtype)
        return self._rig_cache[key]

    def conditioning_pose(self, pose: Tensor) -> Tensor:
        """Pose-head pose input after the configured PCA (mode depends on ``self.training``). [B, P] -> [B, P]"""
        mode = gm.pca_mode_for(self.config.pca, self.training)
        if mode == "none":
            return pose
        m, b, lim = (getattr(self, f"pca_{mode}_{n}") for n in ("mean", "basis", "limit"))
        return pca_project(pose, m.to(pose.dtype), b.to(pose.dtype), lim.to(pose.dtype))

    @torch.no_grad()
    def set_input_stats(self, pose: Tensor, face: Tensor | None = None) -> None:
        """``input_norm``: per-parameter mean/std of the MLP inputs over the training frames.

        pose [F, P] raw radians (the conditioning PCA of training mode is applied here), face [F, E] or None.
        """
        if not self.config.input_norm:
            raise ValueError("set_input_stats needs config.input_norm=True")
        _check("pose", pose, (None, self.pose_dim))
        was = self.training
        self.train(True)
        x = self.conditioning_pose(pose.to(self.pose_in_mean))
        self.train(was)
        self.pose_in_mean.copy_(x.mean(0))
        self.pose_in_std.copy_(x.std(0, correction=0).clamp_min(INPUT_STD_FLOOR))
        if self.config.face_dim and face is not None:
            _check("face", face, (pose.shape[0], self.config.face_dim))
            f = face.to(self.face_in_mean)
            self.face_in_mean.copy_(f.mean(0))
            self.face_in_std.copy_(f.std(0, correction=0).clamp_min(INPUT_STD_FLOOR))

    def anchor_inputs(self, pose: Tensor, face: Tensor | None = None, latents: Tensor | None = None) -> Tensor:
        """Per-anchor MLP input ``[θ̂_i, φ̂_i, l_i]``. pose [B, P], face [B, E], latents [B, A, L] -> [B, A, P+E+L]"""
        dt = pose.dtype
        x = self.conditioning_pose(pose)
        if self.config.input_norm:
            x = (x - self.pose_in_mean.to(dt)) / self.pose_in_std.to(dt)
            if face is not None and self.config.face_dim:
                face = (face.to(dt) - self.face_in_mean.to(dt)) / self.face_in_std.to(dt)
        return gm.anchor_inputs(
            x,
            self.pose_mask.to(dt),
            face,
            self.face_mask.to(dt),
            self.config.face_dim,
            latents if self.latent_in else None,
            self.latent_in,
        )

    def _validate(self, pose, root_rotation, root_translation, face, latents, sh_degree) -> None:
        _check("pose", pose, (None, self.pose_dim))
        B = pose.shape[0]
        _check("root_rotation", root_rotation, (B, 3))
        _check("root_translation", root_translation, (B, 3))
        if face is not None:
            if self.config.face_dim == 0:
                raise ValueError(f"face given with shape {list(face.shape)} but the model has face_dim=0")
            _check("face", face, (B, self.config.face_dim))
        if latents is not None and self.latent_in:
            _check("latents", latents, (B, self.num_anchors, self.latent_in))
        if not 0 <= sh_degree <= self.config.sh_degree:
            raise ValueError(f"sh_degree must be in [0, {self.config.sh_degree}], got {sh_degree}")

    # --- forward ---------------------------------------------------------------------------
    def forward(
        self,
        pose: Tensor,
        root_rotation: Tensor,
        root_translation: Tensor,
        face: Tensor | None = None,
        latents: Tensor | None = None,
        sh_degree: int | None = None,
        correctives: bool = True,
    ) -> AvatarOutput:
        """Posed Gaussians for a batch of frames.

        Args:
            pose: Tensor  # [B, P] radians, rig order (raw; PCA applied to the pose head's input only)
            root_rotation: Tensor  # [B, 3] axis-angle
            root_translation: Tensor  # [B, 3] metres
            face: Tensor | None  # [B, E] face embedding; None -> zeros
            latents: Tensor | None  # [B, A, L] appearance latents; None -> zeros; ignored if not use_latent
            sh_degree: SH degree to output (<= config.sh_degree; None -> config.sh_degree)
            correctives: evaluate the pose head; False -> bias terms only (early training)

        Returns:
            AvatarOutput (see its fields)
        """
        return self.evaluate(pose, root_rotation, root_translation, face, latents, sh_degree, correctives)[0]

    def evaluate(
        self,
        pose: Tensor,
        root_rotation: Tensor,
        root_translation: Tensor,
        face: Tensor | None = None,
        latents: Tensor | None = None,
        sh_degree: int | None = None,
        correctives: bool = True,
    ) -> tuple[AvatarOutput, dict[str, Tensor]]:
        """:meth:`forward` and the activated properties of the table's rows the renderer does not read
        (:data:`~gsavatar.models.properties.RENDERED`; models/properties.py), by name: [B, G, *dims]."""
        deg = self.config.sh_degree if sh_degree is None else int(sh_degree)
        self._validate(pose, root_rotation, root_translation, face, latents, deg)
        B, n_rest = pose.shape[0], (deg + 1) ** 2 - 1
        d = self.pose_head(self, pose, face, latents, n_rest) if correctives else PoseDeltas()
        unknown = set(d.gauss) - {p.name for p in self.PROPERTIES}
        if unknown:
            raise ValueError(f"pose head gave deltas of {sorted(unknown)}, not properties of this avatar")
        ctrl_disp = gm.add_delta(self.ctrl_bias, d.ctrl, B)  # [B, C, 3]
        offset = gm.sparse_interpolate(
            ctrl_disp, self.sparse_weights("gauss_ctrl", ctrl_disp.device, ctrl_disp.dtype)
        )  # [B, G, 3]
        if d.position is not None:
            offset = offset + d.position
        canonical = self.rest_means[None] + offset  # [B, G, 3]
        values = self.activate(d, B, n_rest)  # [B, G, *dims] per property, the position offset excepted
        sh0 = values["sh0"]  # [B, G, 3]
        sh = torch.cat([sh0[:, :, None], values["shn"]], dim=2) if n_rest else sh0[:, :, None]  # [B, G, K, 3]
        extras = {k: v for k, v in values.items() if k not in RENDERED}

        T = skinning_transforms(
            self.rig_tensors(pose.device, pose.dtype), pose, root_rotation, root_translation
        )  # [B, J, 4, 4]
        means, quats = gm.pose_lbs(
            canonical,
            values["rotation"],
            T,
            self.skin_indices,
            self.skin_weights,
            self.sparse_weights("skin", T.device, T.dtype),
        )
        return AvatarOutput(means, quats, values["scale"], values["opacity"], sh, ctrl_disp, canonical), extras

    def activate(self, d: PoseDeltas, batch: int, n_sh_rest: int) -> dict[str, Tensor]:
        """Every property of the table but the position offset: ``h(λ + Δ)`` (a row without a basis: ``h(λ)``
        once, expanded over the batch; a row without a bias: ``h(Δ)``). SH bands rows keep the first
        ``n_sh_rest`` bands (none: left out). -> name: [B, G, *dims]"""
        cfg, out = self.config, {}
        for p in self.PROPERTIES:
            if p.name == "position":  # consumed by the canonical centres
                continue
            bias = None if p.bias is None else getattr(self, p.bias)
            delta = d.gauss.get(p.name)
            if p.shape is None:  # SH bands: the degree asked for
                if not n_sh_rest:
                    continue
                bias = None if bias is None else bias[:, :n_sh_rest]
            act = (lambda x: x) if p.activation is None else (lambda x, p=p: p.activation(x, cfg))
            if p.basis is None:  # no pose delta: one activation, expanded over the frames
                out[p.name] = act(bias)[None].expand(batch, *bias.shape)
            elif bias is None:
                if delta is None:
                    raise ValueError(f"property {p.name!r} has no bias and the pose head gave no delta")
                out[p.name] = act(delta)
            else:
                out[p.name] = act(gm.add_delta(bias, delta, batch))
        return out

    # --- optimisation ----------------------------------------------------------------------
    def _groups(self) -> list[tuple[str, str]]:
        """(parameter, LearningRates field) of every parameter but the pose head's: the table's biases and bases,
        the control points', the anchors' SH0 maps (at the rate of the SH0 basis)."""
        biased, tail = [], []  # rows with a bias, the bias-less rows' bases (registration_order)
        for p in registration_order(self.PROPERTIES):
            rows = biased if p.bias is not None else tail
            rows += [(p.bias, p.lr_bias)] if p.bias is not None else []
            rows += [(p.basis, p.lr_basis)] if p.basis is not None else []
        at = next((p for p in self.PROPERTIES if p.anchor_terms), None)
        extra = [(n, at.lr_basis) for n in ("sh0_anchor_basis", "sh0_latent_basis")] if at is not None else []
        # the control points' between the two: the groups' order before the table (checkpoints' optimiser states)
        return [*biased, ("ctrl_bias", "ctrl_bias"), ("ctrl_basis", "ctrl_basis"), *tail, *extra]

    def param_groups(self, lrs: LearningRates | None = None) -> list[dict]:
        """AdamW parameter groups with the paper's per-property learning rates (supp. D.1).

        Every group has ``name``, ``params``, ``lr`` and ``weight_decay`` (group ``mlp``, the pose head's
        network: ``lrs.mlp`` and ``lrs.mlp_weight_decay``; everything else weight decay 0). Empty parameters
        (SH bands at degree 0, the bases of a head without any) are left out. Use with
        ``torch.optim.AdamW(groups, eps=1e-15, betas=(0.9, 0.999))``.
        """
        lrs = lrs or LearningRates()
        groups = [
            {
                "name": "mlp",
                "params": list(self.pose_head.parameters()),
                "lr": lrs.mlp,
                "weight_decay": lrs.mlp_weight_decay,
            }
        ]
        for attr, lr_name in self._groups():
            p = getattr(self, attr)
            if p is not None and p.numel():
                groups.append({"name": attr, "params": [p], "lr": getattr(lrs, lr_name), "weight_decay": 0.0})
        covered = {id(p) for g in groups for p in g["params"]}
        missing = [n for n, p in self.named_parameters() if id(p) not in covered and p.numel()]
        if missing:  # pragma: no cover - guards future parameters
            raise RuntimeError(f"parameters without an optimiser group: {missing}")
        return groups

    def parameter_counts(self) -> dict[str, int]:
        """Number of scalars per parameter group (and ``total``)."""
        out = {"mlp": sum(p.numel() for p in self.pose_head.parameters())}
        out.update({a: getattr(self, a).numel() for a, _ in self._groups() if getattr(self, a) is not None})
        out["total"] = sum(out.values())
        return out
