"""Posing (local rotations + forward kinematics) forward and backward: the batched code against the per-joint
loops it replaced (kept below as the reference), in one run, on three rig shapes.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_posing.py [--capture out/demo/capture] [--threads 1]

Rigs: SMPL-X's 55-joint tree with one axis-angle factor per joint (``fit-body --smplx-model``), a CMU-BVH-like
31-joint tree with three euler factors per joint, and the capture's own rig when ``--capture`` is given (the
synthetic captures' anny body). Batches: 6 frames (one ``fit-body`` shape step) and 64. Prints ms per call of the
loop and the batched code, their ratio, and the largest difference of the transforms (float64).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from gsavatar.data_schema.rig import rig_from_json
from gsavatar.geometry.lbs import RigTensors, forward_kinematics, pose_to_local_rotations, root_transform
from gsavatar.geometry.rotations import axis_angle_to_matrix
from gsavatar.importers.smplx_model import SMPLX_PARENTS


def loop_local_rotations(pose: torch.Tensor, rt: RigTensors) -> torch.Tensor:
    """The per-parameter loop (gsavatar before 2026-12-07): one Rodrigues call per axis-angle parameter."""
    B = pose.shape[0]
    eul = (
        axis_angle_to_matrix(rt.euler_axes.to(pose)[None] * pose[:, rt.euler_slots, None])
        if len(rt.euler_slots)
        else None
    )
    local, k = [None] * rt.num_joints, 0
    for j, kind, slot in rt.order:
        if kind == "euler":
            R, k = eul[:, k], k + 1
        else:
            R = axis_angle_to_matrix(pose[:, slot : slot + 3])
        local[j] = R if local[j] is None else local[j] @ R
    eye = torch.eye(3, dtype=pose.dtype).expand(B, 3, 3)
    return torch.stack([eye if r is None else r for r in local], dim=1)


def loop_forward_kinematics(local_rot: torch.Tensor, heads: torch.Tensor, parents) -> torch.Tensor:
    """The per-joint loop (gsavatar before 2026-12-07)."""
    B, J = local_rot.shape[:2]
    rots, pos = [None] * J, [None] * J
    for j in range(J):
        p = int(parents[j])
        if p < 0:
            rots[j], pos[j] = local_rot[:, j], heads[j].expand(B, 3)
        else:
            rots[j] = rots[p] @ local_rot[:, j]
            pos[j] = pos[p] + (rots[p] @ (heads[j] - heads[p]))
    R, P = torch.stack(rots, 1), torch.stack(pos, 1)
    T = torch.zeros(B, J, 4, 4, dtype=local_rot.dtype)
    T[..., :3, :3], T[..., :3, 3], T[..., 3, 3] = R, P - (R @ heads[None, :, :, None])[..., 0], 1.0
    return T


def make_rig(parents, kind: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    joints = [
        {"name": f"j{j}", "parent": None if p < 0 else f"j{p}", "head": rng.normal(0, 0.2, 3).tolist()}
        for j, p in enumerate(parents)
    ]
    params = []
    for j in range(len(parents)):
        if kind == "axis_angle":
            params.append({"name": f"j{j}.aa", "joint": f"j{j}", "kind": "axis_angle"})
        else:
            for a, ax in (("rz", [0, 0, 1]), ("rx", [1, 0, 0]), ("ry", [0, 1, 0])):
                params.append({"name": f"j{j}.{a}", "joint": f"j{j}", "kind": "euler", "axis": ax})
    return rig_from_json(
        {"joints": joints, "pose_params": params, "groups": {"torso_head": [p["name"] for p in params]}}
    )


def pose_both(rt: RigTensors, pose, rr, tr, batched: bool) -> torch.Tensor:
    heads = rt.heads
    if batched:
        T = forward_kinematics(pose_to_local_rotations(pose, rt), heads, rt.parents, rt.levels)
    else:
        T = loop_forward_kinematics(loop_local_rotations(pose, rt), heads, rt.parents)
    return root_transform(rr, tr, heads[0])[:, None] @ T


def time_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    t0 = time.perf_counter()
    for _ in range(repeats):
        fn()
    return 1000 * (time.perf_counter() - t0) / repeats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", default=None, help="also time this capture's rig")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cmu_parents = [-1] + [max(0, j - 1 - (j % 5 == 0) * 3) for j in range(1, 31)]  # five short chains off a spine
    rigs = {
        "smplx (55 x axis-angle)": make_rig(SMPLX_PARENTS, "axis_angle"),
        "bvh-like (31 x 3 euler)": make_rig(cmu_parents, "euler"),
    }
    if args.capture:
        from gsavatar.data_schema import load_capture

        rig = load_capture(args.capture).rig
        rigs[f"capture ({rig.num_joints} joints, {len(rig.params)} factors)"] = rig
    print(f"threads {args.threads}, {args.repeats} repeats, forward + backward, float64")
    print(f"{'rig':<40} {'batch':>5} {'loop ms':>9} {'batched ms':>10} {'ratio':>6} {'max |dT|':>9}")
    for name, rig in rigs.items():
        rt = RigTensors(rig, dtype=torch.float64)
        for B in (6, 64):
            g = torch.Generator().manual_seed(B)
            pose = (0.5 * torch.randn(B, rig.pose_dim, generator=g, dtype=torch.float64)).requires_grad_(True)
            rr, tr = (
                0.3 * torch.randn(B, 3, generator=g, dtype=torch.float64),
                torch.randn(B, 3, generator=g, dtype=torch.float64),
            )

            def run(batched: bool) -> None:
                pose.grad = None
                pose_both(rt, pose, rr, tr, batched).square().sum().backward()

            old, new = time_ms(lambda: run(False), args.repeats), time_ms(lambda: run(True), args.repeats)
            with torch.no_grad():
                diff = float((pose_both(rt, pose, rr, tr, True) - pose_both(rt, pose, rr, tr, False)).abs().max())
            print(f"{name:<40} {B:>5} {old:>9.2f} {new:>10.2f} {old / new:>6.1f} {diff:>9.1e}")


if __name__ == "__main__":
    main()
