"""Joint-local rotations -> a rig's pose vector, for any valid rig (``data_schema.rig``): the inverse of
``geometry.lbs.pose_to_local_rotations``, used by retargeting.

Per joint, by the kind of its parameters (first listed = leftmost factor, ``R = R_1 R_2 ... R_k``):

- **none**: nothing to write (the caller warns when such a joint should move);
- **one ``axis_angle``** (SMPL-X): the rotation vector of R; a joint with an ``axis_angle`` parameter among
  others: that parameter takes R, the others stay 0 (their product is then R);
- **three ``euler`` on principal axes** (``rz, ry, rx``; any order with consecutive axes distinct, signs
  allowed): the intrinsic Euler angles of that sequence;
- **three ``euler`` on mutually orthogonal axes** ``a, b, c`` (e.g. a bone's rest axes): with ``M = [a, b, c']``
  (``c' = +-c``, whichever makes ``M`` a rotation), ``R_a(t) = M R_x(t) M^T`` etc., so the angles are the
  intrinsic ``XYZ`` angles of ``M^T R M`` (the third negated when ``c' = -c``). Exact, like the case above;
- **anything else** (one or two euler parameters, non-orthogonal axes, more than three): the angles whose
  rotation is closest to R; one parameter: the twist of R about the axis, ``atan2(a . vee(R - R^T),
  tr R - a^T R a)`` (it maximises ``tr(R_a(t)^T R)``); several: that twist sequence refined by damped
  Gauss-Newton on the geodesic error ``log(R R(t)^T)``. A rig with fewer degrees of freedom than the motion
  gets the motion's projection onto them.

Euler angles are made continuous over frames: of the two solutions (and their 2 pi shifts) each frame takes
the one closest to the previous frame's.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.rig import PoseParam, Rig

_PRINCIPAL = {(1.0, 0.0, 0.0): "X", (0.0, 1.0, 0.0): "Y", (0.0, 0.0, 1.0): "Z"}
_ORTHO_TOL = 1e-6
_GN_ITERS = 30


def euler_continuous(R: np.ndarray, seq: str) -> np.ndarray:
    """Intrinsic Euler angles ``R = R_seq[0](a) R_seq[1](b) R_seq[2](c)`` per frame, continuous over time (of the
    two solutions and their 2 pi shifts each frame takes the closest to the previous frame). seq: three
    upper-case axes, consecutive ones distinct (Tait-Bryan ``ZYX`` or proper ``ZXZ``). [F,J,3,3] -> [F,J,3]"""
    F, J = R.shape[:2]
    e = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler(seq).reshape(F, J, 3)  # intrinsic
    mid = -e[..., 1] if seq[0] == seq[2] else math.pi - e[..., 1]
    alt = np.stack([e[..., 0] + math.pi, mid, e[..., 2] + math.pi], -1)
    alt = (alt + math.pi) % (2 * math.pi) - math.pi
    out = np.empty_like(e)
    out[0] = e[0]
    two_pi = 2 * math.pi
    for f in range(1, F):
        prev = out[f - 1]
        best = None
        for cand in (e[f], alt[f]):
            c = cand + two_pi * np.round((prev - cand) / two_pi)  # nearest 2 pi shift per angle
            d = np.abs(c - prev).sum(-1)
            if best is None:
                best, bd = c, d
            else:
                take = d < bd - 1e-9
                best = np.where(take[:, None], c, best)
                bd = np.where(take, d, bd)
        out[f] = best
    return out


def _rot(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations by ``angle`` [F] about unit ``axis`` [3]. -> [F, 3, 3]"""
    return Rotation.from_rotvec(angle[:, None] * axis[None]).as_matrix()


