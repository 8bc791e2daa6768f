"""Autoregressive appearance predictor (paper section 3.4, supp. D.3).

At driving time no UV texture exists, so the per-anchor appearance latents ``l_t``
(``[A, L]``) are predicted from the motion and the previous latents:

    l_t = clampPCA( f(θ_{t-N_b+1..t}, root_{t-N_b+1..t}, l_{t-1}) )

Causality: the window holds the ``N_b`` most recent poses *including the current
frame t* (the paper's "previous N_b body poses" read for driving, where pose t is
known when frame t is rendered), plus the latents of frame ``t-1``. Nothing after
``t`` and nothing older than ``t-N_b+1`` enters. At a sequence start the window is
filled by repeating the first frame (:meth:`AppearancePredictor.init_state`; the
trainer pads the same way at segment starts).

Tokens (one set per frame, attention is across tokens, not across time):

- one **pose token per pose slot** ``j`` of ``pose_slots`` (the "local" slots: by
  default those active for at least one anchor in the localization masks). The slot's
  ``N_b`` values, ``N_b-1`` velocities and ``N_b-2`` accelerations (finite differences
  over the window) -> ``3 N_b - 3`` features -> the slot's own shallow MLP.
- **six root-motion slots**, treated exactly like pose slots: the axis-angle and the
  translation of every window frame's root transform expressed in the *last* frame's
  root frame, ``R_rel,k = R_N^T R_k`` and ``t_rel,k = R_N^T (t_k - t_N)``. This is the
  paper's normalisation ("remove the last frame's global translation and rotation from
  all poses"): the joint-local pose parameters are invariant to root motion anyway, and
  the relative root motion is invariant to any constant rigid transform of the whole
  window (so heading and position in the room cannot become appearance cues). The
  last frame's own root values are then identically zero (constant features are
  dropped by the input normalisation).
- one **latent token per anchor** from its previous latent (own shallow MLP per anchor).

Pose values are optionally passed through the avatar's localized pose PCA with
±2σ clamping first (same transform as the avatar's conditioning, train and test).
Features are standardised per (slot, feature) with statistics fit on the training
windows (:meth:`fit_input_normalization`). Tokens get a sinusoidal absolute
positional encoding over the token index plus a learnable type embedding (pose /
latent), go through ``blocks`` pre-norm transformer blocks and a final LayerNorm; a
linear head maps every *anchor* token to its ``L``-d latent. Latents are standardised
with per-(anchor, dim) training mean/std on the way in and de-standardised on the
way out (the encoder's latents can be far from unit scale; without this, the clamp
below zeroes the gradients of an untrained head). Outputs are clamped by a
per-anchor latent PCA (``K`` components, coefficients clamped to ±clamp_sigma·σ,
fit on the training targets; a low-rank projection like the pose PCA) in training
and driving alike.

Optional (beyond the paper): :class:`InitialLatentNet` regresses a frame's latents
from its (PCA'd) pose alone; ``init_state(..., init_latents=None)`` starts from it
when it has been trained, otherwise from zeros.

The *signal readout* (``PredictorConfig.readout = "signals"``, beyond the paper, the CPU
recipe since 2026-12-06) replaces tokens and transformer by a small state-space model:
every rig joint's speed, height, vertical velocity and vertical acceleration over the
window (:func:`signal_features`) are tokens of one shared MLP, learnt softmax
selections pool them, and a gated update ``z_t = z_{t-1} + g (c - z_{t-1})`` moves the
coefficients of the global latent PCA. Same interface, streaming and clamp; measured
against the transformer in docs/train.md ("Kinematic signal tokens").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from gsavatar.data_schema.pose_pca import clamp_coefficients, pca_project
from gsavatar.geometry.lbs import KinematicChain, RigTensors, skinning_transforms
from gsavatar.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from gsavatar.models.mlp import AnchorMLPs
from gsavatar.utils.jsonio import config_to_json

ORIENTATION_FEATURES = 6
"""Inputs of :func:`orientation_features`."""


def orientation_features(root_rotation: Tensor) -> Tensor:
    """The root's world orientation as the first two columns of its rotation matrix (continuous, unlike the
    axis-angle; with the third column implied).  [B, 3] axis-angle -> [B, 6]"""
    return axis_angle_to_matrix(root_rotation)[..., :2].transpose(-1, -2).reshape(*root_rotation.shape[:-1], 6)


SIGNAL_KINDS = ("speed", "height", "vertical_velocity", "vertical_acceleration")
"""The kinematic signal tokens of every joint (``PredictorConfig.readout = "signals"``), :func:`signal_features`."""

SELECTION_LR_SCALE = 50.0
"""The trainer's learning-rate multiplier for the signal readout's selection logits (no weight decay): softmax
logits that start uniform over ~120 tokens must move by several units to select a few of them within a few
hundred steps, far more than the MLP weights' steps of ~lr each."""

GATE_BIAS_INIT = -4.0
"""Initial bias of the gate's logits (``config.gate``): sigmoid(-4) ~ 0.018, a predictor that starts as near
persistence."""

ROOT_SLOTS = 6
"""Extra pose slots carrying the relative root motion: axis-angle (3), translation (3)."""


