"""Frame-rate resampling of motions: one implementation for every consumer (BVH retargeting,
driving inputs, the importers to come).

Output frame ``k`` is at time ``k / fps_out`` from the first source frame (the clip never extends past
the last source frame), so 60 -> 30 fps keeps every other frame *exactly* and 15 -> 30 inserts
midpoints. Interpolation is rotation-aware:

- root rotation (axis-angle) and each joint with a single ``axis_angle`` parameter:
  quaternion slerp (shortest arc), back to a rotation vector;
- each joint with three ``euler`` parameters on principal axes (``rz, ry, rx`` etc.,
  consecutive axes distinct, signs allowed): the joint's local rotation is built from its
  angles (first listed = leftmost factor), slerped, and decomposed back into the same
  sequence; of the two Euler solutions (and their 2π wraps) we keep the one closest to the
  linear interpolation of the angles, so the angle curves stay continuous;
- a joint with one euler parameter (a hinge): linear in the angle, which *is* the slerp
  for steps below π; joints with two euler parameters, mixed kinds or non-principal axes:
  linear per parameter (a slerped rotation generally leaves their 1-2 DOF manifold);
- root translation and face embedding: linear;
- rotation matrices (:func:`slerp_matrices`, used by BVH retargeting before the Euler
  decomposition): shortest-arc slerp.

A resampled motion may have at most MAX_RESAMPLED_FRAMES frames (:mod:`gsavatar.data_schema.limits`);
loaders check the frame rates they read against [MIN_FPS, MAX_FPS] first, naming the file.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.limits import MAX_RESAMPLED_FRAMES
from gsavatar.data_schema.rig import Rig

_AXES = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}


class ResampleTimes(NamedTuple):
    i0: np.ndarray
    """Left source frame of each output frame.  # [T_out] int64"""
    i1: np.ndarray
    """Right source frame.  # [T_out] int64"""
    alpha: np.ndarray
    """Weight of ``i1`` in [0, 1); exactly 0 on source frames.  # [T_out] float64"""


# --------------------------------------------------------------------------- stateless math
def times_at(source_frames: np.ndarray, n_in: int) -> ResampleTimes:
    """:class:`ResampleTimes` of arbitrary (fractional, non-decreasing or not) source frame positions, e.g. a
    motion played at a varying tempo; a position within 1e-6 of a source frame is that frame.
    source_frames [T_out] float in [0, n_in - 1]"""
    s = np.asarray(source_frames, np.float64)
    if s.ndim != 1 or not np.isfinite(s).all() or (s.size and (s.min() < -1e-9 or s.max() > n_in - 1 + 1e-9)):
        raise ValueError(f"source frame positions must be finite and within [0, {n_in - 1}]")
    s = np.clip(s, 0.0, n_in - 1)
    i0 = np.minimum(np.floor(s + 1e-6).astype(np.int64), n_in - 1)
    a = np.clip(s - i0, 0.0, 1.0)
    a[a < 1e-6] = 0.0
    return ResampleTimes(i0, np.minimum(i0 + 1, n_in - 1), a)


