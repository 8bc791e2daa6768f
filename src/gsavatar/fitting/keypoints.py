"""Multi-view 2D keypoints in the formats detectors write, and the map from keypoints to rig joints.

Layout: ``DIR/<camera>/<frame>...json``, one file per camera and capture frame; the frame number is the
leading integer of the file name (OpenPose writes ``<image stem>_keypoints.json``, e.g.
``00000012_keypoints.json``; ``000012.json`` is read as well). Formats:

- ``body25``: OpenPose ``{"people": [{"pose_keypoints_2d": [x, y, c] * 25, ...}]}``, with the
  ``hand_left_keypoints_2d`` / ``hand_right_keypoints_2d`` (21 each) and ``face_keypoints_2d`` (70) arrays where
  OpenPose wrote them (``--hand``, ``--face``): keypoints 0-24 body, 25-45 left hand, 46-66 right hand, 67-136
  face; absent or empty arrays read as not detected (with several people, the one with the most confident body);
- ``coco_wholebody``: 133 keypoints, as MMPose / Sapiens-style tools write them: a list of instances (or
  ``{"instances": [...]}``, ``{"instance_info": [{"instances": [...]}]}``) with ``"keypoints": [[x, y], ...]``
  and ``"keypoint_scores": [...]``, or COCO ``{"annotations": [{"keypoints": [x, y, v] * 17, "foot_kpts",
  "face_kpts", "lefthand_kpts", "righthand_kpts"}]}``.

With several people in a view the one with the largest summed confidence is taken. Pixel coordinates are
those of the capture's (distorted) images; confidence 0 means "not detected".

The keypoint -> joint map (:func:`load_joint_map`) is package data per format (``fitting/maps/``), each
keypoint naming the rig joints it stands for, first match wins (CMU / anny names, then SMPL-X); a JSON
file of the same form overrides it, and so does a packaged map named by its stem (:func:`packaged_joint_maps`:
``body25_hands`` adds OpenPose's hand points to ``body25``).
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Literal

import numpy as np

from gsavatar.utils.errors import SchemaError

KeypointFormat = Literal["body25", "coco_wholebody"]
BODY25_PARTS = (
    ("pose_keypoints_2d", 25),
    ("hand_left_keypoints_2d", 21),
    ("hand_right_keypoints_2d", 21),
    ("face_keypoints_2d", 70),
)
"""An OpenPose person's arrays in the order :func:`read_keypoints` concatenates them (only the first is required)."""
FORMATS: dict[str, int] = {"body25": sum(n for _, n in BODY25_PARTS), "coco_wholebody": 133}
"""Keypoints per person of each format (body25: body, hands and face, 137)."""
MAP_SIZES: dict[str, tuple[int, ...]] = {"body25": (25, FORMATS["body25"]), "coco_wholebody": (133,)}
"""Lengths a joint map's ``names`` may have: a body25 map may list the 25 body keypoints only."""
_COCO_PARTS = (("keypoints", 17), ("foot_kpts", 6), ("face_kpts", 68), ("lefthand_kpts", 21), ("righthand_kpts", 21))


@dataclass(frozen=True)
class JointMap:
    """Which keypoints the fit uses and the rig joint each stands for."""

    format: str
    keypoints: np.ndarray
    """Keypoint indices into the format's list.  # [M] int64"""
    joints: np.ndarray
    """Rig joint index of each.  # [M] int64"""
    names: tuple[str, ...]
    """Keypoint names (for reports)."""
    offsets: np.ndarray | None = None
    """Rest-pose offset of each keypoint's point from its joint's head, metres; the point moves rigidly with
    the joint (0 for a keypoint that is the joint itself; None: all 0).  # [M, 3] float64"""

    def rest_offsets(self) -> np.ndarray:
        """``offsets`` with None as zeros.  # [M, 3]"""
        return np.zeros((len(self.joints), 3)) if self.offsets is None else self.offsets


