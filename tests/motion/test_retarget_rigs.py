"""Retargeting BVH onto any rig: joint-name conventions (CMU, Biovision/MotionBuilder, Mixamo, SMPL-X, SMPL),
the user's joint map, the undriven-joint warning and error, and rigs whose parameters differ (euler about
principal axes, euler about rotated axes, axis-angle, hinges) posing the same surface.

Skeletons: the fake SMPL-X body of tests/importers/fake_smplx.py (no licensed data) is the rig; the BVH files
are written here from the same rest joints (centimetres, arms turned 40 degrees down into an A-pose so that
the rest alignment works) with each convention's joint names and random rotations.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gsavatar.data_schema.rig import Joint, PoseParam, Rig, rig_from_json
from gsavatar.geometry.lbs import lbs, pose_joints, pose_to_local_rotations, skinning_transforms
from gsavatar.importers import load_smplx_model, smplx_template
from gsavatar.importers.smplx_model import GROUP_JOINTS, SMPLX_JOINT_NAMES, SMPLX_PARENTS
from gsavatar.motion.bvh import bvh_joint_positions, read_bvh
from gsavatar.motion.joint_names import CONVENTIONS, convention_map, detect_convention, match_joints, read_joint_map
from gsavatar.motion.retarget import UndrivenJointsWarning, retarget_bvh
from gsavatar.motion.rig_pose import pose_from_local_rotations
from gsavatar.utils.errors import SchemaError
from importers.fake_smplx import write_fake_smplx
from motion.bvh_writer import random_angles, write_bvh

BOXING = Path("/usr/share/assimp/models/BVH/Boxing_Toes.bvh")
SURFACE_TOL_M = 1e-4  # the bar; observed ~1e-15 m (the decompositions are exact)
BONE_COS = 0.9999  # limb bones follow the BVH's: observed 1 - 1e-15
LIMB_BONES = [
    (f"{s}_{a}", f"{s}_{b}")
    for s in ("left", "right")
    for a, b in (("hip", "knee"), ("knee", "ankle"), ("shoulder", "elbow"), ("elbow", "wrist"))
]
BODY22 = list(SMPLX_JOINT_NAMES[:22])
GROUP_OF = {j: g for g, js in GROUP_JOINTS.items() for j in js}


# --------------------------------------------------------------------------- fixtures and helpers
@pytest.fixture(scope="module")
def body(tmp_path_factory):
    """(template, axis-angle SMPL-X rig) of the fake body (1760 vertices)."""
    model = load_smplx_model(write_fake_smplx(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz", rings=4, segs=8))
    b = smplx_template(model, np.zeros(10))
    return b.template, b.rig


def _side(spec_l: list[tuple], sides=("Left", "Right")) -> list[tuple]:
    """Expand ``{S}``/``{s}``/``{c}`` (side name, side canonical prefix, side initial) in a left-side spec."""
    out = []
    for S, s in zip(sides, ("left", "right")):
        fmt = lambda x: (
            x.format(S=S, s=s, c=S[0])
            if isinstance(x, str)
            else tuple(  # noqa: E731
                v.format(S=S, s=s, c=S[0]) if isinstance(v, str) else v for v in x
            )
        )
        out += [(fmt(n), None if p is None else fmt(p), fmt(pos)) for n, p, pos in spec_l]
    return out


def _smpl_name(n: str) -> str:
    """SMPL's spelling of a body joint: ``Pelvis``, ``L_Hip``, ``Spine1``, ``R_Collar``."""
    for side, tag in (("left_", "L_"), ("right_", "R_")):
        if n.startswith(side):
            return tag + n[len(side) :].capitalize()
    return n.capitalize()


