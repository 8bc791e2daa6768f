"""Forward kinematics and linear blend skinning (vectorised torch, batched over frames).

Frames: ``posed_from_rest`` transforms map a rest-pose (template) point to its posed
world position. Root motion: ``world = R_root (x - head_root) + head_root + t_root``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import numpy as np
import torch
from torch import Tensor

from gsavatar.geometry.rotations import axis_angle_to_matrix


class RigParam(Protocol):
    """One pose parameter of a rig (:class:`gsavatar.data_schema.rig.PoseParam` has this shape)."""

    joint: str
    kind: str  # "euler" (one angle about ``axis``) or "axis_angle" (three slots)
    axis: Sequence[float]  # [3] unit axis of an euler parameter
    size: int  # pose slots: 1 (euler) or 3 (axis_angle)


class Rig(Protocol):
    """What the kinematics below read from a rig. :class:`gsavatar.data_schema.rig.Rig` is one; geometry sits
    below data_schema (docs/architecture.md), so it names the shape it needs instead of importing the type."""

    params: Sequence[RigParam]
    num_joints: int
    pose_dim: int

    def heads(self) -> np.ndarray: ...  # [J, 3] rest joint positions, metres

    def parents(self) -> np.ndarray: ...  # [J] int, -1 for the root

    def joint_index(self, name: str) -> int: ...


class ChainParam(NamedTuple):
    """One pose parameter of a :class:`KinematicChain` (the :class:`RigParam` shape)."""

    joint: str
    kind: str
    axis: tuple[float, float, float]
    size: int


class KinematicChain:
    """A rig's kinematics as plain arrays (what forward kinematics needs, no names), so a model can keep them
    as buffers and rebuild the chain from a checkpoint alone. Implements :class:`Rig`; joints are named by
    their index.

    Args:
        heads: rest joint positions, metres.  # [J, 3]
        parents: parent per joint, -1 for the root (parents before children).  # [J]
        param_joint: joint index of every pose parameter, in pose-vector order.  # [M]
        param_axis: unit euler axis of every parameter (zeros for axis-angle ones).  # [M, 3]
        param_size: pose slots of every parameter: 1 (euler) or 3 (axis-angle).  # [M]
    """

    def __init__(self, heads, parents, param_joint, param_axis, param_size) -> None:
        as_np = lambda a: a.detach().cpu().numpy() if isinstance(a, Tensor) else np.asarray(a)  # noqa: E731
        self._heads = as_np(heads).astype(np.float32).reshape(-1, 3)
        self._parents = as_np(parents).astype(np.int64).reshape(-1)
        joint, axis, size = (
            as_np(param_joint).astype(np.int64).reshape(-1),
            as_np(param_axis).astype(np.float64).reshape(-1, 3),
            as_np(param_size).astype(np.int64).reshape(-1),
        )
        J = len(self._heads)
        if len(self._parents) != J or not (len(joint) == len(axis) == len(size)):
            raise ValueError(
                f"kinematic chain: {J} heads, {len(self._parents)} parents, {len(joint)}/{len(axis)}/"
                f"{len(size)} parameter joints/axes/sizes: lengths must agree"
            )
        if np.any(self._parents >= np.arange(J)) or np.any(self._parents < -1):
            raise ValueError("kinematic chain: parents must come before their children (-1 for a root)")
        if np.any((joint < 0) | (joint >= J)) or not np.all(np.isin(size, (1, 3))):
            raise ValueError("kinematic chain: parameter joints must index the joints and sizes be 1 or 3")
        self.params = [
            ChainParam(str(int(j)), "euler" if s == 1 else "axis_angle", tuple(a), int(s))
            for j, a, s in zip(joint, axis, size)
        ]
        self.num_joints, self.pose_dim = J, int(size.sum())

    @classmethod
    def from_rig(cls, rig: Rig) -> "KinematicChain":
        joint = [rig.joint_index(p.joint) for p in rig.params]
        axis = [tuple(p.axis) if p.kind == "euler" else (0.0, 0.0, 0.0) for p in rig.params]
        return cls(rig.heads(), rig.parents(), joint, axis, [p.size for p in rig.params])

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(heads, parents, param_joint, param_axis, param_size)``, the constructor's arguments."""
        return (
            self._heads.copy(),
            self._parents.copy(),
            np.array([int(p.joint) for p in self.params], np.int64),
            np.array([p.axis for p in self.params], np.float32).reshape(-1, 3),
            np.array([p.size for p in self.params], np.int64),
        )

    def heads(self) -> np.ndarray:
        return self._heads

    def parents(self) -> np.ndarray:
        return self._parents

    def joint_index(self, name: str) -> int:
        return int(name)


