"""Small synthetic template/rig fixtures for the prep tests (a capped-free cylinder "arm").

The cylinder runs along +x from x=-0.2 to x=1.0 (radius 0.05). Joints (heads on the
axis): Hips (x=-0.3, root, nothing skinned to it) -> Spine (x=-0.2) -> LeftArm (x=0)
-> LeftForeArm (x=0.4) -> LeftHand (x=0.7) -> LeftFinger (x=0.85).
Vertices are skinned to the bone whose segment they lie on, blended linearly with the
neighbouring bone within ±``blend`` of a joint. UVs: u = angle / 2π (seam duplicated,
per-corner UVs), v = (x + 0.2) / 1.2.
"""

from __future__ import annotations

import numpy as np

from gsavatar.data_schema.rig import Rig, rig_from_json
from gsavatar.data_schema.template import Template

JOINT_X = {"Hips": -0.3, "Spine": -0.2, "LeftArm": 0.0, "LeftForeArm": 0.4, "LeftHand": 0.7, "LeftFinger": 0.85}
X0, X1, RADIUS = -0.2, 1.0, 0.05


def arm_rig() -> Rig:
    names = list(JOINT_X)
    joints = [
        {"name": n, "parent": names[i - 1] if i else None, "head": [JOINT_X[n], 0.0, 0.0]} for i, n in enumerate(names)
    ]
    axes = {"rx": [1, 0, 0], "ry": [0, 1, 0], "rz": [0, 0, 1]}
    params = []
    for n in ("Spine", "LeftArm", "LeftHand", "LeftFinger"):
        for a, ax in axes.items():
            params.append({"name": f"{n}.{a}", "joint": n, "kind": "euler", "axis": ax})
    params.insert(6, {"name": "LeftForeArm.r", "joint": "LeftForeArm", "kind": "axis_angle"})
    groups = {
        "torso_head": [p["name"] for p in params if p["joint"] == "Spine"],
        "left_arm": [p["name"] for p in params if p["joint"] in ("LeftArm", "LeftForeArm")],
        "left_hand": [p["name"] for p in params if p["joint"] in ("LeftHand", "LeftFinger")],
    }
    return rig_from_json({"joints": joints, "pose_params": params, "groups": groups})


def body_rig() -> Rig:
    """A rig touching all 7 groups (for PCA tests); geometry irrelevant. P = 3+6+... slots."""
    joints = [{"name": "Hips", "parent": None, "head": [0, 0, 0]}]
    params, groups = [], {}
    sizes = {
        "torso_head": 4,
        "left_leg": 3,
        "right_leg": 3,
        "left_arm": 4,
        "right_arm": 4,
        "left_hand": 9,
        "right_hand": 9,
    }
    for g, n in sizes.items():
        j = f"{g}_j"
        joints.append({"name": j, "parent": "Hips", "head": [0, 0, 0]})
        names = []
        k = 0
        while k < n:
            if n - k >= 3 and k % 2 == 1:
                params.append({"name": f"{j}.aa{k}", "joint": j, "kind": "axis_angle"})
                k += 3
            else:
                params.append({"name": f"{j}.e{k}", "joint": j, "kind": "euler", "axis": [0, 0, 1]})
                k += 1
            names.append(params[-1]["name"])
        groups[g] = names
    return rig_from_json({"joints": joints, "pose_params": params, "groups": groups})


