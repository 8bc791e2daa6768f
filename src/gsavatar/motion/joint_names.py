"""Which motion joint drives which rig joint: joint-name conventions and the user's ``--joint-map`` file.

Every skeleton's names are first turned into **canonical names**, SMPL-X's joint names (``pelvis``,
``left_hip``, ``spine3``, ``left_shoulder`` = upper arm, ``left_index1`` ...) plus a few for joints SMPL-X
lacks (``left_hip_joint``, ``neck1``, ``left_fingers``, ``head_top`` ...). The built-in conventions are JSON
files next to this module (``joint_maps/<convention>.json``: ``{"convention", "description", "joints":
{name: canonical}}``):

===============  ===========================================================================================
``cmu``          CMU mocap BVH (``Hips, LHipJoint, LeftUpLeg, LeftLeg, LeftFoot, LowerBack, Spine, Spine1,
                 Neck, Neck1, LeftShoulder`` = collar, ``LeftArm, LeftForeArm, LeftHand`` ...), the Anny rig
``biovision``    Biovision / MotionBuilder BVH (``Hips, Ab, Chest, LeftCollar, LeftShoulder`` = upper arm,
                 ``LeftElbow, LeftWrist, LeftHip, LeftKnee, LeftAnkle, LeftToes``; ``LeftUpArm`` ...)
``mixamo``       Mixamo (``mixamorig:Hips, Spine, Spine1, Spine2, LeftArm, LeftHandIndex1`` ...)
``smplx``        SMPL-X's own names (``pelvis, left_hip`` ...), SMPL's ``L_Hip`` style
===============  ===========================================================================================

A skeleton's convention is the one that knows most of its names (ties: the order above); names are compared
after dropping a namespace prefix (``mixamorig:``) and case-insensitively; a name its convention does not
know is its own canonical name (so two skeletons with the same custom names still match). Two skeletons'
joints match when their canonical names are equal; the user's joint map (rig joint -> motion joint or
``null``) overrides the match of every rig joint it lists.

Conventions disagree on names: ``LeftShoulder`` is the collar bone in CMU and Mixamo files but the upper
arm in Biovision files, ``Spine1`` is SMPL-X's ``spine3`` in CMU and ``spine2`` in Mixamo; that is why a
skeleton is read with one convention, never with the union of all.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import read_json

MAPS_DIR = Path(__file__).with_name("joint_maps")
"""Folder of the built-in convention files."""
CONVENTIONS: tuple[str, ...] = ("cmu", "biovision", "mixamo", "smplx")
"""Built-in conventions, in tie-breaking order."""

_EXTREMITY = re.compile(r"(index|middle|ring|pinky|thumb|finger|eye|jaw|head_top|_end$|_hand$)")


def is_extremity(canonical: str) -> bool:
    """Whether a canonical joint is a hand or face joint (finger, thumb, eye, jaw, end site): such joints
    left undriven are warned about but never make the motion unusable (a body BVH has no fingers)."""
    return bool(_EXTREMITY.search(canonical))


def plain_name(name: str) -> str:
    """Lookup key of a joint name: namespace prefix dropped (``mixamorig:Hips`` -> ``hips``), lower case."""
    return re.split(r"[:|]", name)[-1].strip().lower()


@lru_cache(maxsize=None)
def convention_map(convention: str) -> dict[str, str]:
    """Lookup key (:func:`plain_name`) -> canonical name of a built-in convention (read from its JSON file)."""
    if convention not in CONVENTIONS:
        raise ValueError(f"joint-name convention must be one of {list(CONVENTIONS)}, got {convention!r}")
    path = MAPS_DIR / f"{convention}.json"
    obj = read_json(path)
    joints = obj.get("joints") if isinstance(obj, dict) else None
    if not isinstance(joints, dict) or not joints:
        raise SchemaError(path, "joints", "expected an object mapping joint names to canonical names")
    out: dict[str, str] = {}
    for k, v in joints.items():
        if not isinstance(v, str) or not v:
            raise SchemaError(path, f"joints.{k}", f"expected a canonical joint name, got {v!r}")
        if plain_name(k) in out and out[plain_name(k)] != v:
            raise SchemaError(path, f"joints.{k}", "the same name (case-insensitively) maps to two canonical names")
        out[plain_name(k)] = v
    return out


def detect_convention(names: Sequence[str]) -> str | None:
    """The built-in convention that knows most of ``names`` (None when none knows any)."""
    best, best_n = None, 0
    for c in CONVENTIONS:
        m = convention_map(c)
        n = sum(plain_name(x) in m for x in names)
        if n > best_n:
            best, best_n = c, n
    return best


def canonical_names(names: Sequence[str], convention: str | None) -> list[str]:
    """Canonical name of each joint under ``convention`` (None: every name is its own)."""
    m = convention_map(convention) if convention is not None else {}
    return [m.get(plain_name(x), plain_name(x)) for x in names]


@dataclass(frozen=True)
class JointMatch:
    """Which motion joint drives each rig joint."""

    rig_to_motion: dict[int, int]
    """Rig joint index -> motion joint index (rig joints absent here are driven by nothing)."""
    rig_convention: str | None
    """Convention detected for the rig's names (None: none known)."""
    motion_convention: str | None
    """Convention detected for the motion's names."""
    rig_canonical: tuple[str, ...]
    """Canonical name of each rig joint (hand/face classification: :func:`is_extremity`)."""


