"""Retarget BVH motion capture (e.g. CMU) onto a gsavatar :class:`Rig` (e.g. the Anny
``cmu_mb`` body from :mod:`gsavatar.synth.body`). Used by the synthetic captures and by driving.

Method (per frame, rotations as 3x3 matrices)::

    G_bvh_j            BVH global rotation of joint j (standard BVH FK, rest = all channels 0)
    C                  BVH axes -> our axes (identity for CMU: both are Y up, facing +Z, left +X)
    A_j                rest alignment: maps our rest bone directions of j (towards its
                       children) onto the BVH rest bone directions (minimal rotation for one
                       child, Kabsch for several; leaves inherit their parent's A)
    G_j = C G_bvh_j C^T A_j          our global rotation
    L_j = G_parent(j)^T G_j          our local rotation -> euler params (R = Rz Ry Rx)

so every bone of our rig points where the corresponding BVH bone points, whatever the
two rest poses are (CMU: T-pose; Anny: A-pose). Joints of our rig without a BVH
counterpart get identity local rotations. The root's ``G`` becomes ``root_rotation``
(axis-angle); the root position is the BVH root position times a scale (ratio of leg
lengths, thigh + shin) mapped by ``C``, shifted vertically so the lowest foot joint over
the clip matches our rest foot height (feet stay on the ground), and horizontally so
the first output frame starts at x = z = 0 (``center_xz``).

Frame-rate change (:mod:`gsavatar.motion.resample`): local rotations are resampled by
quaternion slerp, the root translation linearly; output frame k is at time ``k / fps_out``
from the first source frame, so for 120 -> 30 fps output frame k equals source frame 4k exactly.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.limits import check_resampled_frames
from gsavatar.data_schema.rig import Rig
from gsavatar.motion.bvh import BvhMotion, bvh_global_transforms, bvh_rest_positions, read_bvh
from gsavatar.motion.resample import lerp_frames, resample_times, slerp_matrices

CMU_NAME_MAP: dict[str, str] = {"LeftHandFinger1": "LFingers", "RightHandFinger1": "RFingers"}
"""Our (Anny cmu_mb) joint name -> CMU BVH joint name, where they differ."""

_FOOT_JOINTS = ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")


class RetargetedMotion(NamedTuple):
    pose: np.ndarray
    """Pose vector per frame, radians (rig param order).  # [F, P] float32"""
    root_rotation: np.ndarray
    """Root rotation, axis-angle (world = R (x - head_root) + head_root + t).  # [F, 3] float32"""
    root_translation: np.ndarray
    """Root translation, metres.  # [F, 3] float32"""
    fps: float
    """Frames per second of the output."""


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------
def _snap_fps(fps: float) -> float:
    """120.00048 (from 'Frame Time: .0083333') -> 120.0."""
    r = round(fps)
    return float(r) if r > 0 and abs(fps - r) < 1e-4 * fps else float(fps)


def _min_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking direction a onto direction b. -> [3, 3]"""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = np.linalg.norm(v)
    if s < 1e-9:
        if c > 0:
            return np.eye(3)
        # 180 degrees: any axis orthogonal to a
        ax = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        ax /= np.linalg.norm(ax)
        return Rotation.from_rotvec(math.pi * ax).as_matrix()
    return Rotation.from_rotvec(v / s * math.atan2(s, c)).as_matrix()


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R src_i - dst_i|^2 (unit vectors). [N,3],[N,3] -> [3,3]"""
    H = src.T @ dst
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d])
    return Vt.T @ D @ U.T


def _rig_children(rig: Rig) -> list[list[int]]:
    out: list[list[int]] = [[] for _ in rig.joints]
    for j, p in enumerate(rig.parents().tolist()):
        if p >= 0:
            out[p].append(j)
    return out