class RigTensors:
    """A rig's constant arrays as tensors, built once and reused every frame."""

    def __init__(self, rig: Rig, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> None:
        self.heads = torch.as_tensor(rig.heads(), dtype=dtype, device=device)  # [J, 3]
        self.parents = rig.parents().tolist()  # len J, -1 for root
        self.num_joints = rig.num_joints
        self.pose_dim = rig.pose_dim
        # Per pose slot: joint index, euler axis (zero for axis-angle slots) and, for
        # axis-angle triplets, the slot index of their first component.
        axes, aa_starts, eul_slots, eul_joints = [], [], [], []
        slot = 0
        order: list[tuple[int, str, int]] = []  # (joint, kind, slot) in listed order
        for p in rig.params:
            j = rig.joint_index(p.joint)
            order.append((j, p.kind, slot))
            if p.kind == "euler":
                axes.append(p.axis)
                eul_slots.append(slot)
                eul_joints.append(j)
            else:
                aa_starts.append(slot)
            slot += p.size
        self.order = order
        self.euler_slots = torch.as_tensor(eul_slots, dtype=torch.long, device=device)
        self.euler_axes = torch.as_tensor(np.array(axes, dtype=np.float64).reshape(-1, 3), dtype=dtype, device=device)
        # Batched composition (pose_to_local_rotations): the factors are computed euler first, then axis-angle;
        # round r multiplies the r-th factor (listed order) of every joint that has one into that joint.
        aa_slots = np.array(aa_starts, np.int64).reshape(-1, 1) + np.arange(3)
        self.aa_slots = torch.as_tensor(aa_slots, dtype=torch.long, device=device)  # [n_aa, 3]
        per_joint, e, a = [[] for _ in range(self.num_joints)], 0, len(eul_slots)  # factor indices of each joint
        for j, kind, _ in order:
            per_joint[j].append(e if kind == "euler" else a)
            e, a = (e + 1, a) if kind == "euler" else (e, a + 1)
        rounds = max((len(f) for f in per_joint), default=0)
        self.rounds = [
            (
                torch.as_tensor([j for j, f in enumerate(per_joint) if len(f) > r], dtype=torch.long, device=device),
                torch.as_tensor([f[r] for f in per_joint if len(f) > r], dtype=torch.long, device=device),
            )
            for r in range(rounds)
        ]  # [(joints [n_r], factors [n_r])]
        # forward kinematics by depth: every joint of one depth at once, from its parent one depth up
        self.levels = [(j.to(device), p.to(device)) for j, p in _depth_levels(self.parents)]


def pose_to_local_rotations(pose: Tensor, rig: Rig | RigTensors) -> Tensor:
    """Joint-local rotations from the pose vector.

    pose: [B, P] radians (rig order) -> [B, J, 3, 3]; joints without parameters get identity.
    Every factor (euler and axis-angle) in two batched Rodrigues calls, then one batched product per factor rank
    (a joint's factors multiply in listed order; the per-parameter loop is the reference in tests/geometry/).
    """
    rt = rig if isinstance(rig, RigTensors) else RigTensors(rig, pose.device, pose.dtype)
    if pose.ndim != 2 or pose.shape[1] != rt.pose_dim:
        raise ValueError(f"pose must be [B, {rt.pose_dim}], got {tuple(pose.shape)}")
    B = pose.shape[0]
    dev = pose.device
    factors = []
    if len(rt.euler_slots):
        factors.append(axis_angle_to_matrix(rt.euler_axes.to(pose)[None] * pose[:, rt.euler_slots.to(dev), None]))
    if len(rt.aa_slots):
        factors.append(axis_angle_to_matrix(pose[:, rt.aa_slots.to(dev)]))  # [B, n_aa, 3, 3]
    local = torch.eye(3, dtype=pose.dtype, device=dev).expand(B, rt.num_joints, 3, 3)
    if not factors:
        return local.clone()
    R = torch.cat(factors, 1)  # [B, n_factors, 3, 3]: euler, then axis-angle
    for r, (joints, idx) in enumerate(rt.rounds):
        joints, idx = joints.to(dev), idx.to(dev)
        value = R[:, idx] if r == 0 else local[:, joints] @ R[:, idx]
        local = local.index_copy(1, joints, value)
    return local


def forward_kinematics(local_rot: Tensor, heads: Tensor, parents: list[int] | np.ndarray, levels=None) -> Tensor:
    """Per-joint skinning transforms ``posed_from_rest`` (root fixed at its rest head).

    local_rot: [B, J, 3, 3]; heads: [J, 3] rest joint positions; parents: len J (-1 root);
    ``levels``: :attr:`RigTensors.levels` (built from ``parents`` when None): the joints of one depth are posed at
    once from their parents' (the per-joint loop is the reference in tests/geometry/)
    -> [B, J, 4, 4]
    """
    B, J = local_rot.shape[:2]
    dev = local_rot.device
    if levels is None:
        levels = _depth_levels(parents)
    offsets = heads - heads[torch.as_tensor([max(int(p), 0) for p in parents], dtype=torch.long, device=dev)]
    rots = local_rot  # joints of depth 0 keep their local rotation
    pos = heads.expand(B, J, 3)  # and their rest head
    for joints, par in levels[1:]:
        joints, par = joints.to(dev), par.to(dev)
        Rp = rots[:, par]  # [B, n, 3, 3]
        rots = rots.index_copy(1, joints, Rp @ local_rot[:, joints])
        pos = pos.index_copy(1, joints, pos[:, par] + (Rp @ offsets[joints, :, None])[..., 0])
    t = pos - (rots @ heads[None, :, :, None])[..., 0]  # posed = R x + t maps rest head -> posed head
    T = torch.zeros(B, J, 4, 4, dtype=local_rot.dtype, device=dev)
    T[..., :3, :3] = rots
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def _depth_levels(parents) -> list[tuple[Tensor, Tensor]]:
    """``[(joints of depth d, their parents)]`` for d = 0, 1, ... (parents listed before their children)."""
    parents = np.asarray(list(map(int, parents)), np.int64)
    depth = np.zeros(len(parents), np.int64)
    for j, p in enumerate(parents):
        if p >= j:
            raise ValueError("forward_kinematics: parents must come before their children (-1 for a root)")
        depth[j] = 0 if p < 0 else depth[p] + 1
    top = int(depth.max()) + 1 if len(parents) else 0
    return [(torch.as_tensor(np.flatnonzero(depth == d)), torch.as_tensor(parents[depth == d])) for d in range(top)]


def root_transform(root_rotation: Tensor, root_translation: Tensor, root_head: Tensor) -> Tensor:
    """``world_from_skeleton`` for the root motion. [B,3], [B,3], [3] -> [B, 4, 4]."""
    R = axis_angle_to_matrix(root_rotation)
    t = root_head + root_translation - (R @ root_head[:, None])[..., 0]
    T = torch.zeros(R.shape[0], 4, 4, dtype=R.dtype, device=R.device)
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def skinning_transforms(rig: Rig | RigTensors, pose: Tensor, root_rotation: Tensor, root_translation: Tensor) -> Tensor:
    """World ``posed_from_rest`` per joint incl. root motion. [B,P],[B,3],[B,3] -> [B, J, 4, 4]."""
    rt = rig if isinstance(rig, RigTensors) else RigTensors(rig, pose.device, pose.dtype)
    heads = rt.heads.to(pose.dtype)
    T = forward_kinematics(pose_to_local_rotations(pose, rt), heads, rt.parents, rt.levels)
    root = root_transform(root_rotation, root_translation, heads[0])
    return root[:, None] @ T


def pose_joints(rig: Rig | RigTensors, pose: Tensor, root_rotation: Tensor, root_translation: Tensor) -> Tensor:
    """Posed world joint positions. -> [B, J, 3]"""
    rt = rig if isinstance(rig, RigTensors) else RigTensors(rig, pose.device, pose.dtype)
    T = skinning_transforms(rt, pose, root_rotation, root_translation)
    h = rt.heads.to(pose.dtype)
    return (T[..., :3, :3] @ h[None, :, :, None])[..., 0] + T[..., :3, 3]


def blend_transforms(transforms: Tensor, skin_indices: Tensor, skin_weights: Tensor) -> Tensor:
    """Per-point blended 4x4 (LBS). transforms [B,J,4,4], indices/weights [N,K] -> [B, N, 4, 4]."""
    return torch.einsum("nk,bnkij->bnij", skin_weights.to(transforms.dtype), transforms[:, skin_indices])


def lbs(points: Tensor, skin_indices: Tensor, skin_weights: Tensor, transforms: Tensor) -> Tensor:
    """Linear blend skinning of rest points.

    points: [N, 3] rest positions; skin_indices: [N, K] long; skin_weights: [N, K];
    transforms: [B, J, 4, 4] posed_from_rest -> [B, N, 3] posed positions.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {tuple(points.shape)}")
    if skin_indices.shape != skin_weights.shape or skin_indices.shape[0] != points.shape[0]:
        raise ValueError(
            f"skin_indices/skin_weights must both be [N={points.shape[0]}, K], "
            f"got {tuple(skin_indices.shape)} and {tuple(skin_weights.shape)}"
        )
    # Blend only the 3x4 affine rows: [B, N, 3, 4], avoids materialising [B, N, K, 4, 4] twice.
    A = torch.einsum("nk,bnkij->bnij", skin_weights.to(transforms.dtype), transforms[:, skin_indices.long(), :3, :])
    return (A[..., :3] @ points[None, :, :, None].to(A.dtype))[..., 0] + A[..., 3]


def barycentric_interpolate(values: np.ndarray | Tensor, faces, face_idx, bary):
    """Transfer per-vertex values to surface points.
    values [V, ...], faces [F,3], face_idx [N], bary [N,3] -> [N, ...]."""
    corners = values[faces[face_idx]]  # [N, 3, ...]
    shape = (bary.shape[0], 3) + (1,) * (corners.ndim - 2)
    return (corners * bary.reshape(shape)).sum(1)
