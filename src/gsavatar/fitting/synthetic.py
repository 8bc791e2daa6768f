"""Keypoints a detector would give on a capture whose true joints are known: the true joints projected,
with pixel noise, outliers and dropped detections (the fit's ground-truth check, docs/fit_body.md)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gsavatar.fitting.keypoints import BODY25_PARTS, FORMATS, JointMap
from gsavatar.fitting.triangulate import project_world


def synthetic_keypoints(
    points: np.ndarray,
    cameras: list,
    joint_map: JointMap,
    noise_px: float = 2.0,
    outlier_fraction: float = 0.1,
    drop_fraction: float = 0.2,
    seed: int = 0,
) -> np.ndarray:
    """points [F, M, 3]: world positions of the map's keypoints (:func:`gsavatar.fitting.fit.posed_keypoints`)
    -> keypoints [F, C, K, 3] of ``joint_map.format``: the points projected
    with Gaussian noise of ``noise_px`` (per axis), ``outlier_fraction`` of the detections moved to a uniform
    random spot in the image (confidence kept high: a detector's confident mistake), ``drop_fraction``
    dropped (confidence 0); the rest get confidences in [0.6, 1]. Unmapped keypoints stay 0."""
    rng = np.random.default_rng(seed)
    F, C, K = points.shape[0], len(cameras), FORMATS[joint_map.format]
    out = np.zeros((F, C, K, 3))
    pix, z = project_world(points.reshape(-1, 3), cameras)  # [F*M, C, 2]
    M = len(joint_map.joints)
    pix = pix.reshape(F, M, C, 2).transpose(0, 2, 1, 3) + rng.normal(0, noise_px, (F, C, M, 2))
    conf = rng.uniform(0.6, 1.0, (F, C, M))
    sizes = np.array([[c.width, c.height] for c in cameras], np.float64)  # [C, 2]
    r = rng.uniform(size=(F, C, M))
    outl = r < outlier_fraction
    pix[outl] = (rng.uniform(size=(F, C, M, 2)) * sizes[None, :, None])[outl]
    drop = (r >= outlier_fraction) & (r < outlier_fraction + drop_fraction)
    inside = (pix >= 0).all(-1) & (pix <= sizes[None, :, None]).all(-1) & (z.reshape(F, M, C).transpose(0, 2, 1) > 0)
    conf[drop | ~inside] = 0.0
    out[:, :, joint_map.keypoints, :2] = pix
    out[:, :, joint_map.keypoints, 2] = conf
    return out


def write_openpose(root: str | Path, keypoints: np.ndarray, cameras: list[str], frames: list[int]) -> None:
    """keypoints [F, C, 137, 3] (or [F, C, 25, 3]: body only) -> ``root/<camera>/<frame:08d>_keypoints.json``
    (OpenPose BODY_25 files; the hand and face arrays are written when any of their keypoints is detected, as
    OpenPose writes them with ``--hand`` / ``--face``; a view without any detection gets ``"people": []``)."""
    root = Path(root)
    for c, cam in enumerate(cameras):
        (root / cam).mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(frames):
            a = keypoints[i, c]
            person: dict = {"person_id": [-1]}
            start = 0
            for key, n in BODY25_PARTS:
                part = a[start : start + n]
                start += n
                if key == "pose_keypoints_2d" or (len(part) == n and (part[:, 2] > 0).any()):
                    person[key] = part.reshape(-1).tolist()
            people = [] if not (a[:, 2] > 0).any() else [person]
            (root / cam / f"{f:08d}_keypoints.json").write_text(json.dumps({"version": 1.3, "people": people}))


def write_coco_wholebody(root: str | Path, keypoints: np.ndarray, cameras: list[str], frames: list[int]) -> None:
    """keypoints [F, C, 133, 3] -> ``root/<camera>/<frame:08d>.json`` in MMPose's prediction layout (a list of
    instances with ``keypoints`` [[x, y]] and ``keypoint_scores``; a view without detections gets ``[]``)."""
    root = Path(root)
    for c, cam in enumerate(cameras):
        (root / cam).mkdir(parents=True, exist_ok=True)
        for i, f in enumerate(frames):
            a = keypoints[i, c]
            inst = (
                []
                if not (a[:, 2] > 0).any()
                else [{"keypoints": a[:, :2].tolist(), "keypoint_scores": a[:, 2].tolist()}]
            )
            (root / cam / f"{f:08d}.json").write_text(json.dumps(inst))