def resample_times(n_in: int, fps_in: float, fps_out: float) -> ResampleTimes:
    """Source positions of the output frames ``k / fps_out`` within ``[0, (n_in - 1) / fps_in]``."""
    if n_in < 1:
        raise ValueError(f"n_in must be >= 1, got {n_in}")
    if not (fps_in > 0 and fps_out > 0 and math.isfinite(fps_in) and math.isfinite(fps_out)):
        raise ValueError(f"fps_in and fps_out must be positive, got {fps_in}, {fps_out}")
    ratio = fps_in / fps_out
    n_out = int(math.floor((n_in - 1) / ratio + 1e-6)) + 1
    if n_out > MAX_RESAMPLED_FRAMES:
        raise ValueError(
            f"resampling {n_in} frames from {fps_in:g} to {fps_out:g} fps makes {n_out} frames, "
            f"more than the {MAX_RESAMPLED_FRAMES} allowed"
        )
    return times_at(np.minimum(np.arange(n_out, dtype=np.float64) * ratio, n_in - 1), n_in)


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Shortest-arc slerp of unit quaternions (any component order). [...,4], [...,4], [...] -> [...,4]"""
    q1 = np.where((np.sum(q0 * q1, -1) < 0)[..., None], -q1, q1)
    d = np.clip(np.sum(q0 * q1, -1), -1.0, 1.0)
    th = np.arccos(d)
    s = np.sin(th)
    small = s < 1e-8
    s_safe = np.where(small, 1.0, s)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * th) / s_safe)
    w1 = np.where(small, alpha, np.sin(alpha * th) / s_safe)
    q = w0[..., None] * q0 + w1[..., None] * q1
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def slerp_rotvec(r0: np.ndarray, r1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Slerp between axis-angle rotations. [N,3], [N,3], [N] -> [N,3]"""
    q = quat_slerp(Rotation.from_rotvec(r0).as_quat(), Rotation.from_rotvec(r1).as_quat(), alpha)
    return Rotation.from_quat(q).as_rotvec()