def _bone_pairs(j: int, children: list[list[int]], to_bvh: dict[int, int], heads: np.ndarray, bvh_rest: np.ndarray, eps_o: float, eps_b: float):
    """(our rest vector, BVH rest vector) pairs from joint j towards its (mapped) descendants.

    A child at (near) zero distance on either side is skipped in favour of its children.
    """
    pairs = []
    stack = list(children[j])
    while stack:
        c = stack.pop(0)
        if c not in to_bvh:
            continue
        vo = heads[c] - heads[j]
        vb = bvh_rest[to_bvh[c]] - bvh_rest[to_bvh[j]]
        if np.linalg.norm(vo) < eps_o or np.linalg.norm(vb) < eps_b:
            stack.extend(children[c])
            continue
        pairs.append((vo, vb))
    return pairs


def _leg_length(points: np.ndarray, idx: dict[str, int]) -> float | None:
    total, n = 0.0, 0
    for side in ("Left", "Right"):
        chain = [f"{side}UpLeg", f"{side}Leg", f"{side}Foot"]
        if all(c in idx for c in chain):
            p = points[[idx[c] for c in chain]]
            total += np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[1])
            n += 1
    return total / n if n else None


def _euler_zyx_continuous(R: np.ndarray) -> np.ndarray:
    """R = Rz(a) Ry(b) Rx(c) -> (a, b, c) per frame, continuous over time. [F,J,3,3] -> [F,J,3]

    Of the two equivalent solutions (and their 2 pi shifts) each frame takes the one
    closest to the previous frame, so angles do not jump by 2 pi at +-180 degrees.
    """
    F, J = R.shape[:2]
    e = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler("ZYX").reshape(F, J, 3)  # intrinsic
    alt = np.stack([e[..., 0] + math.pi, math.pi - e[..., 1], e[..., 2] + math.pi], -1)
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


