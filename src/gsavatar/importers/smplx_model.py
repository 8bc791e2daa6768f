"""The user's SMPL-X model file (``SMPLX_NEUTRAL.npz``), read without unpickling and validated.

The SMPL-X model is licensed by the Max Planck Institute for Intelligent Systems (MPI) for non-commercial
research; gsavatar never ships or downloads it, the user points at their own copy (docs/import.md).

Keys read (the layout the ``smplx`` package reads, ``smplx.SMPLX(..., ext="npz")``):

==================  =================  ==========================================================
key                 shape              meaning
==================  =================  ==========================================================
``v_template``      [V, 3]             mean-shape rest vertices, metres, +Y up
``f``               [T, 3] int         triangles
``shapedirs``       [V, 3, S]          shape then expression blend shapes (column split below)
``posedirs``        [V, 3, 486]        pose-corrective blend shapes, one per entry of ``R_j - I``
                                       of joints 1..54 (our LBS format cannot store them)
``J_regressor``     [55, V]            joint positions from shaped vertices
``weights``         [V, 55]            dense skinning weights, rows sum to 1
``kintree_table``   [2, 55]            row 0: parent of each joint (root's entry ignored)
``hands_components{l,r}``  [45, 45]    hand-pose PCA basis (only for PCA hand poses), optional
``hands_mean{l,r}``  [45]              mean hand pose (only when ``flat_hand_mean=False``), optional
``vt``, ``ft``      [T', 2], [T, 3]    UVs (v up) and their per-corner indices, optional
==================  =================  ==========================================================

Other keys (``joint2num``, ``part2num``: pickled dicts in the official file; landmark tables) are never read:
:func:`gsavatar.utils.io.read_npz` only decompresses the keys asked for and refuses object arrays.

``shapedirs`` columns follow ``smplx`` 0.1.28: a model with at least 400 columns (SMPL-X v1.1) has 300 shape
then 100 expression columns; a smaller one (v1.0) has 10 shape columns then 10 expression columns from
column 10 (columns past 20 are ignored, as ``smplx`` does).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gsavatar.geometry.mesh_io import read_obj
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import read_npz

SMPLX_JOINT_NAMES: tuple[str, ...] = (
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
    "left_index1",
    "left_index2",
    "left_index3",
    "left_middle1",
    "left_middle2",
    "left_middle3",
    "left_pinky1",
    "left_pinky2",
    "left_pinky3",
    "left_ring1",
    "left_ring2",
    "left_ring3",
    "left_thumb1",
    "left_thumb2",
    "left_thumb3",
    "right_index1",
    "right_index2",
    "right_index3",
    "right_middle1",
    "right_middle2",
    "right_middle3",
    "right_pinky1",
    "right_pinky2",
    "right_pinky3",
    "right_ring1",
    "right_ring2",
    "right_ring3",
    "right_thumb1",
    "right_thumb2",
    "right_thumb3",
)
"""SMPL-X's 55 joints in model order (``smplx`` calls the eyes ``left_eye_smplhf``/``right_eye_smplhf``). The
full pose ``[global_orient, body_pose (21), jaw, leye, reye, left hand (15), right hand (15)]`` follows it."""

SMPLX_PARENTS: tuple[int, ...] = (
    -1,
    0,
    0,
    0,
    1,
    2,
    3,
    4,
    5,
    6,
    7,
    8,
    9,
    9,
    9,
    12,
    13,
    14,
    16,
    17,
    18,
    19,
    15,
    15,
    15,
    20,
    25,
    26,
    20,
    28,
    29,
    20,
    31,
    32,
    20,
    34,
    35,
    20,
    37,
    38,
    21,
    40,
    41,
    21,
    43,
    44,
    21,
    46,
    47,
    21,
    49,
    50,
    21,
    52,
    53,
)
"""SMPL-X's kinematic tree (parent index per joint). A model's ``kintree_table`` must match it: the joint names
and body-part groups are only right for this tree."""

NUM_JOINTS = len(SMPLX_JOINT_NAMES)
NUM_POSEDIRS = (NUM_JOINTS - 1) * 9


_FINGERS = ("index", "middle", "pinky", "ring", "thumb")
GROUP_JOINTS: dict[str, tuple[str, ...]] = {
    "torso_head": ("spine1", "spine2", "spine3", "neck", "head", "jaw", "left_eye", "right_eye"),
    "left_leg": ("left_hip", "left_knee", "left_ankle", "left_foot"),
    "right_leg": ("right_hip", "right_knee", "right_ankle", "right_foot"),
    "left_arm": ("left_collar", "left_shoulder", "left_elbow"),
    "right_arm": ("right_collar", "right_shoulder", "right_elbow"),
    "left_hand": ("left_wrist", *(f"left_{f}{i}" for f in _FINGERS for i in (1, 2, 3))),
    "right_hand": ("right_wrist", *(f"right_{f}{i}" for f in _FINGERS for i in (1, 2, 3))),
}
"""The SMPL-X joints of each body-part group (:data:`gsavatar.data_schema.rig.BODY_GROUPS`), as the synthetic CMU
rig groups its joints: clavicles (collars) with the arm, the wrist with the hand, jaw and eyes with the head. Every
joint but the root (pelvis: no pose parameter; its vertices count as ``torso_head`` in error reports) is in
exactly one group (tests/importers/test_smplx_inputs.py)."""

SMPLX_JOINT_GROUPS: dict[str, str] = {j: g for g, joints in GROUP_JOINTS.items() for j in joints}
"""Joint name -> body-part group, :data:`GROUP_JOINTS` inverted."""


@dataclass
class SmplxModel:
    """An SMPL-X body model as arrays (float32 unless noted)."""

    path: Path
    """File it was read from (named in errors)."""
    v_template: np.ndarray
    """Mean-shape rest vertices, metres.  # [V, 3]"""
    faces: np.ndarray
    """Triangles.  # [T, 3] int64"""
    shapedirs: np.ndarray
    """Shape blend shapes (10 or 300 columns, see module doc).  # [V, 3, S]"""
    exprdirs: np.ndarray
    """Expression blend shapes (10 or 100 columns).  # [V, 3, E]"""
    posedirs: np.ndarray
    """Pose-corrective blend shapes; column ``9 (j - 1) + 3 r + c`` scales entry (r, c) of ``R_j - I``.
    # [V, 3, 486]"""
    J_regressor: np.ndarray
    """Rest joint positions from shaped vertices.  # [55, V]"""
    weights: np.ndarray
    """Dense skinning weights, rows sum to 1.  # [V, 55]"""
    parents: np.ndarray
    """Parent joint index, -1 for the root (= :data:`SMPLX_PARENTS`).  # [55] int64"""
    hands_components: tuple[np.ndarray, np.ndarray] | None = None
    """Left and right hand-pose PCA bases, rows = components, or None.  # ([45, 45], [45, 45])"""
    hands_mean: tuple[np.ndarray, np.ndarray] | None = None
    """Left and right mean hand pose (axis-angle per finger joint), or None.  # ([45], [45])"""
    uvs: np.ndarray | None = None
    """UV coordinates (v up) or None.  # [T', 2]"""
    face_uvs: np.ndarray | None = None
    """UV index per triangle corner or None.  # [T, 3] int64"""

    @property
    def num_vertices(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    @property
    def num_expression(self) -> int:
        return int(self.exprdirs.shape[2])


def _array(z: dict, key: str, path: Path, ndim: int, kinds: str = "iuf") -> np.ndarray:
    if key not in z:
        raise SchemaError(path, key, f"missing (an SMPL-X model npz needs it; found {sorted(z)})")
    a = z[key]
    if a.dtype.kind not in kinds:
        raise SchemaError(path, key, f"expected {'integers' if kinds == 'iu' else 'real numbers'}, got dtype {a.dtype}")
    if a.ndim != ndim:
        raise SchemaError(path, key, f"expected {ndim} dimensions, got shape {list(a.shape)}")
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise SchemaError(path, key, f"{int((~np.isfinite(a)).sum())} NaN/Inf values")
    return a


def _shape(a: np.ndarray, want: tuple[int | None, ...], path: Path, key: str, why: str = "") -> None:
    if len(want) != a.ndim or any(w is not None and w != s for w, s in zip(want, a.shape)):
        shown = ", ".join("*" if w is None else str(w) for w in want)
        raise SchemaError(path, key, f"expected shape [{shown}]{why}, got {list(a.shape)}")


KEYS = (
    "v_template",
    "f",
    "shapedirs",
    "posedirs",
    "J_regressor",
    "weights",
    "kintree_table",
    "hands_componentsl",
    "hands_componentsr",
    "hands_meanl",
    "hands_meanr",
    "vt",
    "ft",
)
"""Keys :func:`load_smplx_model` reads (the rest of the file is never decompressed)."""


def load_smplx_model(path: str | Path) -> SmplxModel:
    """Read and validate an SMPL-X model npz (``SMPLX_NEUTRAL.npz``); SchemaError names the file and key."""
    path = Path(path)
    z = read_npz(path, keys=KEYS)
    v = _array(z, "v_template", path, 2)
    _shape(v, (None, 3), path, "v_template")
    V = v.shape[0]
    f = _array(z, "f", path, 2, "iu").astype(np.int64)
    _shape(f, (None, 3), path, "f")
    if f.size == 0 or f.min() < 0 or f.max() >= V:
        raise SchemaError(path, "f", f"vertex index out of range [0, {V})")
    sd = _array(z, "shapedirs", path, 3)
    _shape(sd, (V, 3, None), path, "shapedirs")
    S = sd.shape[2]
    if S < 20:
        raise SchemaError(path, "shapedirs", f"{S} columns; SMPL-X needs >= 20 (10 shape + 10 expression)")
    shape_cols, expr_cols = (slice(0, 300), slice(300, 400)) if S >= 400 else (slice(0, 10), slice(10, 20))
    pd = _array(z, "posedirs", path, 3)
    _shape(pd, (V, 3, NUM_POSEDIRS), path, "posedirs", f" (9 entries of R - I for {NUM_JOINTS - 1} joints)")
    jr = _array(z, "J_regressor", path, 2)
    _shape(jr, (NUM_JOINTS, V), path, "J_regressor", f" ({NUM_JOINTS} SMPL-X joints x vertices)")
    w = _array(z, "weights", path, 2)
    _shape(w, (V, NUM_JOINTS), path, "weights")
    if w.min() < -1e-6:
        raise SchemaError(path, "weights", f"negative skinning weights (min {w.min():.3g})")
    s = w.sum(1)
    bad = np.abs(s - 1) > 1e-3
    if bad.any():
        i = int(np.argmax(bad))
        raise SchemaError(path, "weights", f"{int(bad.sum())} rows do not sum to 1 (vertex {i}: {s[i]:.4f})")
    kt = _array(z, "kintree_table", path, 2, "iu")
    _shape(kt, (2, NUM_JOINTS), path, "kintree_table")
    parents = kt[0].astype(np.int64)
    parents[0] = -1  # the official file stores 2^32 - 1 for the root
    if kt[1].tolist() != list(range(NUM_JOINTS)) or tuple(parents.tolist()) != SMPLX_PARENTS:
        raise SchemaError(
            path,
            "kintree_table",
            "not SMPL-X's kinematic tree (55 joints, pelvis first, "
            f"parents {list(SMPLX_PARENTS)}); got parents {parents.tolist()}",
        )
    hands_components = hands_mean = None
    if "hands_componentsl" in z and "hands_componentsr" in z:
        hc = tuple(_array(z, k, path, 2) for k in ("hands_componentsl", "hands_componentsr"))
        for k, a in zip(("hands_componentsl", "hands_componentsr"), hc):
            _shape(a, (None, 45), path, k)
        hands_components = tuple(a.astype(np.float32) for a in hc)
    if "hands_meanl" in z and "hands_meanr" in z:
        hm = tuple(_array(z, k, path, 1) for k in ("hands_meanl", "hands_meanr"))
        for k, a in zip(("hands_meanl", "hands_meanr"), hm):
            _shape(a, (45,), path, k)
        hands_mean = tuple(a.astype(np.float32) for a in hm)
    uvs = face_uvs = None
    if "vt" in z and "ft" in z:
        uvs, face_uvs = _check_uvs(_array(z, "vt", path, 2), _array(z, "ft", path, 2, "iu"), len(f), path, "vt", "ft")
    return SmplxModel(
        path=path,
        v_template=v.astype(np.float32),
        faces=f,
        shapedirs=np.ascontiguousarray(sd[:, :, shape_cols], dtype=np.float32),
        exprdirs=np.ascontiguousarray(sd[:, :, expr_cols], dtype=np.float32),
        posedirs=pd.astype(np.float32),
        J_regressor=jr.astype(np.float32),
        weights=w.astype(np.float32),
        parents=parents,
        hands_components=hands_components,
        hands_mean=hands_mean,
        uvs=uvs,
        face_uvs=face_uvs,
    )


def _check_uvs(
    vt: np.ndarray, ft: np.ndarray, num_faces: int, path: Path, kv: str, kf: str
) -> tuple[np.ndarray, np.ndarray]:
    _shape(vt, (None, 2), path, kv)
    _shape(ft, (num_faces, 3), path, kf, " (one UV index per corner of every model triangle)")
    if ft.min() < 0 or ft.max() >= len(vt):
        raise SchemaError(path, kf, f"UV index out of range [0, {len(vt)})")
    return vt.astype(np.float32), ft.astype(np.int64)


def load_smplx_uvs(path: str | Path, model: SmplxModel) -> tuple[np.ndarray, np.ndarray]:
    """UVs of the SMPL-X mesh from the user's UV file (an OBJ such as ``smplx_uv.obj``, whose triangles must be the
    model's ``f``). -> (uvs [T', 2] float32 v up, face_uvs [T, 3] int64)."""
    path = Path(path)
    obj = read_obj(path)
    if obj.uvs is None or obj.face_uvs is None:
        raise SchemaError(path, "vt", "no texture coordinates (every face needs v/vt corners)")
    if len(obj.vertices) != model.num_vertices or obj.faces.shape != model.faces.shape:
        raise SchemaError(
            path,
            "f",
            f"{len(obj.vertices)} vertices / {len(obj.faces)} triangles, the model "
            f"{model.path.name} has {model.num_vertices} / {len(model.faces)}",
        )
    if not np.array_equal(obj.faces, model.faces):
        i = int(np.argmax((obj.faces != model.faces).any(1)))
        raise SchemaError(
            path,
            "f",
            f"triangle {i} is {obj.faces[i].tolist()}, the model's is "
            f"{model.faces[i].tolist()}: not the SMPL-X topology",
        )
    return _check_uvs(obj.uvs, obj.face_uvs, len(model.faces), path, "vt", "f")
