"""``template/rig.json``: the skeleton, its pose parameters and body-part groups.

Conventions
-----------
- Joints are listed parents-first; ``parent`` is ``None`` only for the root.
- ``head`` is the joint's rest-pose position in template (world) space, metres.
- Every joint frame is axis-aligned with the world in the rest pose, so a joint's
  local rotation is expressed in world axes at rest (SMPL-style).
- A pose parameter is either ``euler``: one angle (radians) about a fixed unit
  ``axis`` of its joint's frame, or ``axis_angle``: three consecutive slots of the
  pose vector holding a rotation vector. A joint's local rotation is the product of
  its parameters' rotations in the order they are listed (first listed = leftmost).
- ``groups`` maps each of the 7 body-part groups to the names of its parameters;
  every parameter belongs to exactly one group (localized PCA needs that).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_write_text
from gsavatar.utils.jsonio import is_number, read_json
from gsavatar.utils.paths import check_name

BODY_GROUPS: tuple[str, ...] = (
    "torso_head",
    "left_leg",
    "right_leg",
    "left_arm",
    "right_arm",
    "left_hand",
    "right_hand",
)
"""The paper's seven body-part groups for localized PCA (section 3.2)."""


@dataclass(frozen=True)
class Joint:
    name: str
    """Unique joint name (e.g. ``LeftForeArm``)."""
    parent: str | None
    """Parent joint name; ``None`` for the root."""
    head: tuple[float, float, float]
    """Rest-pose joint position in template space, metres."""


@dataclass(frozen=True)
class PoseParam:
    name: str
    """Unique parameter name (e.g. ``LeftForeArm.rx``)."""
    joint: str
    """Joint this parameter rotates."""
    kind: Literal["euler", "axis_angle"]
    """``euler``: one angle about ``axis``; ``axis_angle``: three slots, a rotation vector."""
    axis: tuple[float, float, float] | None = None
    """Unit rotation axis in the joint frame (``euler`` only)."""

    @property
    def size(self) -> int:
        """Number of pose-vector slots this parameter occupies."""
        return 3 if self.kind == "axis_angle" else 1


@dataclass
class Rig:
    joints: list[Joint]
    """Joints, parents before children."""
    params: list[PoseParam]
    """Pose parameters in pose-vector order."""
    groups: dict[str, list[str]]
    """Body-part group name -> parameter names (see :data:`BODY_GROUPS`)."""
    _index: dict[str, int] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        self._index = {j.name: i for i, j in enumerate(self.joints)}

    # --- derived views -------------------------------------------------------
    @property
    def num_joints(self) -> int:
        return len(self.joints)

    @property
    def pose_dim(self) -> int:
        """Length P of the pose vector in ``motion.npz``."""
        return sum(p.size for p in self.params)

    def joint_index(self, name: str) -> int:
        return self._index[name]

    def parents(self) -> np.ndarray:
        """Parent index per joint, -1 for the root.  # [J] int64"""
        return np.array([-1 if j.parent is None else self._index[j.parent] for j in self.joints], dtype=np.int64)

    def heads(self) -> np.ndarray:
        """Rest joint positions.  # [J, 3] float32, metres"""
        return np.array([j.head for j in self.joints], dtype=np.float32)

    def slot_params(self) -> list[int]:
        """Parameter index of every pose-vector slot.  # len P"""
        out: list[int] = []
        for i, p in enumerate(self.params):
            out.extend([i] * p.size)
        return out

    def slot_joints(self) -> np.ndarray:
        """Joint index driven by every pose-vector slot.  # [P] int64"""
        return np.array([self._index[self.params[i].joint] for i in self.slot_params()], dtype=np.int64)

    def slot_groups(self) -> np.ndarray:
        """Group index (into :data:`BODY_GROUPS`) of every pose-vector slot.  # [P] int64"""
        of_param = {}
        for gi, g in enumerate(BODY_GROUPS):
            for name in self.groups.get(g, []):
                of_param[name] = gi
        return np.array([of_param[self.params[i].name] for i in self.slot_params()], dtype=np.int64)

    # --- io ------------------------------------------------------------------
    def to_json(self) -> dict:
        return {
            "joints": [{"name": j.name, "parent": j.parent, "head": list(map(float, j.head))} for j in self.joints],
            "pose_params": [
                {"name": p.name, "joint": p.joint, "kind": p.kind}
                | ({"axis": list(map(float, p.axis))} if p.axis is not None else {})
                for p in self.params
            ],
            "groups": {g: list(v) for g, v in self.groups.items()},
        }

    def save(self, path: str | Path) -> None:
        atomic_write_text(path, json.dumps(self.to_json(), indent=1))