@dataclass(frozen=True)
class PredictorConfig:
    """Hyper-parameters of the appearance predictor (defaults: the paper's, supp. D.3)."""

    history: int = 10
    """N_b: poses in the window, the current frame included (paper: 10). >= 3 with ``velocities``, else >= 1."""
    velocities: bool = True
    """Token features are the window's values, velocities and accelerations (the paper's); False: values only
    (with ``history=1`` the no-history ablation: the current pose alone)."""
    memory_timescales: tuple[float, ...] = ()
    """Beyond the paper (empty = the paper's tokens): time constants tau, in frames, of causal exponential
    averages over a longer pose history that every pose token also gets, three per tau: the averaged value,
    |velocity| and velocity, ``sum_k w_k x_{t-k} / sum_k w_k`` with ``w_k = exp(-k / tau)`` over the last
    ``ceil(3 max tau)`` frames (:func:`memory_features`). Appearance that motion history causes (sweat after
    sustained effort, cloth settling) depends on seconds of motion, the paper's window on N_b = 10 frames; a
    fixed filter bank gives that memory without more parameters per frame. Measured in docs/train.md."""
    width: int = 128
    """Token (embedding) dimension (paper: 128)."""
    heads: int = 4
    """Attention heads (paper: 4)."""
    ff: int = 256
    """Feed-forward hidden dimension of a transformer block (paper: 256)."""
    blocks: int = 1
    """Transformer blocks (paper: 1)."""
    latent_dim: int = 16
    """L: per-anchor latent size (paper: 16); the trainer sets it from the avatar run."""
    token_hidden: int = 64
    """Hidden width of every per-slot / per-anchor token MLP (one hidden layer, ReLU)."""
    latent_pca_components: int = 8
    """K: components of the per-anchor latent PCA that clamps the outputs (<= latent_dim)."""
    clamp_sigma: float = 2.0
    """Latent PCA coefficients are clamped to ±clamp_sigma·σ."""
    latent_pca: Literal["anchor", "global"] = "anchor"
    """Output clamp: ``anchor`` = one PCA per anchor with ``latent_pca_components`` components (the paper's
    clamp); ``global`` = one PCA of all anchors' standardised latents together, ``latent_pca_components``
    components for the whole avatar (beyond the paper: appearance that a few causes drive is low-rank across
    anchors, and predictions outside that subspace are noise). Measured in docs/train.md."""
    dropout: float = 0.0
    """Dropout inside the transformer block (0: training and streaming are deterministic)."""
    residual: bool = True
    """Predict the change from the previous latents, ``l_t = l_{t-1} + scale * head(h)`` (beyond the paper,
    which leaves the output form open): the untrained predictor is persistence, a strong answer for
    appearance that dwells, and training moves away from it only where the data supports it. False:
    ``l_t = mean + scale * head(h)``. Measured in docs/train.md."""
    gate: bool = False
    """Gated update (beyond the paper; needs ``residual``): ``l_t = l_{t-1} + g * (c - l_{t-1})`` per (anchor, dim),
    the candidate ``c = mean + scale * head(h)`` and the gate ``g = sigmoid(gate_head(h))`` both from the anchor's
    token. Appearance that motion history causes is held, decays or is reset by a motion event (a sleeve stays
    up until it is pushed down, sweat fades, cloth settles): a first-order recurrence whose rate and target the
    motion sets. The gate starts nearly shut (``g ~ 0.02``: persistence, like the residual head's start).
    Measured in docs/train.md."""
    latent_tokens: bool = True
    """The previous latents are tokens of the transformer (the paper's). False (needs ``gate``): the anchor tokens
    are learnt per-anchor queries and the previous latents enter only through the gated update, so gate and
    candidate are functions of the motion alone and the recurrence is linear in the latents: the predictor cannot
    key its answer on the exact latents of its training sequence, and its rollout cannot compound a nonlinear
    drift. Measured in docs/train.md."""
    zero_context: Literal["mean", "raw"] = "mean"
    """What "zero" previous latents are (the zero-context training pass and zero-init driving): ``mean`` = zero in
    the predictor's standardised latent space, i.e. the training-mean latent (our encoder's latents are not
    zero-mean: raw zeros lie ~2x farther from every frame's latents than the mean does); ``raw`` = the zero
    vector (checkpoints written before this field). Measured in docs/train.md."""
    joint_tokens: bool = False
    """Also one token per rig joint from its posed position over the window (forward kinematics of the pose and
    root inside the predictor) in the last frame's *heading frame*: +Y (gravity) kept, origin under the root,
    turned about +Y so the root faces +Z; values, velocities and accelerations of the three coordinates (beyond
    the paper, whose tokens are joint angles: cloth and hair respond to where limbs are and how fast they move
    relative to gravity, which joint angles encode only through the nonlinear kinematic chain, and the paper's
    root-frame normalisation tilts with the pelvis). Needs the rig (``kinematics``). Measured in docs/train.md."""
    joint_speeds: bool = False
    """With ``joint_tokens``: every joint token also gets the joint's speed relative to the root over the window,
    ``|r_k - r_{k-1}|`` for the N_b - 1 frame pairs (``r`` = joint minus root position, per frame; the heading frame
    is one rotation for the whole window, so these are world speeds). Beyond the paper: appearance that limb
    *speed* drives (a cuff that rides up on a fast knee, sweat after effort) is a norm of a velocity, which a token
    MLP must otherwise learn from few examples; the capture's fairness regressor with these speeds predicts
    ``second``'s knee-speed hysteresis with R^2 0.52 instead of 0.08. Measured in docs/train.md."""
    readout: Literal["transformer", "signals", "both"] = "transformer"
    """``transformer``: the paper's tokens and transformer. ``signals`` (beyond the paper; needs ``latent_pca =
    "global"``): a small state-space predictor over *kinematic signal tokens*. Every rig joint gives four tokens
    over the window, its speed relative to the root, its height above the root, its vertical velocity and its
    vertical acceleration (forward kinematics of the raw pose, per frame; without ``velocities`` the heights alone),
    standardised per joint and kind; one
    MLP shared by all tokens (plus the kind) embeds them; ``signal_heads`` learnt softmax selections over the
    tokens pool the embeddings; a linear map of the pooled vector gives a gate ``g`` and a candidate ``c`` for each
    coefficient of the global latent PCA, and the coefficients follow ``z_t = z_{t-1} + g (c - z_{t-1})``.
    Appearance that motion causes is driven by a few body parts' kinematics through a memory (a hem swings after
    the pelvis drops, a cuff rides up on a fast knee and stays): a shared embedding learns what a fast or high
    limb looks like once for all joints, the selection learns which joints drive which appearance, and the gated
    linear recurrence holds, fades or resets the state. ``both``: the transformer predicts as usual and the signal
    readout then gates the global PCA coefficients of that prediction toward its own candidate,
    ``y = y_T + g (c - y_T)`` (where no selected signal fires, the gate stays shut and the transformer's answer
    stands). Measured in docs/train.md."""
    signal_pose_path: bool = False
    """With ``readout="signals"``: the latent PCA's coefficients are ``y_t = z_t + p_t``, the gated state ``z_t``
    plus an instantaneous part ``p_t`` = MLP of frame t's clamped pose-PCA coefficients (the InitialLatentNet's
    input; one hidden layer of ``signal_hidden``, zero at the start). Appearance that the current pose decides
    (shading baked into the projected textures, cloth that follows a joint) needs no memory; the state then holds
    only what the motion's history adds. The state fed back is ``z_{t-1} = y_{t-1} - p_{t-1}`` with frame t-1's
    pose from the window (with N_b = 1, frame t's). Measured in docs/train.md."""
    world_orientation: bool = False
    """The predictor also reads the root's *world* orientation (the first two columns of its rotation matrix;
    beyond the paper, whose root enters relative to the window's last frame). A capture lit by lights fixed in the
    room bakes shading into its textures that follows which way the body faces and leans: a function of the root's
    world orientation that a pose-conditioned avatar in canonical space cannot model and the latents take, and that
    every other input (heading-frame joints, root motion relative to the last frame) is blind to. The transformer
    gets six more pose slots (the orientation over the window, values, velocities and accelerations like every
    slot); ``readout="signals"`` reads it in its pose path (needs ``signal_pose_path``). Measured in
    docs/train.md."""
    signal_heads: int = 8
    """Softmax selections over the signal tokens (``readout="signals"``)."""
    signal_hidden: int = 32
    """Width of the shared signal-token MLP (two layers; ``readout="signals"``)."""
    initial_net: bool = True
    """Build the pose-conditioned :class:`InitialLatentNet` (beyond the paper)."""
    initial_hidden: int = 128
    """Hidden width of the InitialLatentNet (two hidden layers)."""

    @property
    def window_frames(self) -> int:
        """Pose frames a prediction reads, the current one included: ``max(N_b, ceil(3 max tau))``."""
        longest = max(self.memory_timescales, default=0.0)
        return max(self.history, math.ceil(3.0 * longest))

    @property
    def signal_readout(self) -> bool:
        """Whether the kinematic signal readout is built (``readout`` ``signals`` or ``both``)."""
        return self.readout in ("signals", "both")

    @property
    def needs_kinematics(self) -> bool:
        """Whether the predictor runs the rig's forward kinematics (joint tokens or the signal readout)."""
        return self.joint_tokens or self.signal_readout

    def to_json(self) -> dict:
        """Plain-JSON form (the predictor checkpoint's config, checked on resume)."""
        return config_to_json(self)


LEGACY_CONFIG = {"residual": False, "zero_context": "raw"}
"""What a saved predictor config that lacks these fields was trained with: absolute outputs (before
``residual``), raw-zero context (before ``zero_context``). Checkpoint readers fill missing fields from it."""


class RolloutState(NamedTuple):
    """Streaming state: the last N_b driving frames (oldest first) and the previous latents."""

    pose: Tensor
    """Pose history.  # [N_b, P]"""
    root_rotation: Tensor
    """Root rotation history, axis-angle.  # [N_b, 3]"""
    root_translation: Tensor
    """Root translation history, metres.  # [N_b, 3]"""
    latents: Tensor
    """Latents of the previous frame.  # [A, L]"""


KINEMATICS_KEYS = ("kin_heads", "kin_parents", "kin_param_joint", "kin_param_axis", "kin_param_size")
"""State-dict buffers of a predictor with ``joint_tokens``: the :class:`KinematicChain` arrays, in its argument
order."""


