"""Retarget BVH motion capture onto any gsavatar :class:`Rig`: the Anny ``cmu_mb`` body of the synthetic
captures (euler ``rz, ry, rx``), an imported SMPL-X body (``axis_angle``), rigs with euler axes about any axes.
Used by the synthetic captures and by driving.

Joint matching (:mod:`gsavatar.motion.joint_names`): rig and BVH names are read with their detected
conventions (CMU, Biovision/MotionBuilder, Mixamo, SMPL-X) and matched by canonical name; ``name_map`` (rig
joint -> BVH joint or None, e.g. the user's ``--joint-map`` file) overrides the rig joints it lists.

Method (per frame, rotations as 3x3 matrices)::

    G_bvh_j            BVH global rotation of joint j (standard BVH FK, rest = all channels 0)
    C                  BVH axes -> our axes (identity for CMU: both are Y up, facing +Z, left +X)
    A_j                rest alignment: maps our rest bone directions of j (towards its matched
                       descendants) onto the BVH rest bone directions (minimal rotation for one
                       bone, Kabsch for several; leaves inherit their parent's A)
    G_j = C G_bvh_j C^T A_j          our global rotation
    L_j = G_parent(j)^T G_j          our local rotation -> the rig's parameters (:mod:`~gsavatar.motion.rig_pose`)

so every bone of our rig points where the corresponding BVH bone points, whatever the two rest poses are
(CMU: T-pose; Anny: A-pose), and whatever the rig's parameters are: world-space bone rotations relative to
each skeleton's rest pose are transferred, never euler angles, so rigs that differ only in their parameter
axes get the same posed surface. Rig joints without a BVH counterpart get identity local rotations (they
follow their parent rigidly); they are listed in an :class:`UndrivenJointsWarning`, and when more than
``max_undriven`` of the rig's body joints (joints with parameters that are not hand or face joints) are
undriven the retargeting is refused (SchemaError naming the BVH): the names did not match.

The root's ``G`` becomes ``root_rotation`` (axis-angle); the root position is the BVH root position times a
scale (ratio of leg lengths, thigh + shin) mapped by ``C``, shifted vertically so the lowest foot joint over
the clip matches our rest foot height (feet stay on the ground), and horizontally so the first output frame
starts at x = z = 0 (``center_xz``).

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
from gsavatar.motion.joint_names import is_extremity, match_joints
from gsavatar.motion.resample import lerp_frames, resample_times, slerp_matrices
from gsavatar.motion.rig_pose import pose_from_local_rotations
from gsavatar.utils.errors import SchemaError

CMU_NAME_MAP: dict[str, str] = {"LeftHandFinger1": "LFingers", "RightHandFinger1": "RFingers"}
"""Our (Anny cmu_mb) joint name -> CMU BVH joint name, where they differ (the ``cmu`` convention of
:mod:`gsavatar.motion.joint_names` knows both, so matching needs no map)."""

MAX_UNDRIVEN = 0.5
"""Largest fraction of a rig's body joints (joints with parameters, hand and face joints excepted) that may be
driven by no motion joint; more is refused (the names did not match: pass a joint map)."""

_FOOT_JOINTS = ("left_ankle", "right_ankle", "left_foot", "right_foot")
"""Canonical names of the joints whose lowest point over a clip is put on our rest foot height."""


class UndrivenJointsWarning(UserWarning):
    """Rig joints that no motion joint drives (they keep their rest rotation relative to their parent)."""


class RetargetedMotion(NamedTuple):
    pose: np.ndarray
    """Pose vector per frame, radians (rig param order).  # [F, P] float32"""
    root_rotation: np.ndarray
    """Root rotation, axis-angle (world = R (x - head_root) + head_root + t).  # [F, 3] float32"""
    root_translation: np.ndarray
    """Root translation, metres.  # [F, 3] float32"""
    fps: float
    """Frames per second of the output."""
    undriven: tuple[str, ...] = ()
    """Rig joints with pose parameters that no BVH joint drives (identity local rotation)."""
    matched: tuple[tuple[str, str], ...] = ()
    """(rig joint, BVH joint) of every matched pair, in rig order."""


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


def _bone_pairs(
    j: int,
    children: list[list[int]],
    to_bvh: dict[int, int],
    heads: np.ndarray,
    bvh_rest: np.ndarray,
    eps_o: float,
    eps_b: float,
):
    """(our rest vector, BVH rest vector) pairs from joint j towards its nearest matched descendants.

    An unmatched child (e.g. SMPL-X's spine2 under a Biovision skeleton's Ab -> Chest) and a child at (near)
    zero distance on either side are skipped in favour of their children.
    """
    pairs = []
    stack = list(children[j])
    while stack:
        c = stack.pop(0)
        if c not in to_bvh:
            stack.extend(children[c])
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
    for side in ("left", "right"):
        chain = [f"{side}_hip", f"{side}_knee", f"{side}_ankle"]  # canonical: thigh + shin
        if all(c in idx for c in chain):
            p = points[[idx[c] for c in chain]]
            total += np.linalg.norm(p[1] - p[0]) + np.linalg.norm(p[2] - p[1])
            n += 1
    return total / n if n else None