def twist_angle(R: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle t maximising ``tr(R_axis(t)^T R)`` (the closest rotation about ``axis``). R [F,3,3] -> [F]"""
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1)
    return np.arctan2(v @ axis, np.trace(R, axis1=1, axis2=2) - np.einsum("i,fij,j->f", axis, R, axis))


def _fit_angles(R: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """Angles t [F, k] whose product ``R_a1(t1) ... R_ak(tk)`` is closest to R [F,3,3] (module docstring)."""
    F, k = len(R), len(axes)
    t = np.zeros((F, k))
    rem = R.copy()
    for i, a in enumerate(axes):  # R = R_1 (R_2 ... R_k): peel the factors off from the left
        t[:, i] = twist_angle(rem, a)
        rem = np.swapaxes(_rot(a, t[:, i]), 1, 2) @ rem
    if k > 1:
        lam = 1e-9
        for _ in range(_GN_ITERS):
            P = np.broadcast_to(np.eye(3), (F, 3, 3)).copy()
            Jac = np.empty((F, 3, k))
            for i, a in enumerate(axes):  # d R / d t_i = [P_i a_i]x R, P_i = R_1 ... R_{i-1}
                Jac[:, :, i] = P @ a
                P = P @ _rot(a, t[:, i])
            err = Rotation.from_matrix(R @ np.swapaxes(P, 1, 2)).as_rotvec()  # log(R P^T), P = R(t)
            if np.abs(err).max() < 1e-12:
                break
            JtJ = np.swapaxes(Jac, 1, 2) @ Jac + lam * np.eye(k)
            t = t + np.linalg.solve(JtJ, (np.swapaxes(Jac, 1, 2) @ err[..., None]))[..., 0]
    return np.unwrap(t, axis=0) if F > 1 else t


def _joint_params(rig: Rig) -> dict[int, list[tuple[int, PoseParam]]]:
    """Joint index -> [(first pose slot, param)] in listed order."""
    out: dict[int, list[tuple[int, PoseParam]]] = {}
    slot = 0
    for p in rig.params:
        out.setdefault(rig.joint_index(p.joint), []).append((slot, p))
        slot += p.size
    return out


def _principal(axis: tuple[float, float, float]) -> tuple[str, float] | None:
    a = np.asarray(axis, dtype=np.float64)
    s = float(np.sign(a[np.argmax(np.abs(a))]))
    letter = _PRINCIPAL.get(tuple(float(round(v, 6)) for v in a * s))
    return None if letter is None else (letter, s)


def pose_from_local_rotations(L: np.ndarray, rig: Rig) -> np.ndarray:
    """Pose vector whose joint-local rotations are (closest to) L. L [F, J, 3, 3] -> pose [F, P] float64.

    Joints without parameters are skipped (their rotation cannot be expressed)."""
    L = np.asarray(L, dtype=np.float64)
    F = L.shape[0]
    pose = np.zeros((F, rig.pose_dim))
    by_seq: dict[str, list[tuple[int, list[int], np.ndarray, np.ndarray | None]]] = {}
    for j, plist in _joint_params(rig).items():
        slots = [s for s, _ in plist]
        aa = [s for s, p in plist if p.kind == "axis_angle"]
        if aa:  # that parameter carries the whole rotation, the others stay 0
            pose[:, aa[0] : aa[0] + 3] = Rotation.from_matrix(L[:, j]).as_rotvec()
            continue
        axes = np.array([p.axis for _, p in plist], dtype=np.float64)
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        if len(plist) == 3:
            pr = [_principal(p.axis) for _, p in plist]
            if all(x is not None for x in pr):
                seq = "".join(x[0] for x in pr)
                if seq[0] != seq[1] and seq[1] != seq[2]:
                    by_seq.setdefault(seq, []).append((j, slots, np.array([x[1] for x in pr]), None))
                    continue
            G = axes @ axes.T
            if np.abs(G - np.eye(3)).max() < _ORTHO_TOL:  # mutually orthogonal: exact, via principal XYZ
                M = axes.T.copy()  # columns a, b, c
                sign3 = 1.0
                if np.linalg.det(M) < 0:
                    M[:, 2] *= -1.0
                    sign3 = -1.0
                by_seq.setdefault("XYZ", []).append((j, slots, np.array([1.0, 1.0, sign3]), M))
                continue
        pose[:, slots] = _fit_angles(L[:, j], axes)
    for seq, items in by_seq.items():
        Rs = np.stack([L[:, j] if M is None else M.T @ L[:, j] @ M for j, _, _, M in items], 1)  # [F, n, 3, 3]
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Gimbal lock")  # any valid split; continuity decides the rest
            e = euler_continuous(Rs, seq)
        for k, (_, slots, signs, _) in enumerate(items):
            pose[:, slots] = e[:, k] * signs
    return pose


def pose_near_local_rotations(L: np.ndarray, ref: np.ndarray, rig: Rig) -> np.ndarray:
    """:func:`pose_from_local_rotations` of L, every frame's Euler angles the branch and 2 pi shift nearest those of
    its reference rotations (one pose for all frames or one per frame): the references are interleaved before the
    frames, and the continuity over time picks the nearest. L [F, J, 3, 3], ref [J, 3, 3] or [F, J, 3, 3] -> [F, P]"""
    L = np.asarray(L, dtype=np.float64)
    both = np.empty((2 * len(L),) + L.shape[1:])
    both[0::2], both[1::2] = ref, L
    return pose_from_local_rotations(both, rig)[1::2]
