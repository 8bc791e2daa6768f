"""AMASS-style SMPL-X motion files (``.npz``) as the motion of an SMPL-X rig (``avatar-prep import``'s rig).

Keys read (AMASS's SMPL-X release; any others, ``betas``, ``gender`` ..., are never decompressed):

======================================  ==========  =====================================================
key                                     shape       meaning
======================================  ==========  =====================================================
``poses``                               [F, 165]    axis-angle of SMPL-X's 55 joints in model order: global
                                                    orientation, 21 body joints, jaw, eyes, 15 + 15 hand joints
``trans``                               [F, 3]      root translation, metres
``mocap_frame_rate``                    scalar      frames per second (``mocap_framerate`` as AMASS's SMPL-H
                                                    files spell it); else ``fps=`` or a sidecar (drive.motion)
======================================  ==========  =====================================================

Hands are read as they are (AMASS's body model adds no hand mean: ``flat_hand_mean=True``, as our importers
write SMPL-X fits). SMPL-X's root convention, ``R(global_orient) (x - J_0) + J_0 + trans``, is ours with
``J_0`` the rig's root head, so ``pose = poses[:, 3:]``, ``root_rotation = poses[:, :3]``, ``root_translation
= trans``. The subject's ``betas`` are not used: the avatar keeps its own shape.

**Up axis.** AMASS's world is Z up; our avatars and orbit cameras are Y up. With ``up="z"`` (default) the
world is turned by ``C = Rx(-90 deg)``, ``(x, y, z) -> (x, z, -y)``: ``root_rotation = C R``, and the
translation keeps ``C (R (x - J_0) + J_0 + t) = C R (x - J_0) + J_0 + t'`` with ``t' = C (J_0 + t) - J_0``.
``up="y"``: the file is taken as it is (fits already in a Y-up frame).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.limits import check_fps, check_motion_values
from gsavatar.data_schema.rig import Rig
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_npz

SMPLX_JOINT_ORDER: tuple[str, ...] = (
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "jaw",
    "left_eye",
    "right_eye",
    *(
        f"{s}_{f}{i}"
        for s in ("left", "right")
        for f in ("index", "middle", "pinky", "ring", "thumb")
        for i in (1, 2, 3)
    ),
)
"""SMPL-X's 55 joints in model order (the order of ``poses``; ``importers.smplx_model.SMPLX_JOINT_NAMES``)."""

AMASS_KEYS: tuple[str, ...] = ("poses", "trans", "mocap_frame_rate", "mocap_framerate")
"""Arrays read from an AMASS file."""

UpAxis = Literal["z", "y"]
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
"""``(x, y, z) -> (x, z, -y)``: AMASS's Z-up world to our Y-up one (a -90 degree turn about X)."""


class AmassMotion(NamedTuple):
    pose: np.ndarray
    """SMPL-X pose of joints 1-54 (the importers' rig order), axis-angle.  # [F, 162] float64"""
    root_rotation: np.ndarray
    """Root rotation, axis-angle, in our (Y-up) world.  # [F, 3] float64"""
    root_translation: np.ndarray
    """Root translation, metres.  # [F, 3] float64"""
    fps: float | None
    """``mocap_frame_rate`` (None when the file has none)."""
    fps_field: str
    """The key the frame rate came from (for messages)."""


def is_amass(keys) -> bool:
    """Whether an npz holding ``keys`` is an AMASS-style motion (``poses``, and no ``pose`` of a motion.npz)."""
    keys = set(keys)
    return "poses" in keys and "pose" not in keys


def check_smplx_rig(rig: Rig, path: str | Path) -> None:
    """SchemaError(path, 'poses') unless ``rig`` is the importers' SMPL-X rig: SMPL-X's 55 joints in model order,
    one ``axis_angle`` parameter per non-root joint in joint order."""
    names = tuple(j.name for j in rig.joints)
    ok = (
        names == SMPLX_JOINT_ORDER
        and len(rig.params) == len(names) - 1
        and all(p.kind == "axis_angle" and p.joint == n for p, n in zip(rig.params, names[1:]))
    )
    if not ok:
        raise SchemaError(
            path,
            "poses",
            f"an AMASS SMPL-X motion drives SMPL-X rigs only (55 joints in SMPL-X order, one "
            f"axis_angle parameter each: an avatar-prep import capture); this avatar's rig has "
            f"{len(names)} joints ({', '.join(names[:4])}, ...) and pose dimension "
            f"{rig.pose_dim}: drive it from a BVH file instead",
        )


def _array(z: dict, path: Path, key: str, width: int) -> np.ndarray:
    a = z.get(key)
    if a is None:
        raise SchemaError(path, key, "missing (an AMASS motion needs poses [F, 165] and trans [F, 3])")
    if a.dtype.kind not in "iuf":
        raise SchemaError(path, key, f"expected real numbers, got dtype {a.dtype}")
    if a.ndim != 2 or a.shape[1] != width or a.shape[0] < 1:
        hint = " (SMPL-X: 55 joints x 3; SMPL-H files with 156 columns are not read)" if key == "poses" else ""
        raise SchemaError(path, key, f"expected shape [F, {width}], got {list(a.shape)}{hint}")
    bad = ~np.isfinite(a)
    if bad.any():
        f, c = np.argwhere(bad)[0]
        raise SchemaError(path, key, f"{int(bad.sum())} NaN/Inf values (first at frame {f}, column {c})")
    check_motion_values(a, path, key)  # before the rotation maths: 1e308 made scipy's SVD fail
    return a.astype(np.float64)


def read_amass(path: str | Path, rig: Rig, up: UpAxis = "z", z: dict[str, np.ndarray] | None = None) -> AmassMotion:
    """An AMASS-style SMPL-X motion as the motion of the SMPL-X ``rig`` (module docstring). ``z``: the file's
    arrays when the caller has read them (:data:`AMASS_KEYS`). SchemaError names the file and key."""
    path = Path(path)
    if up not in ("z", "y"):
        raise ValueError(f"up must be 'z' or 'y', got {up!r}")
    if z is None:
        z = read_npz(path, keys=AMASS_KEYS)
    check_smplx_rig(rig, path)
    poses = _array(z, path, "poses", 3 * len(SMPLX_JOINT_ORDER))
    trans = _array(z, path, "trans", 3)
    if len(trans) != len(poses):
        raise SchemaError(path, "trans", f"has {len(trans)} frames, poses has {len(poses)}")
    fps, field = None, ""
    for key in ("mocap_frame_rate", "mocap_framerate"):
        if key in z:
            a = np.asarray(z[key]).reshape(-1)
            if a.size != 1 or a.dtype.kind not in "iuf":
                raise SchemaError(path, key, f"expected one number, got {a.size} values of dtype {a.dtype}")
            fps, field = check_fps(float(a[0]), path, key), key
            break
    rr, rt = poses[:, :3], trans
    if up == "z":
        C = Z_UP_TO_Y_UP
        j0 = np.asarray(rig.heads()[0], dtype=np.float64)
        rr = Rotation.from_matrix(C @ Rotation.from_rotvec(rr).as_matrix()).as_rotvec()
        rt = (j0 + trans) @ C.T - j0
    return AmassMotion(poses[:, 3:], rr, rt, fps, field)
