"""Appearance that the motion's *history* causes: the states an appearance predictor can learn.

Real captures change appearance because of how the body moved: cloth swings and settles after
a hop, a sleeve stays pushed up after the arm was raised, a shirt darkens with sustained effort.
Each :class:`MotionEffect` is one such mechanism: a scalar *signal* read from the posed joints
(:func:`joint_signal`), a causal *mechanism* that turns the signal's history into a state
(:func:`spring_response`, :func:`hysteresis_state`, :func:`accumulator_state`), and a texture
*effect* on one garment region (:func:`apply_effect`). The same pose reached along different
paths gives different states, so the current pose alone cannot predict them (the capture's
fairness check, :mod:`gsavatar.synth.fairness`, measures how much the pose history adds).

Equations (frame rate ``r``, ``dt = 1 / r``, signal ``u_t``; docs/synth.md):

- spring: ``x'' + 2 zeta w x' + w^2 x = w^2 u``, ``w = 2 pi f``, zero-order hold of ``u_t`` over
  ``(t-1, t]``, discretised exactly (``z_t = Phi z_{t-1} + Gamma u_t``, ``Phi = exp(A dt)``);
  ``level = clip(x / (2.5 std(x)), -1, 1)`` (a unit step of ``u`` settles at ``x = 1``).
- hysteresis: thresholds ``lo``/``hi`` = quantiles of ``u`` over the capture; ``s_t = 1`` if
  ``u_t >= hi``, ``0`` if ``u_t <= lo``, else ``s_{t-1}``; ``s_{-1} = [u_0 > (lo + hi) / 2]``.
- accumulator: ``a = exp(-dt / tau)``, ``s_t = a s_{t-1} + (1 - a) min(u_t / u_ref, 1)``,
  ``s_{-1} = 0``, ``u_ref`` = a quantile of ``u`` (a constant ``u = u_ref`` gives ``1 - a^(t+1)``).

Signals are causal: velocities and accelerations are backward differences (frame 0 repeats
itself, so they start at zero).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.linalg import expm

Mechanism = Literal["spring", "hysteresis", "accumulator"]
Signal = Literal["height", "speed", "vertical_velocity", "vertical_acceleration"]
Effect = Literal["darken", "tint", "dye", "band"]

JOINT_ALIASES: dict[str, tuple[str, ...]] = {
    "pelvis": ("Hips", "pelvis"),
    "chest": ("Spine1", "spine3", "Spine", "spine2"),
    "head": ("Head", "head"),
    "left_hand": ("LeftHand", "left_wrist"),
    "right_hand": ("RightHand", "right_wrist"),
    "left_elbow": ("LeftForeArm", "left_elbow"),
    "right_elbow": ("RightForeArm", "right_elbow"),
    "left_knee": ("LeftLeg", "left_knee"),
    "right_knee": ("RightLeg", "right_knee"),
    "left_foot": ("LeftFoot", "left_ankle"),
    "right_foot": ("RightFoot", "right_ankle"),
}
"""Body-part names a :class:`MotionEffect` may use, with the rig joint names they match (CMU/anny, SMPL-X);
a rig joint name is accepted as well."""


@dataclass(frozen=True)
class MotionEffect:
    """One history-caused appearance mechanism: signal -> causal state -> texture effect."""

    name: str
    """State name (``gt/states.json`` frames[*].motion[name], ``gt/motion_states.npz``)."""
    mechanism: Mechanism
    """How the signal's history becomes a state (module docstring)."""
    signal: Signal
    """``height`` (m, of the joints above ``relative_to``), ``speed`` (m/s, relative to ``relative_to``),
    ``vertical_velocity`` (m/s, world) or ``vertical_acceleration`` (m/s^2, world); averaged over ``joints``."""
    joints: tuple[str, ...]
    """Body parts (:data:`JOINT_ALIASES` keys) or rig joint names the signal is read from."""
    region: str
    """Garment region the effect changes: ``shirt``, ``trousers``, ``hair``, ``skin``, ``shoe``, ``face``."""
    effect: Effect
    """``darken`` (x(1 - strength level)), ``tint`` (hue rotation by strength level rad), ``dye``
    (per-channel gain 1 + level (color - 1)) or ``band`` (a band of ``color`` whose height moves by
    strength level metres)."""
    strength: float = 0.4
    """Size of the effect at |level| = 1 (darken: fraction; tint: radians; band: metres; dye: unused)."""
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Dye gains at level 1, or the band's RGB colour."""
    relative_to: str | None = "pelvis"
    """Body part the ``height``/``speed`` signals are measured against (None: world)."""
    y_range: tuple[float, float] = (0.0, 1.0)
    """Part of the region affected, as fractions of the body height (band: where the band rests)."""
    frequency_hz: float = 1.5
    """Spring: natural frequency f."""
    damping: float = 0.3
    """Spring: damping ratio zeta (0 < zeta < 1: under-damped)."""
    low_quantile: float = 0.3
    """Hysteresis: the state resets when the signal falls to this quantile of its values."""
    high_quantile: float = 0.7
    """Hysteresis: the state sets when the signal rises to this quantile of its values."""
    time_constant_s: float = 1.5
    """Accumulator: decay time tau, seconds."""
    reference_quantile: float = 0.85
    """Accumulator: the input is the signal over this quantile of its values, clipped to [0, 1]."""

    def check(self) -> None:
        """Raise ValueError naming the first field out of range."""
        if self.mechanism not in ("spring", "hysteresis", "accumulator"):
            raise ValueError(
                f"motion effect {self.name!r}: mechanism must be spring/hysteresis/accumulator, got {self.mechanism!r}"
            )
        if self.signal not in ("height", "speed", "vertical_velocity", "vertical_acceleration"):
            raise ValueError(f"motion effect {self.name!r}: unknown signal {self.signal!r}")
        if self.effect not in ("darken", "tint", "dye", "band"):
            raise ValueError(f"motion effect {self.name!r}: effect must be darken/tint/dye/band, got {self.effect!r}")
        if not self.joints:
            raise ValueError(f"motion effect {self.name!r}: joints must name at least one body part")
        if not (self.frequency_hz > 0 and 0 < self.damping < 1):
            raise ValueError(
                f"motion effect {self.name!r}: need frequency_hz > 0 and 0 < damping < 1, got "
                f"{self.frequency_hz}, {self.damping}"
            )
        if not 0 <= self.low_quantile < self.high_quantile <= 1:
            raise ValueError(
                f"motion effect {self.name!r}: need 0 <= low_quantile < high_quantile <= 1, got "
                f"{self.low_quantile}, {self.high_quantile}"
            )
        if not (self.time_constant_s > 0 and 0 < self.reference_quantile <= 1):
            raise ValueError(
                f"motion effect {self.name!r}: need time_constant_s > 0 and reference_quantile in "
                f"(0, 1], got {self.time_constant_s}, {self.reference_quantile}"
            )
        if not self.y_range[0] < self.y_range[1]:
            raise ValueError(f"motion effect {self.name!r}: y_range must be increasing, got {self.y_range}")