# (name, parent, rest position: a canonical joint or (joint a, joint b, t) = a + t (b - a)); expected driven
# SMPL-X joints per convention
SPECS: dict[str, tuple[list[tuple], list[str]]] = {
    "cmu": (
        [("Hips", None, "pelvis")]
        + _side(
            [
                ("{c}HipJoint", "Hips", ("pelvis", "{s}_hip", 0.5)),
                ("{S}UpLeg", "{c}HipJoint", "{s}_hip"),
                ("{S}Leg", "{S}UpLeg", "{s}_knee"),
                ("{S}Foot", "{S}Leg", "{s}_ankle"),
                ("{S}ToeBase", "{S}Foot", "{s}_foot"),
            ]
        )
        + [
            ("LowerBack", "Hips", "spine1"),
            ("Spine", "LowerBack", "spine2"),
            ("Spine1", "Spine", "spine3"),
            ("Neck", "Spine1", "neck"),
            ("Neck1", "Neck", ("neck", "head", 0.5)),
            ("Head", "Neck1", "head"),
        ]
        + _side(
            [
                ("{S}Shoulder", "Spine1", "{s}_collar"),
                ("{S}Arm", "{S}Shoulder", "{s}_shoulder"),
                ("{S}ForeArm", "{S}Arm", "{s}_elbow"),
                ("{S}Hand", "{S}ForeArm", "{s}_wrist"),
                ("{S}FingerBase", "{S}Hand", "{s}_middle1"),
                ("{c}Fingers", "{S}FingerBase", "{s}_middle2"),
                ("{c}Thumb", "{S}Hand", "{s}_thumb1"),
            ]
        ),
        BODY22,
    ),
    "biovision": (
        [
            ("Hips", None, "pelvis"),
            ("Ab", "Hips", "spine1"),
            ("Chest", "Ab", "spine3"),
            ("Neck", "Chest", "neck"),
            ("Head", "Neck", "head"),
        ]
        + _side(
            [
                ("{S}Collar", "Chest", "{s}_collar"),
                ("{S}Shoulder", "{S}Collar", "{s}_shoulder"),
                ("{S}Elbow", "{S}Shoulder", "{s}_elbow"),
                ("{S}Wrist", "{S}Elbow", "{s}_wrist"),
            ]
        )
        + _side(
            [
                ("{S}Hip", "Hips", "{s}_hip"),
                ("{S}Knee", "{S}Hip", "{s}_knee"),
                ("{S}Ankle", "{S}Knee", "{s}_ankle"),
                ("{S}Toes", "{S}Ankle", "{s}_foot"),
            ]
        ),
        [j for j in BODY22 if j != "spine2"],
    ),
    "mixamo": (
        [
            ("mixamorig:Hips", None, "pelvis"),
            ("mixamorig:Spine", "mixamorig:Hips", "spine1"),
            ("mixamorig:Spine1", "mixamorig:Spine", "spine2"),
            ("mixamorig:Spine2", "mixamorig:Spine1", "spine3"),
            ("mixamorig:Neck", "mixamorig:Spine2", "neck"),
            ("mixamorig:Head", "mixamorig:Neck", "head"),
            ("mixamorig:HeadTop_End", "mixamorig:Head", ("neck", "head", 2.0)),
        ]
        + _side(
            [
                ("mixamorig:{S}Shoulder", "mixamorig:Spine2", "{s}_collar"),
                ("mixamorig:{S}Arm", "mixamorig:{S}Shoulder", "{s}_shoulder"),
                ("mixamorig:{S}ForeArm", "mixamorig:{S}Arm", "{s}_elbow"),
                ("mixamorig:{S}Hand", "mixamorig:{S}ForeArm", "{s}_wrist"),
                ("mixamorig:{S}HandIndex1", "mixamorig:{S}Hand", "{s}_index1"),
                ("mixamorig:{S}HandIndex2", "mixamorig:{S}HandIndex1", "{s}_index2"),
                ("mixamorig:{S}HandIndex3", "mixamorig:{S}HandIndex2", "{s}_index3"),
                ("mixamorig:{S}HandThumb1", "mixamorig:{S}Hand", "{s}_thumb1"),
                ("mixamorig:{S}HandThumb2", "mixamorig:{S}HandThumb1", "{s}_thumb2"),
                ("mixamorig:{S}HandThumb3", "mixamorig:{S}HandThumb2", "{s}_thumb3"),
            ]
        )
        + _side(
            [
                ("mixamorig:{S}UpLeg", "mixamorig:Hips", "{s}_hip"),
                ("mixamorig:{S}Leg", "mixamorig:{S}UpLeg", "{s}_knee"),
                ("mixamorig:{S}Foot", "mixamorig:{S}Leg", "{s}_ankle"),
                ("mixamorig:{S}ToeBase", "mixamorig:{S}Foot", "{s}_foot"),
                ("mixamorig:{S}Toe_End", "mixamorig:{S}ToeBase", ("{s}_ankle", "{s}_foot", 1.5)),
            ]
        ),
        BODY22 + [f"{s}_{f}{i}" for s in ("left", "right") for f in ("index", "thumb") for i in (1, 2, 3)],
    ),
    "smplx": (
        [(n, None if p < 0 else SMPLX_JOINT_NAMES[p], n) for n, p in zip(SMPLX_JOINT_NAMES, SMPLX_PARENTS)],
        list(SMPLX_JOINT_NAMES),
    ),
    "smpl": (
        [(_smpl_name(n), None if p < 0 else _smpl_name(BODY22[p]), n) for n, p in zip(BODY22, SMPLX_PARENTS)],
        BODY22,
    ),
}


