"""LBS and FK against naive per-vertex / per-joint references."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.rig import rig_from_json
from gsavatar.geometry.lbs import lbs, pose_joints, skinning_transforms
from gsavatar.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, orthonormalize

CHAIN = {
    "joints": [
        {"name": "root", "parent": None, "head": [0.0, 0.0, 0.0]},
        {"name": "a", "parent": "root", "head": [0.0, 1.0, 0.0]},
        {"name": "b", "parent": "a", "head": [1.0, 1.0, 0.0]},
        {"name": "c", "parent": "root", "head": [0.0, -1.0, 0.5]},
    ],
    "pose_params": [
        {"name": "a.rz", "joint": "a", "kind": "euler", "axis": [0, 0, 1]},
        {"name": "a.rx", "joint": "a", "kind": "euler", "axis": [1, 0, 0]},
        {"name": "b.aa", "joint": "b", "kind": "axis_angle"},
        {"name": "c.ry", "joint": "c", "kind": "euler", "axis": [0, 1, 0]},
    ],
    "groups": {"torso_head": ["a.rz", "a.rx"], "left_arm": ["b.aa"], "left_leg": ["c.ry"]},
}


def naive_global(rig, pose, rr, rt):
    """Per-joint loop with scipy rotations (float64)."""
    heads = rig.heads().astype(np.float64)
    par = rig.parents()
    local = [np.eye(3) for _ in range(rig.num_joints)]
    slot = 0
    for p in rig.params:
        j = rig.joint_index(p.joint)
        if p.kind == "euler":
            R = Rotation.from_rotvec(np.array(p.axis) * pose[slot]).as_matrix()
        else:
            R = Rotation.from_rotvec(pose[slot : slot + 3]).as_matrix()
        local[j] = local[j] @ R
        slot += p.size
    G = []
    for j in range(rig.num_joints):
        M = np.eye(4)
        M[:3, :3] = local[j]
        M[:3, 3] = heads[j] - (heads[par[j]] if par[j] >= 0 else 0)
        G.append(M if par[j] < 0 else G[par[j]] @ M)
    Rr = Rotation.from_rotvec(rr).as_matrix()
    root = np.eye(4)
    root[:3, :3] = Rr
    root[:3, 3] = heads[0] + rt - Rr @ heads[0]
    out = []
    for j in range(rig.num_joints):
        inv_rest = np.eye(4)
        inv_rest[:3, 3] = -heads[j]
        out.append(root @ G[j] @ inv_rest)
    return np.stack(out)


def test_fk_and_lbs_match_naive_reference():
    rig = rig_from_json(CHAIN)
    rng = np.random.default_rng(1)
    B = 4
    pose = rng.normal(0, 0.7, (B, rig.pose_dim))
    rr = rng.normal(0, 0.5, (B, 3))
    rt = rng.normal(0, 0.3, (B, 3))
    T = skinning_transforms(rig, *(torch.from_numpy(a) for a in (pose, rr, rt))).numpy()
    for b in range(B):
        assert np.allclose(T[b], naive_global(rig, pose[b], rr[b], rt[b]), atol=1e-10)
    # LBS: per-vertex loop reference
    V, K = 50, 3
    pts = rng.normal(0, 1, (V, 3))
    idx = rng.integers(0, rig.num_joints, (V, K))
    w = rng.random((V, K))
    w /= w.sum(1, keepdims=True)
    out = lbs(torch.from_numpy(pts), torch.from_numpy(idx), torch.from_numpy(w), torch.from_numpy(T)).numpy()
    for b in range(B):
        for v in range(V):
            M = sum(w[v, k] * T[b, idx[v, k]] for k in range(K))
            assert np.allclose(out[b, v], M[:3, :3] @ pts[v] + M[:3, 3], atol=1e-10)
    # joints land where FK says
    J = pose_joints(rig, *(torch.from_numpy(a) for a in (pose, rr, rt))).numpy()
    heads = rig.heads()
    for b in range(B):
        ref = naive_global(rig, pose[b], rr[b], rt[b])
        assert np.allclose(J[b], np.einsum("jab,jb->ja", ref[:, :3, :3], heads) + ref[:, :3, 3], atol=1e-6)


def test_rest_pose_is_identity():
    rig = rig_from_json(CHAIN)
    z = torch.zeros(2, rig.pose_dim, dtype=torch.float64)
    T = skinning_transforms(rig, z, torch.zeros(2, 3, dtype=torch.float64), torch.zeros(2, 3, dtype=torch.float64))
    assert torch.allclose(T, torch.eye(4, dtype=torch.float64).expand_as(T))


def test_rotation_round_trip_and_gradients_at_zero():
    g = torch.Generator().manual_seed(0)
    aa = torch.randn(200, 3, dtype=torch.float64, generator=g) * 0.9
    aa = aa * (aa.norm(dim=-1, keepdim=True) < 3.0)  # axis-angle is unique only below pi
    assert torch.allclose(matrix_to_axis_angle(axis_angle_to_matrix(aa)), aa, atol=1e-9)
    z = torch.zeros(3, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(z).sum().backward()
    assert torch.isfinite(z.grad).all()
    # blended rotations are shrunk; orthonormalize gives a proper rotation
    R = 0.5 * (axis_angle_to_matrix(aa[:10]) + axis_angle_to_matrix(aa[10:20]))
    Q = orthonormalize(R)
    assert torch.allclose(Q @ Q.transpose(-1, -2), torch.eye(3, dtype=torch.float64).expand_as(Q), atol=1e-9)
    assert torch.allclose(torch.det(Q), torch.ones(10, dtype=torch.float64))