def _wrap_to(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Add multiples of 2π to ``x`` to bring it closest to ``ref`` (elementwise)."""
    return x + 2 * np.pi * np.round((ref - x) / (2 * np.pi))


def euler_from_matrix_near(R: np.ndarray, seq: str, ref: np.ndarray) -> np.ndarray:
    """Intrinsic Euler angles (``R = R_seq[0](a0) R_seq[1](a1) R_seq[2](a2)``) of R [N,3,3],
    choosing among the two solutions and their 2π wraps the one closest to ``ref`` [N,3]. -> [N,3]"""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # gimbal lock: any valid split is fine, ref decides the rest
        e = Rotation.from_matrix(R).as_euler(seq)
    alt = e.copy()
    alt[:, 0] += np.pi
    alt[:, 2] += np.pi
    alt[:, 1] = -e[:, 1] if seq[0] == seq[2] else np.pi - e[:, 1]
    cands = np.stack([_wrap_to(e, ref), _wrap_to(alt, ref)])  # [2, N, 3]
    best = np.argmin(((cands - ref[None]) ** 2).sum(-1), axis=0)  # [N]
    return cands[best, np.arange(len(R))]


def _joint_layouts(rig: Rig) -> list[tuple[str, list[int], str, np.ndarray]]:
    """Per joint with parameters: (kind, pose slots, euler seq, axis signs).

    kind: ``aa`` (one axis-angle param), ``euler3`` (three principal-axis euler params,
    consecutive axes distinct), ``linear`` (anything else)."""
    slots: dict[str, list[int]] = {}
    params: dict[str, list] = {}
    k = 0
    for p in rig.params:
        slots.setdefault(p.joint, []).extend(range(k, k + p.size))
        params.setdefault(p.joint, []).append(p)
        k += p.size
    out = []
    for j, ps in params.items():
        if len(ps) == 1 and ps[0].kind == "axis_angle":
            out.append(("aa", slots[j], "", np.ones(3)))
            continue
        if len(ps) == 3 and all(p.kind == "euler" for p in ps):
            letters, signs = [], []
            for p in ps:
                ax = np.asarray(p.axis, dtype=np.float64)
                s = float(np.sign(ax[np.argmax(np.abs(ax))]))
                letter = _AXES.get(tuple(float(round(v, 6)) for v in ax * s))
                letters.append(letter)
                signs.append(s)
            seq = "".join(letter or "?" for letter in letters)
            if "?" not in seq and seq[0] != seq[1] and seq[1] != seq[2]:
                out.append(("euler3", slots[j], seq, np.array(signs)))
                continue
        out.append(("linear", slots[j], "", np.ones(3)))
    return out


def lerp_frames(x: np.ndarray, t: ResampleTimes) -> np.ndarray:
    """Linear interpolation of per-frame values at the output times. x [T_in, ...] -> [T_out, ...]"""
    a = t.alpha.reshape(-1, *([1] * (x.ndim - 1)))
    return (1.0 - a) * x[t.i0] + a * x[t.i1]


def slerp_matrices(R: np.ndarray, t: ResampleTimes) -> np.ndarray:
    """Shortest-arc slerp of per-frame rotation matrices at the output times; output frames on a source
    frame are copied exactly. R [T_in, ..., 3, 3] -> [T_out, ..., 3, 3] float64"""
    R = np.asarray(R, np.float64)
    out = R[t.i0].copy()
    moving = t.alpha > 0
    if moving.any():
        shape = out[moving].shape  # [M, ..., 3, 3]
        q0 = Rotation.from_matrix(R[t.i0[moving]].reshape(-1, 3, 3)).as_quat()
        q1 = Rotation.from_matrix(R[t.i1[moving]].reshape(-1, 3, 3)).as_quat()
        a = np.broadcast_to(t.alpha[moving].reshape(-1, *([1] * (len(shape) - 3))), shape[:-2]).reshape(-1)
        out[moving] = Rotation.from_quat(quat_slerp(q0, q1, a)).as_matrix().reshape(shape)
    return out


def resample_motion(
    pose: np.ndarray,
    root_rotation: np.ndarray,
    root_translation: np.ndarray,
    face: np.ndarray | None,
    rig: Rig,
    fps_in: float,
    fps_out: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None, ResampleTimes]:
    """Rotation-aware resampling (module docstring). pose [T,P], root_rotation [T,3],
    root_translation [T,3], face [T,E] | None -> the same at ``fps_out`` (float32) + the times.
    Output frames that land on a source frame are copied bit-exactly."""
    t = resample_times(np.asarray(pose).shape[0], fps_in, fps_out)
    return (*resample_motion_at(pose, root_rotation, root_translation, face, rig, t), t)


def resample_motion_at(
    pose: np.ndarray,
    root_rotation: np.ndarray,
    root_translation: np.ndarray,
    face: np.ndarray | None,
    rig: Rig,
    t: ResampleTimes,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`resample_motion` at given source positions ``t`` (:func:`resample_times`, :func:`times_at`)."""
    pose = np.asarray(pose, np.float64)
    if pose.ndim != 2 or pose.shape[1] != rig.pose_dim:
        raise ValueError(f"pose must be [T, {rig.pose_dim}], got {list(pose.shape)}")
    new_pose = lerp_frames(pose, t)
    moving = t.alpha > 0
    if moving.any():
        i0, i1, a = t.i0[moving], t.i1[moving], t.alpha[moving]
        for kind, sl, seq, signs in _joint_layouts(rig):
            if kind == "aa":
                new_pose[np.ix_(moving, sl)] = slerp_rotvec(pose[i0][:, sl], pose[i1][:, sl], a)
            elif kind == "euler3":
                e0, e1 = pose[i0][:, sl] * signs, pose[i1][:, sl] * signs
                q = quat_slerp(Rotation.from_euler(seq, e0).as_quat(), Rotation.from_euler(seq, e1).as_quat(), a)
                ref = (1 - a[:, None]) * e0 + a[:, None] * e1
                new_pose[np.ix_(moving, sl)] = (
                    euler_from_matrix_near(Rotation.from_quat(q).as_matrix(), seq, ref) * signs
                )
    rr = np.asarray(root_rotation, np.float64)
    new_rr = rr[t.i0].copy()
    if moving.any():
        new_rr[moving] = slerp_rotvec(rr[t.i0[moving]], rr[t.i1[moving]], t.alpha[moving])
    new_rt = lerp_frames(np.asarray(root_translation, np.float64), t)
    new_face = None if face is None else lerp_frames(np.asarray(face, np.float64), t)
    # bit-exact copies on source frames
    exact = ~moving
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    out = [f32(new_pose), f32(new_rr), f32(new_rt), None if face is None else f32(new_face)]
    for o, src in zip(out, (pose, rr, root_translation, face)):
        if o is not None:
            o[exact] = np.asarray(src, np.float32)[t.i0[exact]]
    return out[0], out[1], out[2], out[3]