def bvh_from_spec(
    path: Path, spec: list[tuple], heads: np.ndarray, F: int = 6, seed: int = 0, a_pose_deg: float = 40.0
) -> Path:
    """A BVH of ``spec`` with the rest joints ``heads`` (SMPL-X order, metres) in centimetres, arms turned
    ``a_pose_deg`` down at the shoulders, random rotations (ZXY channels, as Boxing_Toes.bvh)."""
    idx = {n: i for i, n in enumerate(SMPLX_JOINT_NAMES)}
    pos = lambda p: (
        heads[idx[p]] if isinstance(p, str) else heads[idx[p[0]]] + p[2] * (heads[idx[p[1]]] - heads[idx[p[0]]])
    )  # noqa: E731
    names = [n for n, _, _ in spec]
    parents = [-1 if p is None else names.index(p) for _, p, _ in spec]
    rest = np.array([pos(p) for _, _, p in spec]) * 100.0
    for sgn, side in ((-1.0, "left"), (1.0, "right")):  # A-pose: the arm chains below each shoulder
        sh = heads[idx[f"{side}_shoulder"]] * 100.0
        R = Rotation.from_euler("z", sgn * a_pose_deg, degrees=True).as_matrix()
        below = [i for i, (_, _, p) in enumerate(spec) if _canon_side_arm(p, side)]
        rest[below] = (rest[below] - sh) @ R.T + sh
    ang = random_angles(F, len(names), seed)
    root = np.array([[0.0, 90.0, 0.0]]) + np.random.default_rng(seed + 1).normal(0, 5, (F, 3))
    return write_bvh(path, names, parents, rest, ang, root)


def _canon_side_arm(p, side: str) -> bool:
    name = p if isinstance(p, str) else p[0]
    arm = ("shoulder", "elbow", "wrist", "index", "middle", "pinky", "ring", "thumb")
    return name.startswith(side + "_") and any(a in name for a in arm)


def posed_joints(rig: Rig, m) -> np.ndarray:
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
    return pose_joints(rig, t(m.pose), t(m.root_rotation), t(m.root_translation)).numpy()


def posed_surface(template, rig: Rig, m) -> np.ndarray:
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
    T = skinning_transforms(rig, t(m.pose), t(m.root_rotation), t(m.root_translation))
    return lbs(
        t(template.vertices), torch.as_tensor(template.skin_indices.astype(np.int64)), t(template.skin_weights), T
    ).numpy()