class LatentPCA(NamedTuple):
    mean: Tensor
    """Per-anchor mean latent.  # [A, L]"""
    basis: Tensor
    """Unit principal directions as columns; zero columns for missing components.  # [A, L, K]"""
    sigma: Tensor
    """Coefficient standard deviation (0 for missing components).  # [A, K]"""


# ----------------------------------------------------------------------------- math
def relative_root_motion(root_rotation: Tensor, root_translation: Tensor) -> Tensor:
    """Each frame's root transform in the last frame's root frame (float64 inside).

    ``R_rel,k = R_N^T R_k`` (as axis-angle), ``t_rel,k = R_N^T (t_k - t_N)``.
    root_rotation [B, N, 3] axis-angle, root_translation [B, N, 3] -> [B, N, 6]
    """
    dt = root_rotation.dtype
    R = axis_angle_to_matrix(root_rotation.double())  # [B, N, 3, 3]
    RlT = R[:, -1:].transpose(-1, -2)  # [B, 1, 3, 3]
    rot = matrix_to_axis_angle(RlT @ R)  # [B, N, 3]
    t = root_translation.double()
    trans = (RlT @ (t - t[:, -1:])[..., None])[..., 0]  # [B, N, 3]
    return torch.cat([rot, trans], -1).to(dt)


def heading_frame(joints: Tensor, root_world_rotation: Tensor) -> Tensor:
    """Window joint positions in the last frame's heading frame (+Y up kept, float64 inside).

    Origin: the last frame's root joint projected on the ``y = 0`` plane (heights stay heights); axes: turned
    about +Y by the root's heading, the horizontal direction of its forward (+Z) axis plus its left (+X) axis
    crossed with up (the two agree for an upright body; their sum stays defined lying down).
    joints [B, N, J, 3] world, root_world_rotation [B, 3, 3] (the root joint at the last frame) -> [B, N, J, 3]
    """
    dt = joints.dtype
    R = root_world_rotation.double()
    hx = R[:, 0, 2] - R[:, 2, 0]  # forward.x + (left x up).x = f_x - l_z
    hz = R[:, 2, 2] + R[:, 0, 0]  # forward.z + (left x up).z = f_z + l_x
    n = torch.sqrt(hx * hx + hz * hz).clamp_min(1e-12)
    c, s = (hz / n)[:, None, None], (hx / n)[:, None, None]  # cos, sin of the heading yaw  [B, 1, 1]
    p = joints.double()
    origin = p[:, -1:, :1].clone()  # [B, 1, 1, 3] the root joint, last frame
    origin[..., 1] = 0.0
    q = p - origin
    x, y, z = q.unbind(-1)
    return torch.stack([c * x - s * z, y, s * x + c * z], -1).to(dt)


def joint_speeds(joints: Tensor, root: int) -> Tensor:
    """Every joint's speed relative to joint ``root`` between consecutive window frames (per frame, not per
    second): ``|r_k - r_{k-1}|`` with ``r_k = p_k - p_k[root]``, k = 1..N-1 (the root's own speeds are 0).

    joints [B, N, J, 3] (one rigid frame for the whole window) -> [B, J, N - 1], oldest pair first
    """
    r = joints - joints[:, :, root : root + 1]
    d = (r[:, 1:] - r[:, :-1]).double()
    return torch.sqrt((d * d).sum(-1)).transpose(1, 2).to(joints.dtype)


def signal_features(joints: Tensor, root: int) -> Tensor:
    """Kinematic signals of every joint over the window (:data:`SIGNAL_KINDS`), per frame, zero-padded at the oldest
    end to N values: the speed relative to joint ``root`` (:func:`joint_speeds`), the height above the root, the
    vertical velocity and the vertical acceleration (backward differences of the height in the world, +Y up).

    joints [B, N, J, 3] (heading frame or world: one rigid frame with +Y up for the whole window)
    -> [B, J, 4, N] (oldest first; kinds in :data:`SIGNAL_KINDS` order)
    """
    B, N, J, _ = joints.shape
    y = joints[..., 1].transpose(1, 2)  # [B, J, N]
    vy = y[..., 1:] - y[..., :-1]  # [B, J, N-1]
    ay = vy[..., 1:] - vy[..., :-1]  # [B, J, N-2]
    pad = lambda x: torch.nn.functional.pad(x, (N - x.shape[-1], 0))  # noqa: E731
    return torch.stack([pad(joint_speeds(joints, root)), y - y[:, root : root + 1], pad(vy), pad(ay)], 2)


def window_features(x: Tensor) -> Tensor:
    """Value, velocity and acceleration (finite differences) of every slot over the window.

    x [B, N, S] -> [B, S, 3N-3]: N values, N-1 velocities, N-2 accelerations (oldest first).
    """
    v = x[:, 1:] - x[:, :-1]  # [B, N-1, S]
    a = v[:, 1:] - v[:, :-1]  # [B, N-2, S]
    return torch.cat([x, v, a], 1).transpose(1, 2)


def memory_features(x: Tensor, timescales: Sequence[float]) -> Tensor:
    """Causal exponential averages of every slot's value, |velocity| and velocity over the window.

    Frame ``t`` is the window's last; weights ``w_k = exp(-k / tau)`` for the frame ``k`` frames back, normalised
    over the frames present (velocities: the ``W - 1`` backward differences). A window that repeats its first
    frame (a sequence start) gives that frame's value and zero velocity, like a stationary past.
    x [B, W, S] -> [B, S, 3 M] (per tau: value, |velocity|, velocity; taus in the given order)
    """
    W = x.shape[1]
    v = x[:, 1:] - x[:, :-1]  # [B, W-1, S]
    out = []
    for tau in timescales:
        k = torch.arange(W - 1, -1, -1, dtype=torch.float64, device=x.device)  # frames back, oldest first
        w = torch.exp(-k / float(tau))
        wx = (w / w.sum()).to(x)  # [W]
        if W > 1:
            wv = (w[1:] / w[1:].sum()).to(x)  # [W-1]
            speed, vel = torch.einsum("bws,w->bs", v.abs(), wv), torch.einsum("bws,w->bs", v, wv)
        else:
            speed = vel = torch.zeros_like(x[:, 0])
        out += [torch.einsum("bws,w->bs", x, wx), speed, vel]
    return torch.stack(out, -1)  # [B, S, 3M]