def _vec3(v, file: Path, fld: str) -> tuple[float, float, float]:
    if not isinstance(v, (list, tuple)) or not all(is_number(x) for x in v):
        raise SchemaError(file, fld, f"expected 3 finite numbers, got {v!r}"[:200])
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise SchemaError(file, fld, f"expected 3 numbers, got {v!r}") from None
    if a.shape != (3,):
        raise SchemaError(file, fld, f"expected 3 numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise SchemaError(file, fld, "contains NaN/Inf")
    return (float(a[0]), float(a[1]), float(a[2]))


def rig_from_json(obj: dict, file: str | Path = "rig.json") -> Rig:
    """Build and validate a :class:`Rig` from parsed JSON, naming the bad field on error."""
    file = Path(file)
    if not isinstance(obj, dict):
        raise SchemaError(file, "", "top level must be an object")
    for key in ("joints", "pose_params", "groups"):
        if key not in obj:
            raise SchemaError(file, key, "missing")
    joints: list[Joint] = []
    seen: set[str] = set()
    for key in ("joints", "pose_params"):
        if not isinstance(obj[key], list):
            raise SchemaError(file, key, f"must be a list, got {type(obj[key]).__name__}")
    for i, j in enumerate(obj["joints"]):
        fld = f"joints[{i}]"
        if not isinstance(j, dict) or "name" not in j or "head" not in j:
            raise SchemaError(file, fld, "needs 'name', 'parent' and 'head'")
        check_name(j["name"], file, f"{fld}.name", "joint name")
        parent = j.get("parent")
        if parent is not None and not isinstance(parent, str):
            raise SchemaError(file, f"{fld}.parent", f"must be a joint name or null, got {parent!r}")
        if parent is not None and parent not in seen:
            raise SchemaError(file, f"{fld}.parent", f"parent {parent!r} of {j['name']!r} is not listed before it")
        if parent is None and joints:
            raise SchemaError(file, f"{fld}.parent", f"only the first joint may be the root ({j['name']!r} has none)")
        if j["name"] in seen:
            raise SchemaError(file, f"{fld}.name", f"duplicate joint {j['name']!r}")
        joints.append(Joint(str(j["name"]), parent, _vec3(j["head"], file, f"{fld}.head")))
        seen.add(j["name"])
    if not joints:
        raise SchemaError(file, "joints", "empty")
    params: list[PoseParam] = []
    pnames: set[str] = set()
    for i, p in enumerate(obj["pose_params"]):
        fld = f"pose_params[{i}]"
        if not isinstance(p, dict) or not {"name", "joint", "kind"} <= set(p):
            raise SchemaError(file, fld, "needs 'name', 'joint' and 'kind'")
        check_name(p["name"], file, f"{fld}.name", "pose parameter name")
        if not isinstance(p["joint"], str) or p["joint"] not in seen:
            raise SchemaError(file, f"{fld}.joint", f"unknown joint {p['joint']!r}")
        if p["name"] in pnames:
            raise SchemaError(file, f"{fld}.name", f"duplicate parameter {p['name']!r}")
        if not isinstance(p["kind"], str):
            raise SchemaError(file, f"{fld}.kind", f"expected 'euler' or 'axis_angle', got {p['kind']!r}")
        if p["kind"] == "euler":
            if "axis" not in p:
                raise SchemaError(file, f"{fld}.axis", "euler parameters need an axis")
            ax = np.array(_vec3(p["axis"], file, f"{fld}.axis"))
            n = np.linalg.norm(ax)
            if not 0.99 < n < 1.01:
                raise SchemaError(file, f"{fld}.axis", f"axis must be unit length, got norm {n:.3f}")
            params.append(PoseParam(p["name"], p["joint"], "euler", tuple(map(float, ax / n))))
        elif p["kind"] == "axis_angle":
            params.append(PoseParam(p["name"], p["joint"], "axis_angle"))
        else:
            raise SchemaError(file, f"{fld}.kind", f"expected 'euler' or 'axis_angle', got {p['kind']!r}")
        pnames.add(p["name"])
    groups = obj["groups"]
    if not isinstance(groups, dict):
        raise SchemaError(file, "groups", "must map group name -> parameter names")
    unknown = set(groups) - set(BODY_GROUPS)
    if unknown:
        raise SchemaError(file, "groups", f"unknown groups {sorted(unknown)}; expected {list(BODY_GROUPS)}")
    owner: dict[str, str] = {}
    for g, names in groups.items():
        if not isinstance(names, list):
            raise SchemaError(file, f"groups.{g}", f"must be a list of parameter names, got {type(names).__name__}")
        for n in names:
            if not isinstance(n, str) or n not in pnames:  # a list there is unhashable: TypeError, not this
                raise SchemaError(file, f"groups.{g}", f"unknown pose parameter {n!r}")
            if n in owner:
                raise SchemaError(file, f"groups.{g}", f"parameter {n!r} is also in group {owner[n]!r}")
            owner[n] = g
    missing = [p.name for p in params if p.name not in owner]
    if missing:
        raise SchemaError(file, "groups", f"{len(missing)} parameters in no group, e.g. {missing[:3]}")
    return Rig(joints, params, {g: list(v) for g, v in groups.items()})


def load_rig(path: str | Path) -> Rig:
    path = Path(path)
    return rig_from_json(read_json(path), path)