def bone_cosines(rig: Rig, m, bvh, frames, bones) -> dict:
    """cos(angle) between each posed rig bone and the posed BVH bone of the matched joints.  -> {bone: [F]}"""
    P = posed_joints(rig, m)
    Pb = bvh_joint_positions(bvh, frames)
    to_b = dict(m.matched)
    out = {}
    for a, c in bones:
        vo = P[:, rig.joint_index(c)] - P[:, rig.joint_index(a)]
        vb = Pb[:, bvh.joint_index(to_b[c])] - Pb[:, bvh.joint_index(to_b[a])]
        out[(a, c)] = (vo * vb).sum(1) / (np.linalg.norm(vo, axis=1) * np.linalg.norm(vb, axis=1))
    return out


def euler_rig(base: Rig, axes_of) -> Rig:
    """``base``'s joints with three euler parameters per non-root joint about ``axes_of(joint index)`` [3, 3]
    (rows, in listed order)."""
    params = []
    groups: dict[str, list[str]] = {}
    for j, jt in enumerate(base.joints):
        if jt.parent is None:
            continue
        for k, ax in enumerate(axes_of(j)):
            p = PoseParam(f"{jt.name}.e{k}", jt.name, "euler", tuple(float(v) for v in ax))
            params.append(p)
            groups.setdefault(GROUP_OF[jt.name], []).append(p.name)
    rig = Rig([Joint(j.name, j.parent, j.head) for j in base.joints], params, groups)
    return rig_from_json(rig.to_json(), "test rig")


PRINCIPAL = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # rz, ry, rx


def _quiet(fn, *a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UndrivenJointsWarning)
        return fn(*a, **k)


# --------------------------------------------------------------------------- the name maps
def test_builtin_maps_load_and_detect():
    for c in CONVENTIONS:
        m = convention_map(c)
        assert len(m) >= 20 and "pelvis" in m.values()
    box = ["Hips", "Ab", "Chest", "Neck", "Head", "LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist", "LeftHip"]
    assert detect_convention(box) == "biovision"
    assert detect_convention(["Hips", "LHipJoint", "LowerBack", "Spine", "Spine1", "Neck1", "LeftArm"]) == "cmu"
    assert detect_convention(["mixamorig:Hips", "mixamorig:Spine2", "mixamorig:LeftHandIndex1"]) == "mixamo"
    assert detect_convention(list(SMPLX_JOINT_NAMES)) == "smplx"
    assert detect_convention(["a", "b"]) is None


@pytest.mark.parametrize("convention", list(SPECS))
def test_each_name_map_drives_the_smplx_rig(convention, body, tmp_path):
    """A BVH written with the convention's names (A-pose rest, random rotations) drives exactly the expected
    SMPL-X joints, and every limb bone of the posed rig points along the posed BVH bone."""
    template, rig = body
    spec, expected = SPECS[convention]
    bvh = read_bvh(bvh_from_spec(tmp_path / f"{convention}.bvh", spec, rig.heads().astype(np.float64)))
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        m = retarget_bvh(bvh, rig)
    assert sorted(r for r, _ in m.matched) == sorted(expected)
    undriven = sorted(set(SMPLX_JOINT_NAMES[1:]) - set(expected))
    assert sorted(m.undriven) == undriven
    msgs = [str(x.message) for x in w if issubclass(x.category, UndrivenJointsWarning)]
    assert (len(msgs) == 1 and all(n in msgs[0] for n in undriven)) if undriven else not msgs
    for bone, cos in bone_cosines(rig, m, bvh, None, LIMB_BONES).items():
        assert cos.min() > BONE_COS, (convention, bone, cos.min())
    assert np.abs(m.pose).max() > 0.3  # the motion moves the rig


