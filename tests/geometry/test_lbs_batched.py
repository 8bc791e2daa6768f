"""The batched local rotations and depth-level forward kinematics against the per-joint scipy loop
(:func:`geometry.test_lbs.naive_global`) on random rigs: trees of every shape, joints with zero to four factors,
euler and axis-angle factors interleaved in any listed order."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geometry.test_lbs import naive_global
from gsavatar.data_schema.rig import rig_from_json
from gsavatar.geometry.lbs import RigTensors, forward_kinematics, pose_to_local_rotations, skinning_transforms


def random_rig(seed: int, num_joints: int = 12):
    rng = np.random.default_rng(seed)
    joints = [{"name": "j0", "parent": None, "head": rng.normal(0, 0.3, 3).tolist()}]
    for j in range(1, num_joints):
        parent = int(rng.integers(0, j)) if rng.random() < 0.5 else j - 1  # bushy and chain-like branches
        joints.append({"name": f"j{j}", "parent": f"j{parent}", "head": rng.normal(0, 0.3, 3).tolist()})
    params = []
    for j in range(num_joints):
        for k in range(int(rng.integers(0, 5))):  # 0..4 factors; some joints have none
            if rng.random() < 0.4:
                params.append({"name": f"j{j}.aa{k}", "joint": f"j{j}", "kind": "axis_angle"})
            else:
                axis = rng.normal(size=3)
                params.append(
                    {
                        "name": f"j{j}.e{k}",
                        "joint": f"j{j}",
                        "kind": "euler",
                        "axis": (axis / np.linalg.norm(axis)).tolist(),
                    }
                )
    order = rng.permutation(len(params))  # listed order is not joint order
    params = [params[i] for i in order]
    groups = {"torso_head": [p["name"] for p in params]}
    return rig_from_json({"joints": joints, "pose_params": params, "groups": groups})


@pytest.mark.parametrize("seed", range(6))
def test_batched_skinning_transforms_match_the_per_joint_loop(seed):
    rig = random_rig(seed)
    rng = np.random.default_rng(100 + seed)
    B = 3
    pose, rr, rt = rng.normal(0, 0.8, (B, rig.pose_dim)), rng.normal(0, 0.5, (B, 3)), rng.normal(0, 0.3, (B, 3))
    T = skinning_transforms(rig, *(torch.from_numpy(a) for a in (pose, rr, rt))).numpy()
    for b in range(B):
        np.testing.assert_allclose(T[b], naive_global(rig, pose[b], rr[b], rt[b]), atol=1e-10, rtol=0)


def test_local_rotations_of_joints_without_factors_are_identity_and_gradients_flow():
    rig = random_rig(3)
    rt = RigTensors(rig, dtype=torch.float64)
    pose = torch.randn(2, rig.pose_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    L = pose_to_local_rotations(pose, rt)
    bare = [j for j in range(rig.num_joints) if all(rig.joint_index(p.joint) != j for p in rig.params)]
    assert bare, "the random rig should have a joint without parameters"
    torch.testing.assert_close(L[:, bare], torch.eye(3, dtype=torch.float64).expand(2, len(bare), 3, 3))
    pose.requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda p: forward_kinematics(pose_to_local_rotations(p, rt), rt.heads, rt.parents, rt.levels), (pose[:1],)
    )


def test_a_rig_without_pose_parameters_and_fk_without_levels():
    rig = rig_from_json(
        {
            "joints": [
                {"name": "a", "parent": None, "head": [0, 0, 0]},
                {"name": "b", "parent": "a", "head": [0, 1, 0]},
            ],
            "pose_params": [],
            "groups": {},
        }
    )
    L = pose_to_local_rotations(torch.zeros(4, 0, dtype=torch.float64), rig)
    torch.testing.assert_close(L, torch.eye(3, dtype=torch.float64).expand(4, 2, 3, 3))
    heads = torch.as_tensor(rig.heads(), dtype=torch.float64)
    T = forward_kinematics(L, heads, rig.parents())  # levels built from the parents
    torch.testing.assert_close(T, torch.eye(4, dtype=torch.float64).expand(4, 2, 4, 4))