EXTREMES = ("+x", "-x", "+y", "-y", "+z", "-z", "bone")
"""How a marker keypoint picks its template point among the vertices skinned mostly to its joint: the one
farthest along a template axis (+Y up, facing +Z, left on +X), or along the joint's bone (parent head -> head)."""


def marker_offset(rig, template, joint: int, extreme: str) -> np.ndarray:
    """Rest offset [3] from ``joint``'s head to the template vertex (dominantly skinned to it) that is farthest
    along ``extreme`` (:data:`EXTREMES`); e.g. the nose is the Head's most forward vertex."""
    V = np.asarray(template.vertices, np.float64)
    si, sw = np.asarray(template.skin_indices), np.asarray(template.skin_weights)
    own = si[np.arange(len(si)), sw.argmax(1)] == joint
    if not own.any():
        raise ValueError(f"no template vertex is skinned mostly to joint {rig.joints[joint].name!r}")
    head = rig.heads()[joint].astype(np.float64)
    if extreme == "bone":
        parent = int(rig.parents()[joint])
        axis = head - (rig.heads()[parent] if parent >= 0 else head - np.array([0.0, 1.0, 0.0]))
    else:
        axis = np.zeros(3)
        axis["xyz".index(extreme[1])] = 1.0 if extreme[0] == "+" else -1.0
    axis = axis / max(np.linalg.norm(axis), 1e-12)
    pts = V[own]
    return pts[np.argmax((pts - head) @ axis)] - head


def packaged_joint_maps() -> tuple[str, ...]:
    """Names of the keypoint -> joint maps shipped in ``gsavatar/fitting/maps`` (a format's default map is
    named after the format), e.g. ``("body25", "body25_hands", "coco_wholebody")``."""
    maps = resources.files("gsavatar.fitting").joinpath("maps")
    return tuple(sorted(p.name[: -len(".json")] for p in maps.iterdir() if p.name.endswith(".json")))