@pytest.mark.skipif(not BOXING.exists(), reason="assimp-testmodels not installed")
def test_boxing_toes_drives_limbs_of_smplx_and_cmu_rigs(body):
    """The issue's case: Boxing_Toes.bvh (Biovision names) drove only hips, neck and head of a CMU-named rig."""
    from gsavatar.motion.bvh import bvh_rest_positions
    from gsavatar.synth.body import make_rig

    _, rig = body
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the file's one extra frame row
        box = read_bvh(BOXING)
    frames = slice(0, 3000, 60)
    with pytest.warns(UndrivenJointsWarning, match=r"body joints \['spine2'\]"):
        m = retarget_bvh(box, rig, frames=frames)
    assert len(m.matched) == 21
    for bone, cos in bone_cosines(rig, m, box, frames, LIMB_BONES).items():
        assert cos.min() > BONE_COS, bone
    # a CMU-named rig (the CMU skeleton itself, metres)
    cmu = read_bvh(BOXING.with_name("01_01.bvh"))
    crig = make_rig(cmu.names, cmu.parents.tolist(), bvh_rest_positions(cmu) * 0.056)
    with pytest.warns(UndrivenJointsWarning, match="LHipJoint"):
        mc = retarget_bvh(box, crig, frames=frames)
    drv = dict(mc.matched)
    assert drv["LeftArm"] == "LeftShoulder" and drv["LeftShoulder"] == "LeftCollar" and drv["LeftUpLeg"] == "LeftHip"
    cmu_bones = [
        (f"{s}{a}", f"{s}{b}")
        for s in ("Left", "Right")
        for a, b in (("UpLeg", "Leg"), ("Leg", "Foot"), ("Arm", "ForeArm"), ("ForeArm", "Hand"))
    ]
    for bone, cos in bone_cosines(crig, mc, box, frames, cmu_bones).items():
        assert cos.min() > BONE_COS, bone


# --------------------------------------------------------------------------- any rig: same surface
def _rotated_axes(seed: int):
    rng = np.random.default_rng(seed)
    Q = Rotation.random(55, random_state=rng).as_matrix()
    return lambda j: PRINCIPAL @ Q[j].T  # rows: Q z, Q y, Q x


@pytest.mark.parametrize("source", ["written", "boxing"])
def test_same_surface_on_principal_rotated_and_axis_angle_rigs(source, body, tmp_path):
    """The same BVH onto the SMPL-X skeleton with euler rz/ry/rx parameters, with euler parameters about each
    joint's own rotated axes (a random rotation per joint), and with axis-angle parameters: the LBS surfaces
    agree (< 1e-4 m), while the euler angles of the two euler rigs differ (angles are not copied)."""
    template, rig_aa = body
    if source == "boxing":
        if not BOXING.exists():
            pytest.skip("assimp-testmodels not installed")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            bvh = read_bvh(BOXING)
        frames = slice(0, 3000, 150)
    else:
        bvh = read_bvh(bvh_from_spec(tmp_path / "m.bvh", SPECS["cmu"][0], rig_aa.heads().astype(np.float64), F=8))
        frames = None
    rig_p = euler_rig(rig_aa, lambda j: PRINCIPAL)
    rig_r = euler_rig(rig_aa, _rotated_axes(3))
    ms = {
        name: _quiet(retarget_bvh, bvh, r, frames=frames)
        for name, r in (("aa", rig_aa), ("principal", rig_p), ("rotated", rig_r))
    }
    X = {
        name: posed_surface(template, r, ms[name])
        for name, r in (("aa", rig_aa), ("principal", rig_p), ("rotated", rig_r))
    }
    rest_move = np.linalg.norm(X["aa"] - X["aa"][:, :1].mean(), axis=-1).max()
    assert rest_move > 0.1
    for name in ("principal", "rotated"):
        err = np.abs(X[name] - X["aa"]).max()
        assert err < SURFACE_TOL_M, (name, err)
    assert np.abs(ms["principal"].pose - ms["rotated"].pose).max() > 0.3
    np.testing.assert_array_equal(ms["principal"].root_translation, ms["rotated"].root_translation)