def _check_undriven(
    rig: Rig,
    bvh: BvhMotion,
    to_bvh: dict[int, int],
    canonical: tuple[str, ...],
    root: int,
    max_undriven: float,
    conventions: tuple[str | None, str | None],
) -> tuple[str, ...]:
    """Warn about rig joints with parameters that no BVH joint drives; SchemaError(BVH) when more than
    ``max_undriven`` of the body joints among them are undriven. -> the undriven joint names."""
    with_params = sorted({rig.joint_index(p.joint) for p in rig.params} - {root})
    undriven = [j for j in with_params if j not in to_bvh]
    names = tuple(rig.joints[j].name for j in undriven)
    body = [j for j in with_params if not is_extremity(canonical[j])]
    body_undriven = [rig.joints[j].name for j in body if j not in to_bvh]
    where = (
        f"(rig names read as {conventions[0] or 'no known convention'}, BVH names as "
        f"{conventions[1] or 'no known convention'}"
    )
    if body and len(body_undriven) > max_undriven * len(body):
        raise SchemaError(
            bvh.path or "BVH",
            "joints",
            f"{len(body_undriven)} of the rig's {len(body)} body joints are driven by no BVH joint: "
            f"{body_undriven} {where}; BVH joints: {bvh.names}); map them with a joint map "
            "(--joint-map FILE, docs/import.md)",
        )
    if names:
        extra = [n for n in names if n not in body_undriven]
        warnings.warn(
            f"{bvh.path or 'BVH'}: {len(names)} of the rig's {len(with_params)} posed joints are driven by no "
            f"BVH joint and keep their rest rotation relative to their parent: body joints {body_undriven}, "
            f"hand/face joints {extra} {where})",
            UndrivenJointsWarning,
            stacklevel=3,
        )
    return names


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
    name_map: dict[str, str | None] | None = None,
    name_map_file: str | Path = "name_map",
    bvh_to_ours: np.ndarray | None = None,
    scale: float | None = None,
    center_xz: bool = True,
    max_undriven: float = MAX_UNDRIVEN,
) -> RetargetedMotion:
    """Retarget ``bvh`` onto ``rig`` (see module docstring for the method).

    rest_heads: our rest joint positions [J, 3] (default ``rig.heads()``).
    fps_out: output frame rate (default: the BVH's); resampled by slerp/lerp.
    frames: source (BVH) frames to use, e.g. ``slice(0, 400)`` (default: all).
    name_map: our joint name -> BVH joint name (or ``None``: driven by nothing) for the rig joints it lists
        (e.g. :func:`gsavatar.motion.joint_names.read_joint_map` of a user's file, named in errors by
        ``name_map_file``); the others are matched by convention (:mod:`gsavatar.motion.joint_names`).
    bvh_to_ours: 3x3 rotation from BVH axes to ours (default identity: Y up, facing +Z).
    scale: metres per BVH unit (default: our leg length / BVH leg length).
    center_xz: move the horizontal root position of the first output frame to x = z = 0.
    max_undriven: largest fraction of undriven body joints accepted (:data:`MAX_UNDRIVEN`; 1 accepts all).
    """
    heads = np.asarray(rig.heads() if rest_heads is None else rest_heads, dtype=np.float64)
    J = rig.num_joints
    if heads.shape != (J, 3):
        raise ValueError(f"rest_heads must be [{J}, 3], got {heads.shape}")
    C = np.eye(3) if bvh_to_ours is None else np.asarray(bvh_to_ours, np.float64)
    match = match_joints([jt.name for jt in rig.joints], bvh.names, name_map, name_map_file)
    to_bvh = match.rig_to_motion
    canonical = match.rig_canonical
    parents = rig.parents()
    root = int(np.flatnonzero(parents < 0)[0])
    if any(p.joint == rig.joints[root].name for p in rig.params):
        raise ValueError("the root joint must have no pose params (its motion is root_rotation)")
    if root not in to_bvh:
        raise SchemaError(
            bvh.path or "BVH",
            "joints",
            f"the rig root {rig.joints[root].name!r} has no BVH joint "
            f"(BVH joints: {bvh.names}); map it with a joint map (--joint-map FILE)",
        )
    undriven = _check_undriven(
        rig, bvh, to_bvh, canonical, root, max_undriven, (match.rig_convention, match.motion_convention)
    )

    # --- scale: ratio of leg lengths ----------------------------------------------------
    bvh_rest = bvh_rest_positions(bvh)
    if scale is None:  # over matched legs only, by canonical name
        ours_idx = {canonical[j]: j for j in to_bvh}
        bvh_named = {canonical[j]: b for j, b in to_bvh.items()}
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
    feet = [j for j in range(J) if canonical[j] in _FOOT_JOINTS and j in to_bvh]
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

    # --- pack ---------------------------------------------------------------------------
    pose = pose_from_local_rotations(L, rig)
    moving = [
        rig.joints[j].name for j in to_bvh if j != root and not any(p.joint == rig.joints[j].name for p in rig.params)
    ]
    if moving:
        warnings.warn(f"joints without pose params keep their rest orientation: {moving}", stacklevel=2)
    root_rot = Rotation.from_matrix(L[:, root]).as_rotvec()
    # translation t with world_root_head = head_root + t
    root_trans = root_pos - heads[root]
    return RetargetedMotion(
        pose=pose.astype(np.float32),
        root_rotation=root_rot.astype(np.float32),
        root_translation=root_trans.astype(np.float32),
        fps=fps,
        undriven=undriven,
        matched=tuple((rig.joints[j].name, bvh.names[b]) for j, b in sorted(to_bvh.items())),
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
    :func:`retarget_bvh` (``name_map``, ``name_map_file``, ``bvh_to_ours``, ``scale``, ``center_xz``,
    ``max_undriven``).
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
        m = m._replace(
            pose=m.pose[:count], root_rotation=m.root_rotation[:count], root_translation=m.root_translation[:count]
        )
    return m