# --------------------------------------------------------------------------------------
# main entry points
# --------------------------------------------------------------------------------------
def retarget_bvh(
    bvh: BvhMotion,
    rig: Rig,
    rest_heads: np.ndarray | None = None,
    fps_out: float | None = None,
    frames: slice | None = None,
    *,
    name_map: dict[str, str] | None = None,
    bvh_to_ours: np.ndarray | None = None,
    scale: float | None = None,
    center_xz: bool = True,
) -> RetargetedMotion:
    """Retarget ``bvh`` onto ``rig`` (see module docstring for the method).

    rest_heads: our rest joint positions [J, 3] (default ``rig.heads()``).
    fps_out: output frame rate (default: the BVH's); resampled by slerp/lerp.
    frames: source (BVH) frames to use, e.g. ``slice(0, 400)`` (default: all).
    name_map: our joint name -> BVH joint name (or ``None``: no counterpart) where they
        differ (default :data:`CMU_NAME_MAP`); other joints match by name.
    bvh_to_ours: 3x3 rotation from BVH axes to ours (default identity: Y up, facing +Z).
    scale: metres per BVH unit (default: our leg length / BVH leg length).
    center_xz: move the horizontal root position of the first output frame to x = z = 0.
    """
    heads = np.asarray(rig.heads() if rest_heads is None else rest_heads, dtype=np.float64)
    J = rig.num_joints
    if heads.shape != (J, 3):
        raise ValueError(f"rest_heads must be [{J}, 3], got {heads.shape}")
    for p in rig.params:
        if p.kind != "euler":
            raise ValueError(f"retarget_bvh supports euler rigs only; {p.name} is {p.kind}")
    C = np.eye(3) if bvh_to_ours is None else np.asarray(bvh_to_ours, np.float64)
    nm = dict(CMU_NAME_MAP if name_map is None else name_map)
    bidx = {n: i for i, n in enumerate(bvh.names)}
    to_bvh: dict[int, int] = {}
    for j, jt in enumerate(rig.joints):
        b = nm.get(jt.name, jt.name)  # None: deliberately unmapped
        if b is not None and b in bidx:
            to_bvh[j] = bidx[b]
    parents = rig.parents()
    root = int(np.flatnonzero(parents < 0)[0])
    if root not in to_bvh:
        raise ValueError(f"the rig root {rig.joints[root].name!r} has no BVH joint (BVH joints: {bvh.names})")

    # --- scale: ratio of leg lengths ----------------------------------------------------
    bvh_rest = bvh_rest_positions(bvh)
    if scale is None:
        ours_idx = {jt.name: j for j, jt in enumerate(rig.joints)}
        bvh_named = {rig.joints[j].name: b for j, b in to_bvh.items()}
        lo = _leg_length(heads, ours_idx)
        lb = _leg_length(bvh_rest, bvh_named)
        if lo and lb:
            scale = lo / lb
        else:  # fall back to the overall rest heights
            hb = np.ptp(bvh_rest[:, 1])
            scale = np.ptp(heads[:, 1]) / hb if hb > 0 else 1.0
    scale = float(scale)

    # --- rest alignment A_j ---------------------------------------------------------
    children = _rig_children(rig)
    eps_o = 1e-4 * max(np.ptp(heads, axis=0).max(), 1e-9)
    eps_b = 1e-4 * max(np.ptp(bvh_rest, axis=0).max(), 1e-9)
    A = np.tile(np.eye(3), (J, 1, 1))
    for j in range(J):  # parents first
        if j not in to_bvh:
            A[j] = A[parents[j]] if parents[j] >= 0 else np.eye(3)
            continue
        pairs = _bone_pairs(j, children, to_bvh, heads, bvh_rest, eps_o, eps_b)
        if not pairs:
            A[j] = A[parents[j]] if parents[j] >= 0 else np.eye(3)
        elif len(pairs) == 1:
            A[j] = _min_rotation(pairs[0][0], C @ pairs[0][1])
        else:
            src = np.array([p[0] / np.linalg.norm(p[0]) for p in pairs])
            dst = np.array([C @ p[1] / np.linalg.norm(p[1]) for p in pairs])
            A[j] = _kabsch(src, dst)

    # --- per-frame global rotations ---------------------------------------------------
    src_frames = np.arange(bvh.num_frames)[frames if frames is not None else slice(None)]
    if len(src_frames) == 0:
        raise ValueError(f"no frames selected ({frames}) from {bvh.num_frames}")
    Gb = bvh_global_transforms(bvh, src_frames)  # [F, Jb, 4, 4]
    F = len(src_frames)
    G = np.empty((F, J, 3, 3))
    for j in range(J):
        if j in to_bvh:
            G[:, j] = C @ Gb[:, to_bvh[j], :3, :3] @ C.T @ A[j]
        else:
            G[:, j] = G[:, parents[j]] if parents[j] >= 0 else np.eye(3)
    L = np.empty_like(G)
    for j in range(J):
        p = parents[j]
        L[:, j] = G[:, j] if p < 0 else np.swapaxes(G[:, p], -1, -2) @ G[:, j]
    root_pos = scale * (Gb[:, to_bvh[root], :3, 3] @ C.T)  # [F, 3] metres, our axes

    # --- ground: lowest foot joint over the whole clip at our rest foot height -------------
    feet = [j for j, jt in enumerate(rig.joints) if jt.name in _FOOT_JOINTS and j in to_bvh]
    up = np.array([0.0, 1.0, 0.0])
    if feet:
        all_pos = bvh_global_transforms(bvh, None)[:, [to_bvh[j] for j in feet], :3, 3]  # whole clip
        lowest_bvh = float((scale * all_pos @ C.T @ up).min())
        lowest_ours = float((heads[feet] @ up).min())
        dy = lowest_ours - lowest_bvh
    else:
        dy = float(heads[root] @ up - (scale * (bvh_rest[to_bvh[root]] @ C.T)) @ up)
    root_pos = root_pos + dy * up

    # --- resample ---------------------------------------------------------------------
    fps_src = _snap_fps(bvh.fps)
    step = 1
    if isinstance(frames, slice) and frames.step not in (None, 0):
        step = abs(int(frames.step))
    fps_in = fps_src / step
    fps = float(fps_in if fps_out is None else fps_out)
    if fps <= 0:
        raise ValueError(f"fps_out must be > 0, got {fps_out}")
    if fps_out is not None and abs(fps - fps_in) > 1e-9 and F > 1:
        check_resampled_frames(F, fps_in, fps, bvh.path or "BVH", "MOTION")
        times = resample_times(F, fps_in, fps)
        L = slerp_matrices(L, times)  # exact source frames where output times coincide (e.g. 120 -> 30 fps)
        root_pos = lerp_frames(root_pos, times)
    if center_xz:
        root_pos = root_pos - np.array([root_pos[0, 0], 0.0, root_pos[0, 2]])

    # --- pack --------------------------------------------------------------------------
    eul = _euler_zyx_continuous(L)  # [F, J, 3] (rz, ry, rx)
    col = {"rz": 0, "ry": 1, "rx": 2}
    axis_of = {(0.0, 0.0, 1.0): "rz", (0.0, 1.0, 0.0): "ry", (1.0, 0.0, 0.0): "rx"}
    pose = np.zeros((L.shape[0], rig.pose_dim))
    per_joint: dict[int, list[str]] = {}
    for i, p in enumerate(rig.params):
        j = rig.joint_index(p.joint)
        ax = axis_of.get(tuple(float(round(a, 6)) for a in p.axis))
        if ax is None:
            raise ValueError(f"{p.name}: retarget_bvh needs principal-axis euler params, got axis {p.axis}")
        per_joint.setdefault(j, []).append(ax)
        pose[:, i] = eul[:, j, col[ax]]
    for j, axes in per_joint.items():
        if axes != ["rz", "ry", "rx"]:
            raise ValueError(f"joint {rig.joints[j].name}: params must be rz, ry, rx in that order, got {axes}")
        if j == root:
            raise ValueError("the root joint must have no pose params (its motion is root_rotation)")
    missing = [rig.joints[j].name for j in range(J) if j != root and j not in per_joint]
    if missing:
        warnings.warn(f"joints without pose params keep their rest orientation: {missing}", stacklevel=2)
    root_rot = Rotation.from_matrix(L[:, root]).as_rotvec()
    # translation t with world_root_head = head_root + t
    root_trans = root_pos - heads[root]
    return RetargetedMotion(
        pose=pose.astype(np.float32),
        root_rotation=root_rot.astype(np.float32),
        root_translation=root_trans.astype(np.float32),
        fps=fps,
    )