def match_joints(
    rig_names: Sequence[str],
    motion_names: Sequence[str],
    overrides: Mapping[str, str | None] | None = None,
    overrides_file: str | Path = "joint map",
) -> JointMatch:
    """Match rig joints to motion joints (module docstring).

    overrides: rig joint name -> motion joint name (or None: driven by nothing), from the user's joint map or
        a caller's ``name_map``; each rig joint listed is matched by it only. ``overrides_file`` names its
        source in errors (SchemaError): a rig joint the rig does not have, a motion joint the motion does not
        have, one motion joint given to two rig joints.
    """
    overrides = dict(overrides or {})
    rig_idx = {n: i for i, n in enumerate(rig_names)}
    mot_idx = {n: i for i, n in enumerate(motion_names)}
    out: dict[int, int] = {}
    used: dict[int, str] = {}
    for r, m in overrides.items():
        if r not in rig_idx:
            raise SchemaError(overrides_file, r, f"the rig has no joint {r!r} (rig joints: {list(rig_names)})")
        if m is None:
            continue
        if m not in mot_idx:
            raise SchemaError(overrides_file, r, f"the motion has no joint {m!r} (motion joints: {list(motion_names)})")
        if mot_idx[m] in used:
            raise SchemaError(
                overrides_file, r, f"motion joint {m!r} is already given to rig joint {used[mot_idx[m]]!r}"
            )
        out[rig_idx[r]] = mot_idx[m]
        used[mot_idx[m]] = r
    rc, mc = detect_convention(rig_names), detect_convention(motion_names)
    rig_can, mot_can = canonical_names(rig_names, rc), canonical_names(motion_names, mc)
    first: dict[str, int] = {}
    for i, c in enumerate(mot_can):
        first.setdefault(c, i)  # a name given twice: the first (parents-first order) drives
    for j, (name, c) in enumerate(zip(rig_names, rig_can)):
        if name in overrides or c not in first or first[c] in used:
            continue
        out[j] = first[c]
        used[first[c]] = name
    return JointMatch(out, rc, mc, tuple(rig_can))


def read_joint_map(path: str | Path) -> dict[str, str | None]:
    """A user's joint map: a JSON object ``{"<rig joint>": "<motion joint>" | null, ...}`` (strict reader:
    duplicate keys, NaN, non-UTF-8 refused). Names are checked against the rig and motion by
    :func:`match_joints`; here only the form (SchemaError naming the file and key)."""
    path = Path(path)
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise SchemaError(
            path, "", f"expected a JSON object mapping rig joints to motion joints, got {type(obj).__name__}"
        )
    if not obj:
        raise SchemaError(path, "", "empty joint map")
    for k, v in obj.items():
        if v is not None and (not isinstance(v, str) or not v):
            raise SchemaError(path, k, f"expected a motion joint name or null, got {v!r}"[:200])
    return dict(obj)
