"""A fake SMPL-X model file, built at test time (no licensed data): the keys, shapes and dtypes of
``SMPLX_NEUTRAL.npz`` that ``smplx.SMPLX(..., ext="npz")`` reads, with a procedural body.

Body: one tube of ``rings x segs`` vertices per joint along its bone (to the mean of its children, leaves extended),
SMPL-X's 55-joint tree with roughly human rest heads (metres, +Y up, facing +Z, left on +X, pelvis off the origin
as in the real model, so the root convention is observable). ``J_regressor`` averages each tube's first ring (the
joint's head), weights blend a tube's joint with its parent, first child and the joints nearest in the tree
(4 per vertex unless ``influences`` says more), shape columns move and thicken tubes, expression columns move
head/jaw/eye vertices only, pose correctives are zero or random. The default has 10560 vertices: ``smplx`` reads
vertex ids up to 9929 for its extra joints.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gsavatar.importers.smplx_model import SMPLX_JOINT_NAMES, SMPLX_PARENTS

J = 55
_BODY_OFFSETS = {  # offset of each joint's head from its parent's, metres (left side; right mirrors x)
    "pelvis": (0.003, -0.35, 0.012),
    "left_hip": (0.06, -0.09, 0.0),
    "spine1": (0.0, 0.11, -0.02),
    "left_knee": (0.04, -0.38, 0.0),
    "spine2": (0.0, 0.13, 0.0),
    "left_ankle": (0.0, -0.40, -0.04),
    "spine3": (0.0, 0.05, 0.0),
    "left_foot": (0.02, -0.06, 0.12),
    "neck": (0.0, 0.22, -0.03),
    "left_collar": (0.07, 0.12, -0.01),
    "head": (0.0, 0.09, 0.05),
    "left_shoulder": (0.12, 0.03, 0.0),
    "left_elbow": (0.26, 0.0, 0.0),
    "left_wrist": (0.25, 0.0, 0.0),
    "jaw": (0.0, -0.01, 0.03),
    "left_eye": (0.03, 0.06, 0.08),
    "left_index1": (0.09, 0.005, 0.025),
    "left_middle1": (0.095, 0.005, 0.0),
    "left_pinky1": (0.075, -0.005, -0.04),
    "left_ring1": (0.085, 0.0, -0.02),
    "left_thumb1": (0.03, -0.015, 0.03),
}
_PHALANX = {"thumb": (0.025, -0.005, 0.02)}  # offsets of finger joints 2 and 3 from the previous one
HEAD_JOINTS = ("head", "jaw", "left_eye", "right_eye")


def _offset(name: str) -> np.ndarray:
    side = -1.0 if name.startswith("right_") else 1.0
    base = "left_" + name[6:] if name.startswith("right_") else name
    if base in _BODY_OFFSETS:
        o = np.array(_BODY_OFFSETS[base])
    else:  # finger joint 2 or 3
        finger = base[5:-1]
        o = np.array(_PHALANX.get(finger, (0.03, 0.0, 0.0)))
    return o * np.array([side, 1.0, 1.0])


def rest_heads() -> np.ndarray:
    """Rest joint positions of the fake body.  # [55, 3]"""
    h = np.zeros((J, 3))
    for j, (n, p) in enumerate(zip(SMPLX_JOINT_NAMES, SMPLX_PARENTS)):
        h[j] = _offset(n) + (h[p] if p >= 0 else 0.0)
    return h


