"""Model configuration: :class:`ModelConfig`, learning rates and named presets.

Paper sizes (supp. D.1 / D.2): anchor MLPs with hidden layers ``(512, 256, 256, 256)``,
16 Gaussian-corrective and 16 control-point coefficients per anchor, appearance
latents ``N_l = 16``, SH up to degree 1.

Every model variant of the paper (ours, ablations, baselines; section 4) is one row of
:data:`VARIANTS`: the ``ModelConfig`` fields it sets, among them ``variant``, the pose head
(:mod:`gsavatar.models.pose_heads`). The allowed names (:data:`VariantName`, the CLI's
``--variant`` choices) and the pose-head names (:data:`Variant`) are derived from that table.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from gsavatar.utils.jsonio import config_to_json

PcaMode = Literal["local", "global", "global_test_only", "none"]
PresetName = Literal["tiny", "small", "paper"]

VARIANTS: dict[str, dict[str, object]] = {
    "ours": dict(variant="ours", local_pose=True, pca="local", use_latent=True),
    "wo_local_pose": dict(variant="ours", local_pose=False, pca="local", use_latent=True),  # ablation
    "wo_local_pca": dict(variant="ours", local_pose=True, pca="global", use_latent=True),  # ablation
    "wo_appearance": dict(variant="ours", local_pose=True, pca="local", use_latent=False),  # ablation
    "mmlps_dagger": dict(variant="mmlps", local_pose=True, pca="global_test_only", use_latent=False),  # baseline
    "nrfgca_dagger": dict(variant="conv_uv", local_pose=False, pca="none", use_latent=False),  # baseline
}
"""The paper's model, ablations and baselines (section 4): name -> the :class:`ModelConfig` fields it sets
(:func:`variant_config`). ``variant`` names the pose head (:data:`gsavatar.models.pose_heads.POSE_HEADS`):
``ours`` localized anchor MLPs, ``mmlps`` anchor MLPs of the full pose (MMLPs-dagger), ``conv_uv`` one
convolutional UV decoder of the full pose (nRFGCA-dagger). Adding a variant: a row here (and, for a new
kind of network, a pose head)."""


def pose_head_names() -> tuple[str, ...]:
    """The pose heads :data:`VARIANTS` uses, in table order (the values ``ModelConfig.variant`` accepts)."""
    return tuple(dict.fromkeys(str(row["variant"]) for row in VARIANTS.values()))


# Both name sets come from the table (typing.get_args gives them back; tyro builds the CLI choices from them).
VariantName = Literal[tuple(VARIANTS)]  # type: ignore[valid-type]
"""Names of :data:`VARIANTS` (``TrainConfig.variant``)."""
Variant = Literal[pose_head_names()]  # type: ignore[valid-type]
"""Pose-head names used by :data:`VARIANTS` (``ModelConfig.variant``)."""

INPUT_STD_FLOOR = 0.05
"""Floor of the per-parameter std used by ``input_norm`` (radians / face units): parameters that hardly
move in the training frames are not blown up at test time."""

SH_C0 = 0.28209479177387814
"""Band-0 real SH constant: ``colour = SH0 * SH_C0 + 0.5``."""


@dataclass(frozen=True)
class ModelConfig:
    """Hyper-parameters of the Gaussian avatar (anchor MLPs + per-Gaussian bases)."""

    hidden: tuple[int, ...] = (512, 256, 256, 256)
    """Hidden layer widths of every anchor MLP (paper: 512, 256, 256, 256)."""
    n_basis: int = 16
    """Gaussian corrective coefficients per anchor (length of ``w`` in supp. A, paper 16)."""
    n_ctrl_basis: int = 16
    """Control-point corrective coefficients per anchor (paper 16)."""
    latent_dim: int = 16
    """Appearance latent size ``N_l`` per anchor (paper 16); unused when ``use_latent`` is False."""
    sh_degree: int = 1
    """Maximum SH degree (paper: 0 for the first 60k iterations, then 1)."""
    scale_max: float = 0.05
    """Upper clamp of the activated Gaussian scale, metres. The paper's "0.2" is in its
    own (unstated, not metric) units; 5 cm is our metric equivalent for a human body."""
    variant: Variant = "ours"
    """Pose head (:data:`gsavatar.models.pose_heads.POSE_HEADS`), one of the heads :data:`VARIANTS` uses:
    ``ours`` per-anchor localized pose; ``mmlps`` MMLPs baseline, every anchor sees the full pose
    except the hand/finger parameters, which stay localized ("augmented with our localized face
    embedding and localized hand/finger pose conditioning"); ``conv_uv`` nRFGCA-dagger, a
    convolutional UV decoder of the full pose (no anchors)."""
    local_pose: bool = True
    """Multiply each anchor's pose input by its pose mask. False = ablation "w/o local
    pose": every anchor sees every pose parameter (hands included, any variant)."""
    pca: PcaMode = "local"
    """Pose PCA applied to the MLP pose input (never to the skinning pose): ``local`` in
    train and test (ours), ``global`` in train and test (ablation "w/o local PCA"),
    ``global_test_only`` only in eval mode (MMLPs-dagger), ``none``."""
    use_latent: bool = True
    """Feed the per-anchor appearance latent to the MLPs (False for MMLPs-dagger)."""
    face_dim: int = 0
    """Face embedding size ``E`` (from the capture's ``motion.face``; 0 = no face input)."""
    init_opacity: float = 0.9
    """Initial activated opacity of every Gaussian."""
    init_normal_scale_ratio: float = 0.3
    """Initial scale along the surface normal relative to the tangent scale (flat Gaussians)."""
    shn_bound: float = 1.0
    """Higher-order SH coefficients are ``shn_bound * tanh(x)`` (a degree-1 term shifts
    colour by at most ``0.489 * shn_bound``)."""
    mlp_out_init_scale: float = 1.0
    """Scale of the anchor MLPs' last-layer init relative to ``nn.Linear``'s. Correctives
    start at exactly 0 anyway because every basis ``ΔΛ`` is zero-initialised; a zero or
    tiny last layer as well would stall learning (the gradient of each factor of
    ``<w, ΔΛ>`` is proportional to the other)."""

    input_norm: bool = False
    """Standardise the anchor MLPs' pose and face inputs with the training frames' per-parameter mean and
    std (after the PCA; std floored at ``INPUT_STD_FLOOR``), before the localization mask. Raw radians
    vary by a few hundredths over a capture, so the MLP outputs barely change from frame to frame at
    init and the correctives learn a static offset. CPU presets: on; ``paper``: off (docs/train.md)."""
    center_correctives: bool = False
    """Coefficients ``w = MLP(x) - MLP(x_ref)``, ``x_ref`` the standardised mean input (zeros): the
    correctives vanish at the mean pose and appearance, so the biases hold the mean avatar and the bases
    only the frame-dependent part (without it they first learn a static offset, redundant with the
    biases). Needs ``input_norm`` (and ``latent_norm`` for the latent block) to mean "the mean frame"."""
    anchor_sh0: bool = False
    """Also a colour (SH band 0) basis per anchor, ``[A, n_basis, 3]``, whose delta ``<w_a, ΔΛ^a>`` is
    interpolated to the Gaussians like the coefficients: a region-wide colour change (a garment's dye) is then
    learnt once per anchor instead of once per Gaussian. Off by default (docs/train.md: it raises the
    frame dependence from 0.23 to 0.63 on ``small`` but lowers the latent gain)."""
    latent_sh0: bool = False
    """Also a linear map per anchor from its (standardised) appearance latent to a colour delta,
    ``[A, latent_dim, 3]``, interpolated to the Gaussians like the coefficients: the colour change then
    follows the latent directly instead of through the pose-and-latent MLP, so it cannot answer a pose it
    saw with a colour it saw (docs/train.md). Needs ``use_latent`` (ignored without a latent). CPU presets:
    on (on ``small`` it raised the frame dependence from 0.23 to 0.89 at the same latent gain); ``paper``: off."""
    mlp_init: Literal["linear", "he"] = "linear"
    """Anchor-MLP init (:class:`~gsavatar.models.mlp.AnchorMLPs`): ``linear`` (``nn.Linear``'s, the
    paper's framework default) or ``he`` (variance-preserving). With ``linear`` the coefficients ``w``
    of unit-variance inputs have std ~0.01 through four layers, so the product ``<w, ΔΛ>`` with
    zero-initialised bases learns ~100x slower than with ``he`` (docs/train.md)."""
    latent_norm: bool = False
    """Standardise each anchor's latent channel over frames with running statistics
    (:class:`~gsavatar.models.encoder.LatentNorm`), so the frame-to-frame change the encoder sees
    reaches the MLPs at unit scale whatever the encoder's output scale."""

    uv_decoder_size: int = 128
    """``conv_uv`` only: side of the decoded UV property map (8 x a power of two)."""
    uv_decoder_channels: int = 128
    """``conv_uv`` only: channels of the decoder's first 8x8 grid, halved per x2 upsampling down to 32."""

    def __post_init__(self) -> None:
        if not self.hidden or any(int(h) <= 0 for h in self.hidden):
            raise ValueError(f"hidden must be a non-empty tuple of positive ints, got {self.hidden!r}")
        for name in ("n_basis", "n_ctrl_basis", "latent_dim"):
            if int(getattr(self, name)) <= 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"sh_degree must be in [0, 3], got {self.sh_degree}")
        if not self.scale_max > 0:
            raise ValueError(f"scale_max must be > 0 (metres), got {self.scale_max}")
        if self.variant not in pose_head_names():
            raise ValueError(f"variant must be one of {list(pose_head_names())}, got {self.variant!r}")
        if self.pca not in ("local", "global", "global_test_only", "none"):
            raise ValueError(f"pca must be local/global/global_test_only/none, got {self.pca!r}")
        if self.face_dim < 0:
            raise ValueError(f"face_dim must be >= 0, got {self.face_dim}")
        if self.mlp_init not in ("linear", "he"):
            raise ValueError(f"mlp_init must be 'linear' or 'he', got {self.mlp_init!r}")
        if not 0 < self.init_opacity < 1:
            raise ValueError(f"init_opacity must be in (0, 1), got {self.init_opacity}")
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))

    @property
    def num_sh(self) -> int:
        """SH coefficients per channel at ``sh_degree``: ``(sh_degree + 1)^2``."""
        return (self.sh_degree + 1) ** 2

    def replace(self, **changes) -> ModelConfig:
        """Copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        """Plain-JSON form (``config.json`` of a run, checked against a checkpoint's on resume)."""
        return config_to_json(self)


@dataclass(frozen=True)
class LearningRates:
    """Per-property learning rates, (bias / corrective basis), paper supp. D.1."""

    scale_bias: float = 5e-4
    """Log-scale bias ``λ_s``."""
    scale_basis: float = 1e-4
    """Scale basis ``ΔΛ_s``."""
    rotation_bias: float = 5e-4
    """Quaternion bias ``λ_r``."""
    rotation_basis: float = 1e-4
    """Quaternion basis ``ΔΛ_r``."""
    opacity_bias: float = 5e-4
    """Opacity logit (bias only; no opacity correctives)."""
    sh0_bias: float = 2.5e-3
    """SH band 0 bias (pre-tanh)."""
    sh0_basis: float = 1e-4
    """SH band 0 basis."""
    shn_bias: float = 2.5e-5
    """Higher SH bands bias (pre-tanh)."""
    shn_basis: float = 2.5e-6
    """Higher SH bands basis."""
    ctrl_bias: float = 1.6e-4
    """Control-point displacement bias, metres."""
    ctrl_basis: float = 1.6e-5
    """Control-point displacement basis."""
    gauss_pos_basis: float = 1e-4
    """Per-Gaussian position-offset basis (no bias: "Gaussian position -/1e-4")."""
    mlp: float = 5e-4
    """The pose head's network: anchor MLP weights and biases (or the UV decoder's)."""
    mlp_weight_decay: float = 1e-3
    """AdamW weight decay of the pose head's network (the avatar's other groups: 0)."""
    encoder: float = 5e-4
    """Appearance encoder (supp. D.2; :meth:`AppearanceEncoder.param_groups`)."""
    encoder_weight_decay: float = 1e-3
    """AdamW weight decay of the appearance encoder (supp. D.2)."""


CPU_RECIPE = dict(input_norm=True, center_correctives=True, latent_norm=True, latent_sh0=True)
"""What the CPU presets add to the paper's model so the frame-dependent half learns in ~1-2k steps
(docs/train.md, "A recipe for the CPU budget")."""


def model_preset(name: PresetName, **overrides) -> ModelConfig:
    """Named sizes: ``tiny`` (hidden (64, 64), tests / CPU), ``small`` ((128, 128, 128)), ``paper``.

    ``tiny`` and ``small`` also turn on :data:`CPU_RECIPE`; ``paper`` keeps the paper's model.
    """
    hidden = {"tiny": (64, 64), "small": (128, 128, 128), "paper": (512, 256, 256, 256)}
    if name not in hidden:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(hidden)}")
    recipe = {} if name == "paper" else dict(CPU_RECIPE)
    return ModelConfig(hidden=hidden[name], **{**recipe, **overrides})


def variant_config(base: ModelConfig, name: VariantName) -> ModelConfig:
    """``base`` with the fields of one of the paper's variants (a row of :data:`VARIANTS`)."""
    if name not in VARIANTS:
        raise ValueError(f"unknown variant {name!r}; expected one of {sorted(VARIANTS)}")
    return base.replace(**VARIANTS[name])
