"""A hand-made, tiny but valid capture (box mesh, 2-joint rig, 2 cameras, 3 frames).

Used by schema and CLI tests that must not depend on the anny body model.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gsavatar.data_schema import Camera, Motion, Split, Template, write_capture_metadata
from gsavatar.data_schema.rig import rig_from_json
from gsavatar.data_schema.template import save_template
from gsavatar.geometry.camera import look_at
from gsavatar.utils.io import write_image

RIG_JSON = {
    "joints": [
        {"name": "Hips", "parent": None, "head": [0.0, 0.0, 0.0]},
        {"name": "Spine", "parent": "Hips", "head": [0.0, 0.5, 0.0]},
    ],
    "pose_params": [
        {"name": "Spine.rz", "joint": "Spine", "kind": "euler", "axis": [0, 0, 1]},
        {"name": "Spine.ry", "joint": "Spine", "kind": "euler", "axis": [0, 1, 0]},
        {"name": "Spine.rx", "joint": "Spine", "kind": "euler", "axis": [1, 0, 0]},
    ],
    "groups": {"torso_head": ["Spine.rz", "Spine.ry", "Spine.rx"]},
}


def box_template() -> Template:
    x = np.array([-0.2, 0.2])
    y = np.array([0.0, 1.0])
    z = np.array([-0.1, 0.1])
    V = np.array([[a, b, c] for a in x for b in y for c in z], dtype=np.float32)
    F = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ],
        dtype=np.int64,
    )
    w = np.stack([1 - V[:, 1], V[:, 1]], 1).astype(np.float32)
    idx = np.tile(np.array([0, 1], dtype=np.int32), (len(V), 1))
    uv = np.array([[0.1, 0.1], [0.9, 0.1], [0.5, 0.9]], dtype=np.float32)
    return Template(V, F, idx, w, uv, np.tile(np.arange(3), (len(F), 1)), None)


def make_minimal_capture(root: Path, num_frames: int = 3, size: tuple[int, int] = (32, 24)) -> Path:
    root = Path(root)
    (root / "template").mkdir(parents=True, exist_ok=True)
    save_template(box_template(), root / "template")
    (root / "template" / "rig.json").write_text(json.dumps(RIG_JSON))
    rig_from_json(RIG_JSON)
    w, h = size
    K = np.array([[40.0, 0, w / 2], [0, 40.0, h / 2], [0, 0, 1]])
    cams = {}
    for i, ang in enumerate((0.0, 1.5)):
        eye = np.array([3 * np.sin(ang), 0.5, 3 * np.cos(ang)])
        R, T = look_at(eye, np.array([0, 0.5, 0]))
        cams[f"cam{i:02d}"] = Camera(f"cam{i:02d}", K, R, T, np.zeros(5), w, h)
    splits = {"train": Split(list(range(num_frames - 1)), ["cam00"]), "test": Split([num_frames - 1], ["cam01"])}
    write_capture_metadata(root, 30.0, num_frames, cams, splits)
    rng = np.random.default_rng(0)
    Motion(
        rng.normal(0, 0.1, (num_frames, 3)).astype(np.float32),
        np.zeros((num_frames, 3), np.float32),
        np.zeros((num_frames, 3), np.float32),
    ).save(root / "motion.npz")
    for c in cams:
        for f in range(num_frames):
            write_image(root / "images" / c / f"{f:08d}.png", rng.random((h, w, 3)))
            m = np.zeros((h, w), np.float32)
            m[4:-4, 8:-8] = 1
            write_image(root / "masks" / c / f"{f:08d}.png", m)
    return root