def motion_from_bvh_file(
    path: str | Path,
    rig: Rig,
    fps_out: float | None = None,
    start: int = 0,
    count: int | None = None,
    **kwargs,
) -> RetargetedMotion:
    """Read a BVH file and retarget ``count`` OUTPUT frames starting at source frame ``start``.

    ``count=None`` takes everything to the end of the file. Extra keyword arguments go to
    :func:`retarget_bvh` (``name_map``, ``bvh_to_ours``, ``scale``, ``center_xz``).
    """
    bvh = read_bvh(path)
    if not 0 <= start < bvh.num_frames:
        raise ValueError(f"{path}: start={start} outside [0, {bvh.num_frames})")
    stop = bvh.num_frames
    if count is not None:
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        fps_src = _snap_fps(bvh.fps)
        ratio = fps_src / (fps_src if fps_out is None else float(fps_out))
        stop = min(bvh.num_frames, start + int(math.ceil((count - 1) * ratio - 1e-6)) + 1)
    if fps_out is not None:  # refused here, naming the file, before the retargeting work
        check_resampled_frames(stop - start, _snap_fps(bvh.fps), float(fps_out), path, "MOTION")
    m = retarget_bvh(bvh, rig, None, fps_out, slice(start, stop), **kwargs)
    if count is not None and len(m.pose) > count:
        m = RetargetedMotion(m.pose[:count], m.root_rotation[:count], m.root_translation[:count], m.fps)
    return m