# --------------------------------------------------------------------------- signals
def resolve_joint(name: str, joint_names: Sequence[str]) -> int:
    """Index of a body part (:data:`JOINT_ALIASES`) or rig joint name in ``joint_names``."""
    names = list(joint_names)
    for cand in JOINT_ALIASES.get(name, ()) + (name,):
        if cand in names:
            return names.index(cand)
    raise ValueError(
        f"body part {name!r} matches no rig joint (tried {JOINT_ALIASES.get(name, ()) + (name,)}; "
        f"the rig has {names[:8]}...)"
    )


def backward_diff(x: np.ndarray, fps: float) -> np.ndarray:
    """Causal derivative: ``(x_t - x_{t-1}) fps``, 0 at frame 0. x [F, ...] -> [F, ...]"""
    d = np.zeros_like(x, dtype=np.float64)
    d[1:] = (x[1:] - x[:-1]) * fps
    return d


def joint_signal(joints: np.ndarray, joint_names: Sequence[str], effect: MotionEffect, fps: float) -> np.ndarray:
    """The effect's scalar signal over the sequence. joints [F, J, 3] world positions (metres, +Y up) -> [F]"""
    if joints.ndim != 3 or joints.shape[2] != 3:
        raise ValueError(f"joints must be [F, J, 3], got {tuple(joints.shape)}")
    p = joints.astype(np.float64)
    idx = [resolve_joint(j, joint_names) for j in effect.joints]
    ref = p[:, resolve_joint(effect.relative_to, joint_names)] if effect.relative_to else np.zeros_like(p[:, 0])
    sel = p[:, idx]  # [F, k, 3]
    if effect.signal == "height":
        return (sel[..., 1] - ref[:, None, 1]).mean(1)
    if effect.signal == "speed":
        return np.linalg.norm(backward_diff(sel - ref[:, None], fps), axis=-1).mean(1)
    vy = backward_diff(sel[..., 1], fps)
    if effect.signal == "vertical_velocity":
        return vy.mean(1)
    return backward_diff(vy, fps).mean(1)  # vertical_acceleration