def fake_smplx_arrays(
    seed: int = 0,
    shape_cols: int = 20,
    posedirs_scale: float = 0.0,
    expr_scale: float = 0.002,
    influences: int = 4,
    rings: int = 12,
    segs: int = 16,
    uv: bool = False,
) -> dict[str, np.ndarray]:
    """The arrays of a fake SMPLX_NEUTRAL.npz.

    shape_cols: columns of ``shapedirs`` (20: v1.0 layout, 10 shape + 10 expression; 400: v1.1, 300 + 100).
    posedirs_scale: std of the random pose correctives, metres per unit of ``R - I`` (0: none).
    influences: joints per vertex with non-zero weight (> 4 exercises the top-K cut).
    """
    rng = np.random.default_rng(seed)
    heads = rest_heads()
    parents = np.array(SMPLX_PARENTS)
    children = [[c for c in range(J) if parents[c] == j] for j in range(J)]
    verts, faces, tube = [], [], []
    ang = np.linspace(0, 2 * np.pi, segs, endpoint=False)
    for j in range(J):
        a = heads[j]
        b = heads[children[j]].mean(0) if children[j] else a + 0.6 * (a - heads[parents[j]])
        d = b - a
        length = np.linalg.norm(d)
        d = d / length
        u = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(d, u)
        r = np.clip(0.25 * length, 0.006, 0.07)
        base = sum(len(x) for x in verts)
        ring_t = np.linspace(0.0, 1.0, rings)
        circle = np.cos(ang)[None, :, None] * u + np.sin(ang)[None, :, None] * w  # [1, segs, 3]
        ring = a + ring_t[:, None, None] * (b - a) + r * circle
        verts.append(ring.reshape(-1, 3))
        tube += [j] * (rings * segs)
        for i in range(rings - 1):
            for k in range(segs):
                p00, p01 = base + i * segs + k, base + i * segs + (k + 1) % segs
                p10, p11 = p00 + segs, p01 + segs
                faces += [(p00, p01, p11), (p00, p11, p10)]
    v = np.concatenate(verts)
    tube = np.array(tube)
    V = len(v)
    t_along = np.tile(np.repeat(np.linspace(0.0, 1.0, rings), segs), J)

    # tree distance between joints: a vertex's extra influences are the joints nearest its own in the tree
    hops = np.full((J, J), J)
    for j in range(J):
        hops[j, j], frontier = 0, [j]
        while frontier:
            nxt = []
            for a in frontier:
                for b in ([parents[a]] if parents[a] >= 0 else []) + children[a]:
                    if hops[j, b] > hops[j, a] + 1:
                        hops[j, b] = hops[j, a] + 1
                        nxt.append(b)
            frontier = nxt
    weights = np.zeros((V, J))
    for i in range(V):
        j, t = tube[i], t_along[i]
        weights[i, j] = 1.0 + 0.1 * rng.random()
        if parents[j] >= 0:
            weights[i, parents[j]] += 0.5 * (1 - t) ** 2 + 0.01
        if children[j]:
            weights[i, children[j][0]] += 0.5 * t**2 + 0.01
        extra = influences - np.count_nonzero(weights[i])
        if extra > 0:
            near = [b for b in np.lexsort((np.arange(J), hops[j])) if weights[i, b] == 0][:extra]
            weights[i, near] = 0.02 * rng.random(len(near)) + 0.005
    weights /= weights.sum(1, keepdims=True)

    J_regressor = np.zeros((J, V))
    for j in range(J):
        first = np.flatnonzero(tube == j)[:segs]  # ring 0, centred on the head
        J_regressor[j, first] = 1.0 / segs

    S = shape_cols
    shapedirs = np.zeros((V, 3, S))
    radial = v - (J_regressor @ v)[tube]  # roughly outwards from the tube's head ring centre
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
    a = rng.normal(0, 0.004, (J, 3, S))  # per-tube translation per column
    s = rng.normal(0, 0.003, (J, S))  # per-tube thickening per column
    shapedirs += a[tube] + s[tube][:, None, :] * radial[:, :, None]
    expr = slice(300, 400) if S >= 400 else slice(10, 20)
    head = np.isin(tube, [SMPLX_JOINT_NAMES.index(n) for n in HEAD_JOINTS])
    shapedirs[:, :, expr] = 0.0
    E = expr.stop - expr.start
    shapedirs[head, :, expr] = rng.normal(0, expr_scale, (int(head.sum()), 3, E))
    posedirs = rng.normal(0, posedirs_scale, (V, 3, (J - 1) * 9)) if posedirs_scale else np.zeros((V, 3, (J - 1) * 9))

    kintree = np.stack([np.where(parents < 0, 2**32 - 1, parents), np.arange(J)]).astype(np.uint32)
    f = np.array(faces, dtype=np.int64)
    out = {
        "v_template": v.astype(np.float32),
        "f": f.astype(np.uint32),
        "shapedirs": shapedirs.astype(np.float32),
        "posedirs": posedirs.astype(np.float32),
        "J_regressor": J_regressor.astype(np.float32),
        "weights": weights.astype(np.float32),
        "kintree_table": kintree,
        "hands_componentsl": rng.normal(0, 0.3, (45, 45)).astype(np.float32),
        "hands_componentsr": rng.normal(0, 0.3, (45, 45)).astype(np.float32),
        "hands_meanl": rng.normal(0, 0.15, 45).astype(np.float32),
        "hands_meanr": rng.normal(0, 0.15, 45).astype(np.float32),
        "lmk_faces_idx": np.arange(51, dtype=np.int64),
        "lmk_bary_coords": np.full((51, 3), 1.0 / 3.0, dtype=np.float32),
        # the official file holds pickled dicts like these; gsavatar must never unpickle them
        "part2num": np.array({"pelvis": 0}, dtype=object),
    }
    if uv:
        out["vt"] = rng.random((V, 2)).astype(np.float32)
        out["ft"] = f.copy()
    return out


def write_fake_smplx(path: Path, **kw) -> Path:
    """Save :func:`fake_smplx_arrays` as an npz (uncompressed, as np.savez; pickles allowed, for ``part2num``)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **fake_smplx_arrays(**kw))
    return path


def random_fit(
    num_frames: int,
    seed: int = 1,
    num_betas: int = 10,
    num_expression: int = 10,
    expression: bool = False,
    hand_cols: int = 45,
) -> dict[str, np.ndarray]:
    """A short fit with moderate angles (as ``smpl_params.npz`` holds it), float32."""
    rng = np.random.default_rng(seed)
    F = num_frames
    f32 = lambda a: np.asarray(a, dtype=np.float32)  # noqa: E731
    return {
        "betas": f32(rng.normal(0, 1.0, (1, num_betas))),
        "global_orient": f32(rng.normal(0, 0.6, (F, 3))),
        "transl": f32(rng.normal(0, 0.5, (F, 3))),
        "body_pose": f32(rng.normal(0, 0.3, (F, 63))),
        "jaw_pose": f32(rng.normal(0, 0.15, (F, 3))),
        "leye_pose": f32(rng.normal(0, 0.1, (F, 3))),
        "reye_pose": f32(rng.normal(0, 0.1, (F, 3))),
        "left_hand_pose": f32(rng.normal(0, 0.3, (F, hand_cols))),
        "right_hand_pose": f32(rng.normal(0, 0.3, (F, hand_cols))),
        "expression": f32(rng.normal(0, 1.0, (F, num_expression)) if expression else np.zeros((F, num_expression))),
    }