def load_joint_map(fmt: str, rig, path: str | Path | None = None, template=None) -> JointMap:
    """The keypoint -> joint map of ``fmt`` for ``rig`` (package data, or the JSON file ``path``; a ``path``
    that is no file but the name of a packaged map, :func:`packaged_joint_maps`, reads that map).

    File: ``{"format", "num_keypoints", "names": [...], "joints": {keypoint name: entry}}``; an entry is a
    list of rig joint candidates (the keypoint is that joint), or ``{"joints": [...], "extreme": "+z"}``: a
    marker on the template, its point chosen by :func:`marker_offset` (needs ``template``; without one markers
    are left out). A keypoint whose candidates the rig lacks is left out; fewer than 4 usable keypoints is an
    error.
    """
    src = Path(path) if path is not None else None
    packaged = src is None or (not src.exists() and str(src) in packaged_joint_maps())
    name = fmt if src is None else str(src)
    try:
        text = resources.files("gsavatar.fitting").joinpath("maps", f"{name}.json").read_text() if packaged else None
        text = src.read_text() if text is None else text
        obj = json.loads(text)
    except FileNotFoundError:
        raise SchemaError(
            src or fmt, "", f"joint map file not found (packaged maps by name: {', '.join(packaged_joint_maps())})"
        ) from None
    except (IsADirectoryError, PermissionError) as e:
        raise SchemaError(src or fmt, "", f"joint map cannot be read: {e.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SchemaError(src or fmt, "", f"not valid JSON: {e}") from None
    where = f"gsavatar/fitting/maps/{name}.json" if packaged else src
    if not isinstance(obj, dict) or not isinstance(obj.get("names"), list) or not isinstance(obj.get("joints"), dict):
        raise SchemaError(where, "", "needs 'names' (list) and 'joints' (object: keypoint -> [rig joints])")
    if obj.get("format", fmt) != fmt or len(obj["names"]) not in MAP_SIZES[fmt]:
        raise SchemaError(
            where,
            "names",
            f"is a map for {obj.get('format')!r} with {len(obj['names'])} keypoints; a {fmt} map lists "
            f"{' or '.join(map(str, MAP_SIZES[fmt]))}",
        )
    rig_names = [j.name for j in rig.joints]
    kp, jt, names, offs = [], [], [], []
    for name, entry in obj["joints"].items():
        if name not in obj["names"]:
            raise SchemaError(where, f"joints.{name}", f"is not one of the {fmt} keypoint names")
        extreme = None
        if isinstance(entry, dict):
            extreme, entry = entry.get("extreme"), entry.get("joints")
            if extreme not in EXTREMES:
                raise SchemaError(where, f"joints.{name}.extreme", f"must be one of {EXTREMES}, got {extreme!r}")
        if not isinstance(entry, list) or not all(isinstance(c, str) for c in entry):
            raise SchemaError(where, f"joints.{name}", "must be a list of rig joint names (or {joints, extreme})")
        hit = next((c for c in entry if c in rig_names), None)
        if hit is None or (extreme is not None and template is None):
            continue
        j = rig_names.index(hit)
        try:
            off = np.zeros(3) if extreme is None else marker_offset(rig, template, j, extreme)
        except ValueError as e:
            raise SchemaError(where, f"joints.{name}", str(e)) from None
        kp.append(obj["names"].index(name))
        jt.append(j)
        names.append(name)
        offs.append(off)
    if len(kp) < 4:
        raise SchemaError(
            where,
            "joints",
            f"only {len(kp)} keypoints match joints of this rig (it has {rig_names[:6]}...); pass a --joint-map for it",
        )
    return JointMap(fmt, np.asarray(kp, np.int64), np.asarray(jt, np.int64), tuple(names), np.asarray(offs, np.float64))


def _finite_array(v, file: Path, fld: str, shape_last: int) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise SchemaError(file, fld, "is not a list of numbers") from None
    if a.ndim == 1 and shape_last > 1:
        if a.size % shape_last:
            raise SchemaError(file, fld, f"has {a.size} numbers, not a multiple of {shape_last}")
        a = a.reshape(-1, shape_last)
    if not np.all(np.isfinite(a)):
        raise SchemaError(file, fld, "holds NaN or infinite values")
    return a


def _person_body25(p: dict, file: Path, i: int) -> np.ndarray:
    if "pose_keypoints_2d" not in p:
        raise SchemaError(file, f"people[{i}]", "has no 'pose_keypoints_2d'")
    parts = []
    for key, n in BODY25_PARTS:
        v = p.get(key)
        if v is None or (isinstance(v, list) and not v):  # OpenPose without --hand / --face (or --body 0)
            parts.append(np.zeros((n, 3)))
            continue
        a = _finite_array(v, file, f"people[{i}].{key}", 3)
        if a.shape != (n, 3):
            raise SchemaError(
                file,
                f"people[{i}].{key}",
                f"has shape {list(a.shape)} ([x, y, c] per keypoint); OpenPose writes {n} x 3",
            )
        parts.append(a)
    return np.concatenate(parts)


def _person_coco(p: dict, file: Path, i: int) -> np.ndarray:
    if "keypoint_scores" in p:
        xy = _finite_array(p["keypoints"], file, f"instances[{i}].keypoints", 2)
        sc = _finite_array(p["keypoint_scores"], file, f"instances[{i}].keypoint_scores", 1).reshape(-1)
        if len(xy) != len(sc):
            raise SchemaError(file, f"instances[{i}]", f"{len(xy)} keypoints but {len(sc)} keypoint_scores")
        a = np.concatenate([xy, sc[:, None]], 1)
    else:
        parts = []
        for key, n in _COCO_PARTS:
            if key not in p:
                raise SchemaError(file, f"annotations[{i}].{key}", "is missing (COCO-WholeBody has all five parts)")
            parts.append(_finite_array(p[key], file, f"annotations[{i}].{key}", 3))
            if len(parts[-1]) != n:
                raise SchemaError(file, f"annotations[{i}].{key}", f"has {len(parts[-1])} keypoints, expected {n}")
        a = np.concatenate(parts)
    if len(a) != 133:
        raise SchemaError(file, f"instances[{i}].keypoints", f"has {len(a)} keypoints, COCO-WholeBody has 133")
    return a


def read_keypoint_file(path: str | Path, fmt: KeypointFormat) -> np.ndarray | None:
    """The most confident person's keypoints in one file -> [K, 3] (x, y, confidence), None if nobody."""
    path = Path(path)
    try:
        obj = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SchemaError(path, "", f"not valid JSON: {e}") from None
    if fmt == "body25":
        if not isinstance(obj, dict) or not isinstance(obj.get("people"), list):
            raise SchemaError(path, "people", "missing: not an OpenPose keypoint file")
        people = [_person_body25(p, path, i) for i, p in enumerate(obj["people"]) if isinstance(p, dict)]
    else:
        if isinstance(obj, dict) and "instance_info" in obj:
            info = obj["instance_info"]
            obj = info[0].get("instances", []) if isinstance(info, list) and info else []
        elif isinstance(obj, dict):
            obj = obj.get("instances", obj.get("annotations"))
        if not isinstance(obj, list):
            raise SchemaError(path, "instances", "missing: not a COCO-WholeBody keypoint file")
        people = [_person_coco(p, path, i) for i, p in enumerate(obj) if isinstance(p, dict)]
    if not people:
        return None
    body = BODY25_PARTS[0][1] if fmt == "body25" else len(people[0])  # OpenPose: rank by the body, not the face
    return max(people, key=lambda a: float(np.clip(a[:body, 2], 0, None).sum()))


_FRAME = re.compile(r"^(\d+)")


def detect_format(root: str | Path) -> KeypointFormat:
    """``body25`` or ``coco_wholebody`` from the first file under ``root``."""
    root = Path(root)
    first = next(iter(sorted(root.glob("*/*.json"))), None)
    if first is None:
        raise SchemaError(root, "", "no keypoint files (expected DIR/<camera>/<frame>.json)")
    try:
        obj = json.loads(first.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SchemaError(first, "", f"not valid JSON: {e}") from None
    return "body25" if isinstance(obj, dict) and "people" in obj else "coco_wholebody"


def read_keypoints(
    root: str | Path,
    cameras: list[str],
    frames: list[int],
    fmt: KeypointFormat,
    sizes: dict[str, tuple[int, int]] | None = None,
) -> np.ndarray:
    """Every camera's keypoints of ``frames`` -> [F, C, K, 3] (x, y, confidence; missing file / nobody: 0).

    ``sizes``: camera -> (width, height); detections outside the image get confidence 0. Unknown camera
    folders, negative confidences and malformed files are errors naming the file.
    """
    root = Path(root)
    if not root.is_dir():
        raise SchemaError(root, "", "keypoint folder not found")
    known = set(cameras)
    extra = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name not in known)
    if extra:
        raise SchemaError(
            root, extra[0], f"keypoint folder for a camera the capture does not have ({sorted(known)[:6]}...)"
        )
    K = FORMATS[fmt]
    out = np.zeros((len(frames), len(cameras), K, 3))
    row = {f: i for i, f in enumerate(frames)}
    for c, cam in enumerate(cameras):
        d = root / cam
        if not d.is_dir():
            continue
        for p in sorted(d.glob("*.json")):
            m = _FRAME.match(p.name)
            if m is None or int(m.group(1)) not in row:
                continue
            a = read_keypoint_file(p, fmt)
            if a is None:
                continue
            if np.any(a[:, 2] < 0):
                raise SchemaError(p, "confidence", "negative keypoint confidence")
            if sizes is not None:
                w, h = sizes[cam]
                off = (a[:, 0] < 0) | (a[:, 1] < 0) | (a[:, 0] > w) | (a[:, 1] > h)
                a[off, 2] = 0.0
            out[row[int(m.group(1))], c] = a
    return out