# --------------------------------------------------------------------------- mechanisms
def spring_response(u: np.ndarray, fps: float, frequency_hz: float, damping: float) -> np.ndarray:
    """Displacement of ``x'' + 2 zeta w x' + w^2 x = w^2 u`` from rest, exact ZOH discretisation. u [F] -> [F]"""
    w = 2 * np.pi * frequency_hz
    A = np.array([[0.0, 1.0], [-w * w, -2 * damping * w]])
    B = np.array([0.0, w * w])
    phi = expm(A / fps)
    gamma = np.linalg.solve(A, (phi - np.eye(2)) @ B)
    z = np.zeros(2)
    out = np.empty(len(u))
    for t, ut in enumerate(np.asarray(u, np.float64)):
        z = phi @ z + gamma * ut
        out[t] = z[0]
    return out


def hysteresis_state(u: np.ndarray, low: float, high: float) -> np.ndarray:
    """Set at ``u >= high``, reset at ``u <= low``, held in between. u [F] -> [F] float in {0, 1}"""
    u = np.asarray(u, np.float64)
    s = np.empty(len(u))
    cur = bool(len(u)) and u[0] > 0.5 * (low + high)
    for t, ut in enumerate(u):
        if ut >= high:
            cur = True
        elif ut <= low:
            cur = False
        s[t] = float(cur)
    return s


def accumulator_state(u: np.ndarray, fps: float, time_constant_s: float, reference: float) -> np.ndarray:
    """Leaky integral of ``min(u / reference, 1)`` (clipped at 0) with decay time tau. u [F] -> [F] in [0, 1]"""
    a = float(np.exp(-1.0 / (time_constant_s * fps)))
    x = np.clip(np.asarray(u, np.float64) / max(reference, 1e-12), 0.0, 1.0)
    s, cur = np.empty(len(x)), 0.0
    for t, xt in enumerate(x):
        cur = a * cur + (1 - a) * xt
        s[t] = cur
    return s


def effect_level(effect: MotionEffect, u: np.ndarray, fps: float) -> tuple[np.ndarray, dict]:
    """The effect's texture level over the sequence and its constants. u [F] -> ([F], {name: float})"""
    if effect.mechanism == "spring":
        x = spring_response(u - u[0], fps, effect.frequency_hz, effect.damping)  # rest at the first frame's signal
        scale = 2.5 * float(x.std()) if x.std() > 1e-9 else 1.0
        return np.clip(x / scale, -1.0, 1.0), {"scale": scale}
    if effect.mechanism == "hysteresis":
        lo, hi = (float(np.quantile(u, q)) for q in (effect.low_quantile, effect.high_quantile))
        return hysteresis_state(u, lo, hi), {"low": lo, "high": hi}
    ref = float(np.quantile(u, effect.reference_quantile))
    return accumulator_state(u, fps, effect.time_constant_s, ref), {"reference": ref}


# --------------------------------------------------------------------------- texture
def hue_rotation(angle: float) -> np.ndarray:
    """3x3 RGB rotation about the grey axis (hue shift that keeps the grey level). -> [3, 3]"""
    a = np.ones(3) / np.sqrt(3.0)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K).astype(np.float32)


def apply_effect(
    flat: np.ndarray,
    idx: np.ndarray,
    weight: np.ndarray,
    y: np.ndarray,
    effect: MotionEffect,
    level: float,
    body_height: float,
) -> None:
    """Change the texels ``idx`` of ``flat`` [S*S, 3] in place by ``effect`` at ``level``.

    weight [n, 1] region membership in [0, 1]; y [n] texel heights as fractions of the body height.
    """
    if effect.effect == "darken":
        flat[idx] *= 1 - effect.strength * abs(level) * weight
    elif effect.effect == "tint":
        M = hue_rotation(effect.strength * level)
        c = flat[idx]
        flat[idx] = c + weight * (c @ M.T - c)
    elif effect.effect == "dye":
        g = np.asarray(effect.color, np.float32)
        flat[idx] *= 1 + weight * level * (g - 1)
    else:  # band
        y0, y1 = effect.y_range
        centre = 0.5 * (y0 + y1) + effect.strength * level / body_height
        half = 0.25 * (y1 - y0)
        d = np.abs(y - centre)
        m = (np.clip((half - d) / max(0.2 * half, 1e-6) + 0.5, 0.0, 1.0)[:, None] * weight).astype(np.float32)
        flat[idx] = flat[idx] * (1 - m) + m * np.asarray(effect.color, np.float32)