def arm_template(n_theta: int = 24, n_x: int = 61, blend: float = 0.05, k: int = 4) -> Template:
    rig = arm_rig()
    xs = np.linspace(X0, X1, n_x)
    th = 2 * np.pi * np.arange(n_theta) / n_theta
    V = np.stack(
        [np.repeat(xs, n_theta), RADIUS * np.tile(np.cos(th), n_x), RADIUS * np.tile(np.sin(th), n_x)], axis=1
    ).astype(np.float32)
    faces, fuv = [], []
    uv = np.stack(np.meshgrid(np.arange(n_theta + 1) / n_theta, (xs - X0) / (X1 - X0), indexing="xy"), -1).reshape(
        -1, 2
    )
    for i in range(n_x - 1):
        for t in range(n_theta):
            a, b = i * n_theta + t, i * n_theta + (t + 1) % n_theta
            c, d = a + n_theta, b + n_theta
            ua, ub = i * (n_theta + 1) + t, i * (n_theta + 1) + t + 1
            uc, ud = ua + n_theta + 1, ub + n_theta + 1
            faces += [[a, b, c], [b, d, c]]  # outward-facing
            fuv += [[ua, ub, uc], [ub, ud, uc]]
    # skin weights along x
    bones = ["Spine", "LeftArm", "LeftForeArm", "LeftHand", "LeftFinger"]
    starts = np.array([JOINT_X[b] for b in bones])
    W = np.zeros((len(V), rig.num_joints))
    for vi, x in enumerate(V[:, 0]):
        bi = int(np.clip(np.searchsorted(starts, x, side="right") - 1, 0, len(bones) - 1))
        W[vi, rig.joint_index(bones[bi])] = 1.0
        # blend with the previous bone near this bone's head, and the next bone near its end
        if bi > 0 and x - starts[bi] < blend:
            t = 0.5 + 0.5 * (x - starts[bi]) / blend
            W[vi] *= t
            W[vi, rig.joint_index(bones[bi - 1])] += 1 - t
        if bi + 1 < len(bones) and starts[bi + 1] - x < blend:
            t = 0.5 + 0.5 * (starts[bi + 1] - x) / blend
            W[vi] *= t
            W[vi, rig.joint_index(bones[bi + 1])] += 1 - t
    idx = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, idx, 1)
    w /= w.sum(1, keepdims=True)
    mask = np.zeros((32, 16), bool)
    mask[:8, :8] = True  # v in (0.75, 1], u in [0, 0.5)
    return Template(
        vertices=V,
        faces=np.array(faces, np.int64),
        skin_indices=idx.astype(np.int32),
        skin_weights=w.astype(np.float32),
        uvs=uv.astype(np.float32),
        face_uvs=np.array(fuv, np.int64),
        face_uv_mask=mask,
    )


def randomize_bases(avatar, seed: int = 5, std: float = 0.05) -> None:
    """Give a GaussianAvatar non-zero corrective bases (they start at zero), so its outputs depend on the
    MLP coefficients. Biases and MLP weights are left as they are."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in avatar.named_parameters():
            if not name.startswith("pose_head.mlp") and not name.endswith("_bias"):
                p.copy_(torch.randn(p.shape, generator=g) * std)


def arm_avatar_inputs(
    n_anchors: int = 24,
    n_control: int = 120,
    n_gaussians: int = 800,
    min_candidates: int = 2000,
    n_poses: int = 60,
    constant_torso: bool = False,
):
    """What a GaussianAvatar is built from, on the arm rig and template: (rig, hierarchy, localization masks,
    local pose PCA (2 components), global pose PCA (3)). ``constant_torso``: the first three pose slots are
    held at 0.1 in the PCA's training poses (a constant group)."""
    from gsavatar.prep.localize import build_localization
    from gsavatar.prep.pca import fit_pose_pca
    from gsavatar.prep.sample_points import build_hierarchy

    rig = arm_rig()
    t = arm_template()
    h = build_hierarchy(
        t, n_anchors=n_anchors, n_control=n_control, n_gaussians=n_gaussians, seed=0, min_candidates=min_candidates
    )
    masks = build_localization(h, rig, t.face_uv_mask)
    poses = np.random.default_rng(0).normal(size=(n_poses, rig.pose_dim)) * 0.3
    if constant_torso:
        poses[:, :3] = 0.1
    return rig, h, masks, fit_pose_pca(poses, rig, 2, "local"), fit_pose_pca(poses, rig, 3, "global")