def test_pose_from_local_rotations_round_trips_any_parameters():
    """Rotations made by a rig's own parameters are recovered exactly for every kind of joint: principal and
    proper (ZXZ) euler, orthogonal rotated axes (right- and left-handed), non-orthogonal axes, two orthogonal
    axes, a hinge, axis-angle, axis-angle mixed with euler."""
    rng = np.random.default_rng(5)
    Q = Rotation.random(random_state=rng).as_matrix()
    n = lambda v: tuple((np.asarray(v, float) / np.linalg.norm(v)).tolist())  # noqa: E731
    kinds = {
        "zyx": [("euler", (0, 0, 1)), ("euler", (0, 1, 0)), ("euler", (1, 0, 0))],
        "zxz": [("euler", (0, 0, 1)), ("euler", (1, 0, 0)), ("euler", (0, 0, 1))],
        "signed": [("euler", (0, -1, 0)), ("euler", (1, 0, 0)), ("euler", (0, 0, -1))],
        "rotated": [("euler", n(Q[:, 0])), ("euler", n(Q[:, 1])), ("euler", n(Q[:, 2]))],
        "rotated_left": [("euler", n(Q[:, 0])), ("euler", n(Q[:, 1])), ("euler", n(-Q[:, 2]))],
        "skew": [("euler", n([1, 0.3, 0])), ("euler", n([0.2, 1, 0.1])), ("euler", n([0, 0.4, 1]))],
        "two": [("euler", n(Q[:, 1])), ("euler", n(Q[:, 2]))],
        "hinge": [("euler", n([0.3, -0.2, 1.0]))],
        "aa": [("axis_angle", None)],
        "mixed": [("euler", (1, 0, 0)), ("axis_angle", None)],
    }
    joints = [Joint("root", None, (0.0, 0.0, 0.0))]
    params = []
    for i, (k, plist) in enumerate(kinds.items()):
        joints.append(Joint(k, "root", (0.1 * i, 0.0, 0.0)))
        params += [PoseParam(f"{k}.{m}", k, kind, ax) for m, (kind, ax) in enumerate(plist)]
    rig = rig_from_json(Rig(joints, params, {"torso_head": [p.name for p in params]}).to_json(), "round trip")
    pose = rng.uniform(-1.2, 1.2, (40, rig.pose_dim))
    L = pose_to_local_rotations(torch.as_tensor(pose), rig).numpy()
    back = pose_from_local_rotations(L, rig)
    L2 = pose_to_local_rotations(torch.as_tensor(back), rig).numpy()
    err = np.abs(L2 - L).max(axis=(0, 2, 3))
    assert err.max() < 1e-6, dict(zip([j.name for j in joints], err))
    # a hinge given a rotation it cannot make gets the closest one about its axis (a 1-D search agrees)
    R = Rotation.random(5, random_state=rng).as_matrix()
    Lh = np.tile(np.eye(3), (5, len(joints), 1, 1))
    Lh[:, rig.joint_index("hinge")] = R
    slot = int(np.flatnonzero(rig.slot_joints() == rig.joint_index("hinge"))[0])
    t = pose_from_local_rotations(Lh, rig)[:, slot]
    ax = np.array(n([0.3, -0.2, 1.0]))
    grid = np.linspace(-np.pi, np.pi, 20001)
    Rg = Rotation.from_rotvec(grid[:, None] * ax).as_matrix()  # [G, 3, 3]
    for f in range(5):
        best = grid[int(np.argmax(np.einsum("gij,ij->g", Rg, R[f])))]  # tr(R_g^T R)
        assert abs(np.angle(np.exp(1j * (t[f] - best)))) < 1e-3


# --------------------------------------------------------------------------- undriven joints, joint maps
def _without(spec: list[tuple], drop: tuple[str, ...]) -> list[tuple]:
    """``spec`` without the joints whose canonical position names contain any of ``drop`` (and their subtrees)."""
    gone: set[str] = set()
    out = []
    for n, p, pos in spec:
        key = pos if isinstance(pos, str) else pos[1]
        if p in gone or any(d in key for d in drop):
            gone.add(n)
            continue
        out.append((n, p, pos))
    return out