def sinusoidal_encoding(n: int, dim: int) -> Tensor:
    """Transformer sinusoidal absolute positional encoding. -> [n, dim]"""
    pos = torch.arange(n, dtype=torch.float64)[:, None]
    freq = torch.exp(-math.log(10000.0) * torch.arange(0, dim, 2, dtype=torch.float64) / dim)  # [ceil(dim/2)]
    pe = torch.zeros(n, dim, dtype=torch.float64)
    pe[:, 0::2] = torch.sin(pos * freq)
    pe[:, 1::2] = torch.cos(pos * freq)[:, : dim // 2]
    return pe.float()


def fit_latent_pca(latents: Tensor, components: int) -> LatentPCA:
    """Per-anchor PCA of training latents (float64 SVD).

    Keeps ``min(components, L)`` columns; components beyond the numerical rank (or
    ``F-1``) get a zero column and σ = 0, so they project to the mean. Signs: largest
    absolute entry of each direction positive. latents [F, A, L] -> LatentPCA
    """
    if latents.ndim != 3 or latents.shape[0] < 1:
        raise ValueError(f"latents must be [F, A, L] with F >= 1, got {tuple(latents.shape)}")
    F, A, L = latents.shape
    K = min(int(components), L)
    x = latents.detach().double().transpose(0, 1)  # [A, F, L]
    mean = x.mean(1)  # [A, L]
    basis = torch.zeros(A, L, K, dtype=torch.float64)
    sigma = torch.zeros(A, K, dtype=torch.float64)
    if F >= 2 and K > 0:
        _, s, vh = torch.linalg.svd(x - mean[:, None], full_matrices=False)  # s [A, r], vh [A, r, L]
        r = min(K, s.shape[1])
        tol = torch.clamp(s[:, :1] * max(F, L) * torch.finfo(torch.float64).eps, min=1e-12)  # [A, 1]
        keep = (s[:, :r] > tol).double()  # [A, r]
        V = vh[:, :r].transpose(1, 2)  # [A, L, r]
        idx = V.abs().argmax(1, keepdim=True)  # [A, 1, r]
        V = V * torch.where(torch.gather(V, 1, idx) < 0, -1.0, 1.0)
        basis[:, :, :r] = V * keep[:, None]
        sigma[:, :r] = s[:, :r] / math.sqrt(F - 1) * keep
    f = latents.dtype
    return LatentPCA(mean.to(f), basis.to(f), sigma.to(f))


def latent_pca_project(x: Tensor, mean: Tensor, basis: Tensor, limit: Tensor) -> Tensor:
    """Project per-anchor latents onto their PCA box: coefficients clamped to ±limit.

    x [..., A, L], mean [A, L], basis [A, L, K], limit [A, K] -> [..., A, L].
    Differentiable (zero gradient through clamped coefficients).
    """
    c = clamp_coefficients(torch.einsum("...al,alk->...ak", x - mean, basis), limit)
    return mean + torch.einsum("...ak,alk->...al", c, basis)


def _check(name: str, t: Tensor, shape: tuple) -> None:
    if t.ndim != len(shape) or any(e is not None and e != a for e, a in zip(shape, t.shape)):
        pretty = "[" + ", ".join("*" if e is None else str(e) for e in shape) + "]"
        raise ValueError(f"{name} must be {pretty}, got {list(t.shape)}")


# ----------------------------------------------------------------------------- modules
class InitialLatentNet(nn.Module):
    """Pose -> standardised latents regressor, to start a rollout instead of zeros (beyond the paper).

    MLP ``in_dim -> hidden -> hidden -> A·L`` (ReLU); the last layer starts at zero so an
    untrained net predicts the training mean. x [B, in_dim] -> [B, A, L]
    """

    def __init__(self, in_dim: int, num_anchors: int, latent_dim: int, hidden: int = 128) -> None:
        super().__init__()
        self.num_anchors, self.latent_dim = int(num_anchors), int(latent_dim)
        self.net = nn.Sequential(
            nn.Linear(in_dim, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, num_anchors * latent_dim),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x).reshape(x.shape[0], self.num_anchors, self.latent_dim)


class _Streaming:
    """Streaming and rollout of a one-frame latent predictor: ``self(pose_window, root_rot_window,
    root_trans_window, prev_latents)`` with ``config``, ``pose_dim``, ``num_anchors`` and ``initial_latents``."""

    @torch.no_grad()
    def init_state(
        self, first_pose: Tensor, first_root_rot: Tensor, first_root_trans: Tensor, init_latents: Tensor | None = None
    ) -> RolloutState:
        """History = the first frame repeated N_b times; previous latents = ``init_latents`` [A, L]
        or, when None, :meth:`initial_latents` (the trained InitialLatentNet, else zeros)."""
        N = self.config.window_frames
        _check("first_pose", first_pose, (self.pose_dim,))
        _check("first_root_rot", first_root_rot, (3,))
        _check("first_root_trans", first_root_trans, (3,))
        if init_latents is None:
            init_latents = self.initial_latents(first_pose[None])[0]
        _check("init_latents", init_latents, (self.num_anchors, self.config.latent_dim))
        rep = lambda x: x[None].expand(N, -1).clone()  # noqa: E731
        return RolloutState(rep(first_pose), rep(first_root_rot), rep(first_root_trans), init_latents.clone())

    @torch.no_grad()
    def step(
        self, state: RolloutState, pose: Tensor, root_rot: Tensor, root_trans: Tensor
    ) -> tuple[Tensor, RolloutState]:
        """Push frame t (pose [P], root_rot [3], root_trans [3]) and predict its latents.

        -> (latents [A, L], new state). Uses the module's current mode (call ``.eval()`` with dropout).
        """
        _check("pose", pose, (self.pose_dim,))
        _check("root_rot", root_rot, (3,))
        _check("root_trans", root_trans, (3,))
        push = lambda h, x: torch.cat([h[1:], x[None].to(h)], 0)  # noqa: E731
        p, r, t = push(state.pose, pose), push(state.root_rotation, root_rot), push(state.root_translation, root_trans)
        lat = self(p[None], r[None], t[None], state.latents[None])[0]
        return lat, RolloutState(p, r, t, lat)

    @torch.no_grad()
    def rollout(
        self,
        poses: Tensor,
        root_rot: Tensor,
        root_trans: Tensor,
        init_latents: Tensor | None = None,
        reinit_every: int = 0,
        reinit_latents: Callable[[int], Tensor] | None = None,
        first_is_given: bool = False,
    ) -> Tensor:
        """Free-running prediction over a sequence, one :meth:`step` per frame.

        poses [T, P], root_rot [T, 3], root_trans [T, 3]; ``init_latents`` [A, L]: the
        "previous" latents of frame 0 (None: :meth:`initial_latents` of frame 0). With
        ``first_is_given`` they are frame 0's own latents (teacher-forced first frame):
        output 0 is ``init_latents`` and prediction starts at frame 1. ``reinit_every`` > 0:
        at every frame t > 0 with ``t % reinit_every == 0`` the previous latents are replaced
        by ``reinit_latents(t)`` [A, L] (None: :meth:`initial_latents` of frame t).
        -> [T, A, L]
        """
        T = poses.shape[0] if poses.ndim == 2 else -1
        _check("poses", poses, (None, self.pose_dim))
        _check("root_rot", root_rot, (T, 3))
        _check("root_trans", root_trans, (T, 3))
        if T < 1:
            raise ValueError("poses must hold at least one frame, got 0")
        if first_is_given and init_latents is None:
            raise ValueError("first_is_given=True needs init_latents (frame 0's latents), got None")
        state = self.init_state(poses[0], root_rot[0], root_trans[0], init_latents)
        out = [state.latents] if first_is_given else []
        for t in range(1 if first_is_given else 0, T):
            if reinit_every > 0 and t > 0 and t % reinit_every == 0:
                new = reinit_latents(t) if reinit_latents is not None else self.initial_latents(poses[t : t + 1])[0]
                _check("reinit_latents(t)", new, (self.num_anchors, self.config.latent_dim))
                state = state._replace(latents=new.to(state.latents))
            lat, state = self.step(state, poses[t], root_rot[t], root_trans[t])
            out.append(lat)
        return torch.stack(out)


class AppearancePredictor(_Streaming, nn.Module):
    """Transformer over pose-slot and anchor tokens -> per-anchor latents (module docstring).

    Args:
        config: hyper-parameters.
        num_anchors: A.
        pose_slots: indices into the pose vector of the local slots that get tokens.
        pose_dim: P, length of the driving pose vector.
        pose_pca: optional ``(mean [P], basis [P, C], limit [C])`` of the avatar's pose
            PCA; poses are projected and clamped with it before anything else.
        seed: initialisation seed.
        kinematics: the rig's :class:`KinematicChain` (or its :meth:`~KinematicChain.arrays`); required with
            ``config.joint_tokens`` (joint positions come from its forward kinematics), ignored otherwise.
    """

    def __init__(
        self,
        config: PredictorConfig,
        num_anchors: int,
        pose_slots: Sequence[int] | np.ndarray | Tensor,
        pose_dim: int,
        pose_pca: tuple | None = None,
        seed: int = 0,
        kinematics: KinematicChain | tuple | None = None,
    ) -> None:
        super().__init__()
        c = config
        if c.history < (3 if c.velocities else 1):
            raise ValueError(
                f"config.history must be >= 3 (value, velocity, acceleration) or >= 1 without "
                f"velocities, got {c.history} (velocities={c.velocities})"
            )
        if c.width % c.heads:
            raise ValueError(f"config.width ({c.width}) must be divisible by config.heads ({c.heads})")
        if c.latent_pca not in ("anchor", "global"):
            raise ValueError(f"config.latent_pca must be 'anchor' or 'global', got {c.latent_pca!r}")
        if c.latent_pca == "anchor" and not 0 <= c.latent_pca_components <= c.latent_dim:
            raise ValueError(
                f"config.latent_pca_components must be in [0, {c.latent_dim}], got {c.latent_pca_components}"
            )
        if c.latent_pca == "global" and not 0 < c.latent_pca_components <= num_anchors * c.latent_dim:
            raise ValueError(
                f"config.latent_pca_components must be in [1, {num_anchors * c.latent_dim}] with a global "
                f"latent PCA, got {c.latent_pca_components}"
            )
        slots = torch.as_tensor(np.asarray(pose_slots), dtype=torch.long).reshape(-1)
        if slots.numel() and (slots.min() < 0 or slots.max() >= pose_dim):
            raise ValueError(
                f"pose_slots must index [0, {pose_dim}), got range [{int(slots.min())}, {int(slots.max())}]"
            )
        self.config, self.num_anchors, self.pose_dim = c, int(num_anchors), int(pose_dim)
        A, L, D = self.num_anchors, c.latent_dim, c.width
        K = c.latent_pca_components if c.latent_pca == "anchor" else 0
        self.orientation_slots = c.world_orientation and c.readout != "signals"  # the transformer's input
        S = int(slots.numel()) + ROOT_SLOTS + (ORIENTATION_FEATURES if self.orientation_slots else 0)
        if any(not (math.isfinite(float(t)) and float(t) > 0) for t in c.memory_timescales):
            raise ValueError(f"config.memory_timescales must be positive frame counts, got {c.memory_timescales}")
        if c.memory_timescales and c.joint_tokens:
            raise ValueError("config.memory_timescales and config.joint_tokens cannot be combined (not implemented)")
        if c.gate and not c.residual:
            raise ValueError("config.gate needs config.residual (the gate mixes the previous latents in)")
        if not c.latent_tokens and not c.gate:
            raise ValueError("config.latent_tokens=False needs config.gate (the previous latents enter through it)")
        if c.readout not in ("transformer", "signals", "both"):
            raise ValueError(f"config.readout must be 'transformer', 'signals' or 'both', got {c.readout!r}")
        signals = c.signal_readout
        if signals and c.latent_pca != "global":
            raise ValueError("config.readout='signals' needs config.latent_pca='global' (its state is the PCA's)")
        if signals and (c.joint_tokens or c.memory_timescales):
            raise ValueError(
                "config.readout='signals' reads its own joint signals over the window of N_b frames: "
                "joint_tokens, memory_timescales cannot be combined with it"
            )
        if c.signal_pose_path and c.readout != "signals":
            raise ValueError(
                "config.signal_pose_path is for readout='signals' (with 'both' the transformer has the pose)"
            )
        if c.world_orientation and c.readout == "signals" and not c.signal_pose_path:
            raise ValueError(
                "config.world_orientation with readout='signals' is an input of its pose path: it needs "
                "signal_pose_path"
            )
        if c.readout == "signals" and (c.gate or not c.latent_tokens):
            raise ValueError(
                "config.gate and latent_tokens shape the transformer, which readout='signals' does not build"
            )
        if signals and (c.signal_heads < 1 or c.signal_hidden < 1):
            raise ValueError(
                f"config.signal_heads and signal_hidden must be >= 1, got {c.signal_heads}, {c.signal_hidden}"
            )
        if c.joint_speeds and not c.joint_tokens:
            raise ValueError("config.joint_speeds needs config.joint_tokens (the speeds ride on the joint tokens)")
        Fdim = (3 * c.history - 3 if c.velocities else c.history) + 3 * len(c.memory_timescales)
        self.chain: KinematicChain | None = None
        if c.needs_kinematics:
            if kinematics is None:
                what = "joint_tokens" if c.joint_tokens else "readout='signals'"
                raise ValueError(f"config.{what} needs the rig's kinematics (KinematicChain), got None")
            self.chain = kinematics if isinstance(kinematics, KinematicChain) else KinematicChain(*kinematics)
            if self.chain.pose_dim != pose_dim:
                raise ValueError(f"kinematics drive {self.chain.pose_dim} pose slots, pose_dim is {pose_dim}")
            self._rig = RigTensors(self.chain)
            self.root_joint = int(np.flatnonzero(self.chain.parents() < 0)[0])
        J = self.chain.num_joints if self.chain is not None else 0
        self.num_slots, self.num_joints, self.feature_dim = S, J, Fdim
        Jt = self.num_joint_tokens = J if c.joint_tokens else 0  # the transformer's joint tokens
        self.signals_only = False
        """Training-time switch (``readout="both"``, not saved): the transformer is skipped and the signal readout
        updates the previous latents alone, as ``readout="signals"`` (``PredictorTrainConfig.signal_warmup_steps``)."""
        if signals:
            self.joint_feature_dim = len(SIGNAL_KINDS) * c.history  # [kind, frame] flattened
        else:
            self.joint_feature_dim = 3 * Fdim + (c.history - 1 if c.joint_speeds else 0)  # x, y, z blocks (+ speeds)
        f32 = lambda a: None if a is None else torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        self.register_buffer("pose_slots", slots)  # [S - 6]
        pm, pb, pl = pose_pca if pose_pca is not None else (None, None, None)
        self.register_buffer("pose_pca_mean", f32(pm))  # [P] or None
        self.register_buffer("pose_pca_basis", f32(pb))  # [P, C] or None
        self.register_buffer("pose_pca_limit", f32(pl))  # [C] or None
        self.register_buffer("feature_mean", torch.zeros(S, Fdim))  # [S, 3N-3]
        self.register_buffer("feature_scale", torch.ones(S, Fdim))  # [S, 3N-3] 1/std, 0 for constant features
        if self.chain is not None:  # only then: checkpoints without joint tokens keep their state_dict keys
            for key, arr in zip(KINEMATICS_KEYS, self.chain.arrays()):
                self.register_buffer(key, torch.as_tensor(arr))
            self.register_buffer("joint_feature_mean", torch.zeros(J, self.joint_feature_dim))  # [J, 3 (3N-3) (+ N-1)]
            self.register_buffer("joint_feature_scale", torch.ones(J, self.joint_feature_dim))
        self.register_buffer("latent_mean", torch.zeros(A, L))  # [A, L] train mean (also the PCA centre)
        self.register_buffer("latent_scale", torch.ones(A, L))  # [A, L] train std (floored)
        self.register_buffer("latent_basis", torch.zeros(A, L, K))
        self.register_buffer("latent_limit", torch.zeros(A, K))
        self.register_buffer("latent_pca_ready", torch.tensor(False))
        if c.latent_pca == "global":  # only then: checkpoints of per-anchor predictors keep their state_dict keys
            Kg = c.latent_pca_components
            self.register_buffer("global_basis", torch.zeros(A * L, Kg))  # [A*L, Kg] standardised space
            self.register_buffer("global_limit", torch.zeros(Kg))  # [Kg]
        self.register_buffer("initial_ready", torch.tensor(False))
        self.register_buffer("positional", sinusoidal_encoding(S + Jt + A, D), persistent=False)  # [S + Jt + A, D]

        gen = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng(devices=[]):  # nn.TransformerEncoderLayer / nn.Linear draw from the global RNG
            torch.manual_seed(seed)
            if c.readout != "signals":
                self._build_transformer(S, Jt, Fdim, gen)
            if signals:
                self._build_signal_readout(J, gen)
            init_in = int(pb.shape[1]) if pb is not None else int(slots.numel())
            self.initial = InitialLatentNet(init_in, A, L, c.initial_hidden) if c.initial_net and init_in > 0 else None

    def _build_signal_readout(self, J: int, gen: torch.Generator) -> None:
        c, H, K, n = self.config, self.config.signal_hidden, self.config.latent_pca_components, len(SIGNAL_KINDS)
        self.signal_mlp = nn.Sequential(nn.Linear(c.history + n, H), nn.ReLU(), nn.Linear(H, H))
        self.selection_logits = nn.Parameter(torch.zeros(c.signal_heads, J * n))  # uniform at the start
        self.signal_out = nn.Linear(c.signal_heads * H, 2 * K)  # candidate, gate logits
        with torch.no_grad():
            self.signal_out.weight.mul_(0.1)
            self.signal_out.bias.zero_()
            self.signal_out.bias[K:].fill_(GATE_BIAS_INIT)
        self.register_buffer("signal_kind_code", torch.eye(n).repeat(J, 1), persistent=False)  # [J*4, 4]
        if c.signal_pose_path:
            P_in = (
                int(self.pose_pca_basis.shape[1]) if self.pose_pca_basis is not None else int(self.pose_slots.numel())
            )
            P_in += ORIENTATION_FEATURES if c.world_orientation else 0
            self.signal_pose = nn.Sequential(nn.Linear(P_in, H), nn.ReLU(), nn.Linear(H, K))
            with torch.no_grad():
                self.signal_pose[-1].weight.zero_()
                self.signal_pose[-1].bias.zero_()

    def _build_transformer(self, S: int, J: int, Fdim: int, gen: torch.Generator) -> None:
        c, A, L, D = self.config, self.num_anchors, self.config.latent_dim, self.config.width
        self.pose_tokens = AnchorMLPs(S, Fdim, D, (c.token_hidden,), generator=gen)
        if c.latent_tokens:
            self.latent_tokens = AnchorMLPs(A, L, D, (c.token_hidden,), generator=gen)
        else:  # learnt per-anchor queries: the anchors' tokens do not see the previous latents
            self.anchor_queries = nn.Parameter(torch.randn(A, D, generator=gen) * 0.02)
        self.type_embedding = nn.Parameter(torch.zeros(2, D))  # [pose, latent]
        if J:
            self.joint_tokens = AnchorMLPs(J, self.joint_feature_dim, D, (c.token_hidden,), generator=gen)
            self.joint_type_embedding = nn.Parameter(torch.zeros(D))
        layer = nn.TransformerEncoderLayer(
            D, c.heads, c.ff, c.dropout, activation="gelu", batch_first=True, norm_first=True
        )
        self.transformer = nn.TransformerEncoder(layer, c.blocks, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(D)
        self.head = nn.Linear(D, L)
        if c.gate:
            self.gate_head = nn.Linear(D, L)
        with torch.no_grad():  # start at the previous latents (residual: exact persistence) / near the mean
            self.head.weight.mul_(0.0 if c.residual and not c.gate else 0.1)
            self.head.bias.zero_()
            if c.gate:  # nearly shut: ~2% of the way to the candidate per frame
                self.gate_head.weight.mul_(0.1)
                self.gate_head.bias.fill_(GATE_BIAS_INIT)

    # ------------------------------------------------------------------ inputs
    def conditioning_pose(self, pose: Tensor) -> Tensor:
        """Pose PCA projection with clamping (identity without a PCA). [..., P] -> [..., P]"""
        if self.pose_pca_basis is None:
            return pose
        m, b, lim = self.pose_pca_mean.to(pose), self.pose_pca_basis.to(pose), self.pose_pca_limit.to(pose)
        return pca_project(pose, m, b, lim)

    def slot_values(self, pose_window: Tensor, root_rot_window: Tensor, root_trans_window: Tensor) -> Tensor:
        """Per-slot values over the window: local pose slots, the relative root motion, then (``world_orientation``
        with a transformer) the root's world orientation.

        [B, N, P], [B, N, 3], [B, N, 3] -> [B, N, S]
        """
        pose = self.conditioning_pose(pose_window)[..., self.pose_slots]  # [B, N, S-6(-6)]
        parts = [pose, relative_root_motion(root_rot_window, root_trans_window)]
        if self.orientation_slots:
            parts.append(orientation_features(root_rot_window))
        return torch.cat(parts, -1)

    def features(self, pose_window: Tensor, root_rot_window: Tensor, root_trans_window: Tensor) -> Tensor:
        """Raw (unnormalised) token features. -> [B, S, 3N-3] (values only: [B, S, N])"""
        c = self.config
        x = self.slot_values(pose_window, root_rot_window, root_trans_window)  # [B, W, S]
        recent = x[:, -c.history :]
        f = window_features(recent) if c.velocities else recent.transpose(1, 2)
        if c.memory_timescales:
            f = torch.cat([f, memory_features(x, c.memory_timescales)], -1)
        return f

    def joint_features(self, pose_window: Tensor, root_rot_window: Tensor, root_trans_window: Tensor) -> Tensor:
        """Raw joint-token features (``config.joint_tokens``): every joint's heading-frame position over the
        window (:func:`heading_frame`; forward kinematics of the raw pose), then the values, velocities and
        accelerations of x, y, z (and with ``config.joint_speeds`` the :func:`joint_speeds`).
        [B, N, P], [B, N, 3], [B, N, 3] -> [B, J, 3 (3N-3) (+ N-1)] (values only: [B, J, 3N (+ N-1)])"""
        if self.chain is None:
            raise ValueError("joint_features needs config.joint_tokens")
        q = self.heading_joints(pose_window, root_rot_window, root_trans_window)  # [B, N, J, 3]
        B, N, J, _ = q.shape
        if self.config.signal_readout:
            sig = signal_features(q, self.root_joint)  # [B, J, 4, N]
            if not self.config.velocities:  # values only: the heights (the no-history ablation with N_b = 1)
                sig = sig * torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=sig.dtype, device=sig.device)[:, None]
            return sig.reshape(B, J, -1)  # [B, J, 4 N]
        x = q.permute(0, 1, 3, 2).reshape(B, N, 3 * J)  # slot = coordinate * J + joint
        f = window_features(x) if self.config.velocities else x.transpose(1, 2)  # [B, 3J, F]
        f = f.reshape(B, 3, J, -1).permute(0, 2, 1, 3).reshape(B, J, -1)  # [B, J, 3F]: x block, y, z
        if self.config.joint_speeds:
            f = torch.cat([f, joint_speeds(q, self.root_joint)], -1)  # [B, J, 3F + N - 1]
        return f

    def heading_joints(self, pose_window: Tensor, root_rot_window: Tensor, root_trans_window: Tensor) -> Tensor:
        """The rig's joints over the last N_b window frames in the last frame's heading frame (forward kinematics
        of the raw pose, :func:`heading_frame`). [B, N, P], [B, N, 3], [B, N, 3] -> [B, N_b, J, 3]"""
        N = self.config.history  # the paper's window (memory features are pose-slot only)
        pose_window, root_rot_window = pose_window[:, -N:], root_rot_window[:, -N:]
        root_trans_window = root_trans_window[:, -N:]
        B, N, P = pose_window.shape
        if self._rig.heads.device != pose_window.device:  # built on the CPU; follow the inputs
            self._rig = RigTensors(self.chain, pose_window.device)
        T = skinning_transforms(
            self._rig,
            pose_window.reshape(B * N, P),
            root_rot_window.reshape(B * N, 3),
            root_trans_window.reshape(B * N, 3),
        )  # [B*N, J, 4, 4]
        heads = self._rig.heads.to(T)
        joints = ((T[..., :3, :3] @ heads[None, :, :, None])[..., 0] + T[..., :3, 3]).reshape(B, N, -1, 3)
        return heading_frame(joints, T.reshape(B, N, -1, 4, 4)[:, -1, self.root_joint, :3, :3])  # [B, N, J, 3]

    def input_features(
        self, pose_window: Tensor, root_rot_window: Tensor, root_trans_window: Tensor
    ) -> tuple[Tensor, Tensor | None]:
        """Raw features of every token kind: (pose slots [B, S, F], joints [B, J, 3F] or None)."""
        x = self.features(pose_window, root_rot_window, root_trans_window)
        xj = self.joint_features(pose_window, root_rot_window, root_trans_window) if self.chain is not None else None
        return x, xj

    @torch.no_grad()
    def fit_input_normalization(
        self, features: Tensor, joint_features: Tensor | None = None, min_std: float = 1e-6
    ) -> None:
        """Standardise each (slot, feature) with training statistics; constant ones are dropped.

        features [n, S, 3N-3] as returned by :meth:`features`; ``joint_features`` [n, J, joint_feature_dim] from
        :meth:`joint_features` (required with ``config.joint_tokens``).
        """
        _check("features", features, (None, self.num_slots, self.feature_dim))
        pairs = [(features, self.feature_mean, self.feature_scale)]
        if self.chain is not None:
            if joint_features is None:
                raise ValueError("fit_input_normalization: config.joint_tokens needs joint_features")
            _check("joint_features", joint_features, (features.shape[0], self.num_joints, self.joint_feature_dim))
            pairs.append((joint_features, self.joint_feature_mean, self.joint_feature_scale))
        for f, mean_buf, scale_buf in pairs:
            f = f.double()
            mean, std = f.mean(0), f.std(0, unbiased=False)
            mean_buf.copy_(mean)
            scale_buf.copy_(torch.where(std > min_std, 1.0 / std.clamp_min(min_std), torch.zeros_like(std)))

    @torch.no_grad()
    def fit_latent_statistics(self, latents: Tensor, rel_floor: float = 0.1) -> LatentPCA:
        """Fit the latent normalisation and the output clamp on training targets [F, A, L].

        Latent tokens see ``(l - mean) / scale`` and the head predicts ``(l - mean) / scale``,
        with ``scale`` the per-(anchor, dim) std floored at ``rel_floor`` x its RMS over all
        anchors and dims (so near-constant dims are not blown up). Returns the PCA fit.
        """
        _check("latents", latents, (None, self.num_anchors, self.config.latent_dim))
        pca = fit_latent_pca(latents, self.config.latent_pca_components if self.config.latent_pca == "anchor" else 0)
        std = latents.double().std(0, unbiased=False) if latents.shape[0] > 1 else torch.zeros_like(pca.mean).double()
        floor = max(rel_floor * float(std.pow(2).mean().sqrt()), 1e-8)
        self.latent_scale.copy_(std.clamp_min(floor))
        self.latent_mean.copy_(pca.mean)
        self.latent_basis.copy_(pca.basis)
        self.latent_limit.copy_(self.config.clamp_sigma * pca.sigma)
        if self.config.latent_pca == "global":
            z = ((latents.double() - pca.mean.double()) / self.latent_scale.double()).reshape(latents.shape[0], -1)
            g = fit_latent_pca(z[:, None], self.config.latent_pca_components)  # one "anchor" holding everything
            self.global_basis.copy_(g.basis[0])
            self.global_limit.copy_(self.config.clamp_sigma * g.sigma[0])
        self.latent_pca_ready.fill_(True)
        return pca

    def zero_latents(self) -> Tensor:
        """The "zero" previous latents of a rollout without a texture (``config.zero_context``).  # [A, L]"""
        if self.config.zero_context == "mean" and bool(self.latent_pca_ready):
            return self.latent_mean.clone()
        return torch.zeros_like(self.latent_mean)

    def clamp_latents(self, latents: Tensor) -> Tensor:
        """Latent PCA projection with ±clamp_sigma·σ clamping (identity before it is fit). [..., A, L]"""
        if not bool(self.latent_pca_ready):
            return latents
        if self.config.latent_pca == "global":
            z = ((latents - self.latent_mean) / self.latent_scale).flatten(-2)[..., None, :]  # [..., 1, A*L]
            zero = torch.zeros_like(self.global_basis[None, :, 0])
            z = latent_pca_project(z, zero, self.global_basis[None], self.global_limit[None])[..., 0, :]
            return self.latent_mean + self.latent_scale * z.unflatten(-1, latents.shape[-2:])
        return latent_pca_project(latents, self.latent_mean, self.latent_basis, self.latent_limit)

    # ------------------------------------------------------------------ forward
    def forward(
        self,
        pose_window: Tensor,
        root_rot_window: Tensor,
        root_trans_window: Tensor,
        prev_latents: Tensor,
        feature_noise: Tensor | None = None,
    ) -> Tensor:
        """Latents of the window's last frame t.

        pose_window [B, N_b, P] (frames t-N_b+1..t), root_rot_window [B, N_b, 3],
        root_trans_window [B, N_b, 3], prev_latents [B, A, L] (frame t-1) -> [B, A, L] (clamped).
        ``feature_noise`` [B, S, F] (training only): added to the standardised pose-token features.
        """
        N, A, L = self.config.window_frames, self.num_anchors, self.config.latent_dim
        _check("pose_window", pose_window, (None, N, self.pose_dim))
        B = pose_window.shape[0]
        _check("root_rot_window", root_rot_window, (B, N, 3))
        _check("root_trans_window", root_trans_window, (B, N, 3))
        _check("prev_latents", prev_latents, (B, A, L))
        if self.config.readout == "signals" or (self.signals_only and self.config.readout == "both"):
            if feature_noise is not None and self.config.readout == "signals":
                raise ValueError("feature_noise: the signal readout has no pose-token features to perturb")
            return self._signal_forward(pose_window, root_rot_window, root_trans_window, prev_latents)
        x, xj = self.input_features(pose_window, root_rot_window, root_trans_window)
        x = (x - self.feature_mean) * self.feature_scale
        if feature_noise is not None:
            _check("feature_noise", feature_noise, (B, self.num_slots, self.feature_dim))
            x = x + feature_noise * (self.feature_scale > 0)  # dropped (constant) features stay zero
        lat = (prev_latents - self.latent_mean) / self.latent_scale  # [B, A, L] standardised
        parts = [self.pose_tokens(x) + self.type_embedding[0]]
        if self.num_joint_tokens:
            parts.append(
                self.joint_tokens((xj - self.joint_feature_mean) * self.joint_feature_scale) + self.joint_type_embedding
            )
        if self.config.latent_tokens:
            parts.append(self.latent_tokens(lat) + self.type_embedding[1])
        else:
            parts.append((self.anchor_queries + self.type_embedding[1]).expand(B, -1, -1))
        tokens = torch.cat(parts, 1)  # [B, S + J + A, D]
        h = self.norm(self.transformer(tokens + self.positional.to(tokens)))
        ha = h[:, self.num_slots + self.num_joint_tokens :]  # [B, A, D] the anchors' tokens
        if self.config.gate:  # l_{t-1} + g (c - l_{t-1}), in standardised units
            g = torch.sigmoid(self.gate_head(ha))
            out = prev_latents + self.latent_scale * g * (self.head(ha) - lat)
        else:
            base = prev_latents if self.config.residual else self.latent_mean
            out = base + self.latent_scale * self.head(ha)  # [B, A, L]
        if self.config.readout == "both":  # the signals gate the transformer's answer toward their candidate
            return self._signal_forward(pose_window, root_rot_window, root_trans_window, out, xj)
        return self.clamp_latents(out)

    def _signal_forward(
        self,
        pose_window: Tensor,
        root_rot_window: Tensor,
        root_trans_window: Tensor,
        prev_latents: Tensor,
        raw: Tensor | None = None,
    ) -> Tensor:
        """Gated update of the global latent PCA's coefficients from the selected kinematic signal tokens
        (:class:`PredictorConfig`): ``prev_latents`` are the previous frame's (``readout="signals"``) or the
        transformer's answer for frame t (``"both"``); ``raw``: the :meth:`joint_features` of the window when the
        caller has them. Before the latent PCA is fit there is no state to update: ``prev_latents`` are returned.
        Same arguments and result as :meth:`forward`."""
        if not bool(self.latent_pca_ready):
            return prev_latents
        B, K = prev_latents.shape[0], self.config.latent_pca_components
        if raw is None:
            raw = self.joint_features(pose_window, root_rot_window, root_trans_window)  # [B, J, 4 N]
        sig = ((raw - self.joint_feature_mean) * self.joint_feature_scale).reshape(B, -1, self.config.history)
        tok = torch.cat([sig, self.signal_kind_code.to(sig).expand(B, -1, -1)], -1)  # [B, J*4, N + 4]
        pooled = torch.einsum("ht,btd->bhd", torch.softmax(self.selection_logits, -1), self.signal_mlp(tok))
        o = self.signal_out(pooled.reshape(B, -1))  # [B, 2K]
        cand, gate = o[:, :K], torch.sigmoid(o[:, K:])
        basis = self.global_basis  # [A*L, K], orthonormal columns
        z = ((prev_latents - self.latent_mean) / self.latent_scale).flatten(1) @ basis  # [B, K]
        now = torch.zeros_like(z)
        if self.config.signal_pose_path:  # y = z + p: the state is what the current pose does not explain

            def last_two(x: Tensor) -> Tensor:  # frames t-1 and t (with N_b = 1, frame t twice)  [B, N, D] -> [2B, D]
                return (x[:, -2:] if x.shape[1] >= 2 else x[:, -1:].expand(-1, 2, -1)).reshape(2 * B, -1)

            f = self.initial_features(last_two(pose_window))
            if self.config.world_orientation:
                f = torch.cat([f, orientation_features(last_two(root_rot_window))], -1)
            p = self.signal_pose(f).reshape(B, 2, K)
            z, now = z - p[:, 0], p[:, 1]
        z = z + gate * (cand - z) + now
        out = self.latent_mean + self.latent_scale * (z @ basis.T).unflatten(-1, prev_latents.shape[-2:])
        return self.clamp_latents(out)

    # ------------------------------------------------------------------ initial latents
    def initial_features(self, pose: Tensor) -> Tensor:
        """InitialLatentNet input: clamped pose-PCA coefficients / σ (or the local slots). [B, P] -> [B, C]"""
        if self.pose_pca_basis is None:
            return pose[:, self.pose_slots]
        m, b, lim = self.pose_pca_mean.to(pose), self.pose_pca_basis.to(pose), self.pose_pca_limit.to(pose)
        return clamp_coefficients((pose - m) @ b, lim) / lim.clamp_min(1e-12)

    def initial_latents(self, pose: Tensor, trained_only: bool = True) -> Tensor:
        """Latents to start a rollout: the InitialLatentNet's (clamped) when available, else zeros.

        pose [B, P] -> [B, A, L]. ``trained_only=False`` uses the net even before it is marked trained.
        """
        _check("pose", pose, (None, self.pose_dim))
        if self.initial is None or (trained_only and not bool(self.initial_ready)):
            return pose.new_zeros(pose.shape[0], self.num_anchors, self.config.latent_dim)
        return self.clamp_latents(self.latent_mean + self.latent_scale * self.initial(self.initial_features(pose)))


_ENSEMBLE_FIELDS = (
    "history",
    "velocities",
    "latent_dim",
    "latent_pca",
    "latent_pca_components",
    "clamp_sigma",
    "zero_context",
)
"""What the members of an ensemble must share: the window they read and the latent space they write. The readout
and its architecture may differ (a transformer and a signal readout average like two seeds of one)."""
_FITTED_BUFFERS = ("latent_mean", "latent_scale")
"""Data statistics fit from the training targets; equal in members of one run, so checked."""


def _ensemble_interface(m: nn.Module) -> dict:
    return {
        "anchors": m.num_anchors,
        "pose_dim": m.pose_dim,
        **{f: getattr(m.config, f) for f in _ENSEMBLE_FIELDS},
    }


class PredictorEnsemble(_Streaming, nn.Module):
    """K appearance predictors that share an interface, trained from different seeds, averaged at every step.

    One frame's latents are the mean of the members' (clamped) predictions from the same pose window and the
    same previous latents, and that mean is what is fed back: the ensemble streams and rolls out exactly like
    one :class:`AppearancePredictor`. Averaging removes the seed-to-seed part of the members' errors (the
    members agree where the motion determines the appearance and scatter where a single predictor memorised
    its training sequence); measured in docs/train.md. The mean of clamped latents stays inside the clamp box
    (it is convex). The latent statistics, zero latents and mean latent are the first member's (every member is
    fit on the same training targets, so they are equal).

    Args:
        members: the trained predictors (same config, anchors, slots and pose dimension).
    """

    def __init__(self, members: Sequence[AppearancePredictor]) -> None:
        super().__init__()
        members = list(members)
        if not members:
            raise ValueError("members: an ensemble needs at least one predictor")
        m0 = members[0]
        for i, m in enumerate(members[1:], 1):
            key, key0 = _ensemble_interface(m), _ensemble_interface(m0)
            if key != key0:
                diff = {k: (key[k], key0[k]) for k in key if key[k] != key0[k]}
                raise ValueError(f"members[{i}]: differs from members[0] in what an ensemble shares: {diff}")
            for name in _FITTED_BUFFERS:
                if not torch.equal(getattr(m0, name), getattr(m, name)):
                    raise ValueError(f"members[{i}]: its fitted {name} differs from members[0]'s (another run's?)")
        self.members = nn.ModuleList(members)
        self.config, self.num_anchors, self.pose_dim = m0.config, m0.num_anchors, m0.pose_dim

    @property
    def latent_mean(self) -> Tensor:
        return self.members[0].latent_mean

    @property
    def latent_scale(self) -> Tensor:
        return self.members[0].latent_scale

    @property
    def latent_pca_ready(self) -> Tensor:
        return self.members[0].latent_pca_ready

    @property
    def initial(self) -> InitialLatentNet | None:
        """The first member's InitialLatentNet (None: the members have none)."""
        return self.members[0].initial

    @property
    def initial_ready(self) -> Tensor:
        return torch.stack([m.initial_ready for m in self.members]).all()

    def zero_latents(self) -> Tensor:
        return self.members[0].zero_latents()

    def clamp_latents(self, latents: Tensor) -> Tensor:
        return self.members[0].clamp_latents(latents)

    def initial_latents(self, pose: Tensor, trained_only: bool = True) -> Tensor:
        """Mean of the members' :meth:`AppearancePredictor.initial_latents`.  [B, P] -> [B, A, L]"""
        return torch.stack([m.initial_latents(pose, trained_only) for m in self.members]).mean(0)

    def forward(
        self,
        pose_window: Tensor,
        root_rot_window: Tensor,
        root_trans_window: Tensor,
        prev_latents: Tensor,
        feature_noise: Tensor | None = None,
    ) -> Tensor:
        """Mean of the members' :meth:`AppearancePredictor.forward` (same arguments).  -> [B, A, L]"""
        outs = [m(pose_window, root_rot_window, root_trans_window, prev_latents, feature_noise) for m in self.members]
        return torch.stack(outs).mean(0)