def test_undriven_joints_warn_then_refuse(body, tmp_path):
    _, rig = body
    heads = rig.heads().astype(np.float64)
    no_arms = _without(SPECS["cmu"][0], ("collar",))  # 8 of 21 body joints undriven: a warning naming them
    bvh = read_bvh(bvh_from_spec(tmp_path / "no_arms.bvh", no_arms, heads))
    with pytest.warns(UndrivenJointsWarning) as rec:
        m = retarget_bvh(bvh, rig)
    msg = str(rec[0].message)
    arms = [f"{s}_{j}" for s in ("left", "right") for j in ("collar", "shoulder", "elbow", "wrist")]
    assert all(a in msg for a in arms) and "no_arms.bvh" in msg
    assert set(arms) <= set(m.undriven)
    no_limbs = _without(no_arms, ("_hip",))  # 16 of 21: refused, naming the file and the way out
    bvh = read_bvh(bvh_from_spec(tmp_path / "no_limbs.bvh", no_limbs, heads))
    with pytest.raises(SchemaError, match=r"no_limbs\.bvh: joints: 16 of the rig's 21 body joints .*--joint-map"):
        retarget_bvh(bvh, rig)
    assert _quiet(retarget_bvh, bvh, rig, max_undriven=1.0).pose.shape[1] == rig.pose_dim  # the threshold is a knob


def test_joint_map_file_drives_custom_names(body, tmp_path):
    """Unknown names are refused (the root has no counterpart); a --joint-map file maps them; its errors name
    the file and the key."""
    from gsavatar.drive.motion import load_driving_motion

    _, rig = body
    base = SPECS["smplx"][0][:22]
    new = {n: f"b{i:02d}" for i, (n, _, _) in enumerate(base)}
    spec = [(new[n], None if p is None else new[p], pos) for n, p, pos in base]
    path = bvh_from_spec(tmp_path / "custom.bvh", spec, rig.heads().astype(np.float64))
    bvh = read_bvh(path)
    with pytest.raises(SchemaError, match="rig root 'pelvis' has no BVH joint"):
        retarget_bvh(bvh, rig)
    jm = tmp_path / "map.json"
    jm.write_text(json.dumps({pos: name for name, _, pos in spec} | {"jaw": None}))
    names = read_joint_map(jm)
    m = _quiet(retarget_bvh, bvh, rig, name_map=names, name_map_file=jm)
    assert len(m.matched) == 22
    for bone, cos in bone_cosines(rig, m, bvh, None, LIMB_BONES).items():
        assert cos.min() > BONE_COS, bone
    dm = _quiet(load_driving_motion, path, rig, 15.0, joint_map=jm)  # the driving loader passes it on
    assert dm.pose.shape == (3, rig.pose_dim)  # 6 frames at 30 fps -> 15 fps
    bad = {"nope": "b00"}, {"pelvis": "zz"}, {"pelvis": 3}, {"pelvis": "b00", "spine1": "b00"}
    for obj, err in zip(
        bad,
        (
            "rig has no joint 'nope'",
            "motion has no joint 'zz'",
            "expected a motion joint name",
            "already given to rig joint 'pelvis'",
        ),
    ):
        jm.write_text(json.dumps(obj))
        with pytest.raises(SchemaError, match=err) as e:
            retarget_bvh(bvh, rig, name_map=read_joint_map(jm), name_map_file=jm)
        assert str(jm) in str(e.value)
    jm.write_text('{"pelvis": "b00", "pelvis": "b01"}')  # the strict reader
    with pytest.raises(SchemaError, match="key given twice"):
        read_joint_map(jm)
    with pytest.raises(ValueError, match="BVH motions only"):
        load_driving_motion(tmp_path / "map.json", rig, joint_map=jm)


def test_match_overrides_take_precedence():
    m = match_joints(["Hips", "LeftUpLeg", "LeftLeg"], ["Hips", "LeftHip", "LeftKnee", "X"], {"LeftLeg": "X"})
    assert m.rig_to_motion == {0: 0, 1: 1, 2: 3}
    assert (m.rig_convention, m.motion_convention) == ("cmu", "biovision")
