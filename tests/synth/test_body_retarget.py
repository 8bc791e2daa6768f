"""Anny body (Template + Rig) and CMU BVH retargeting onto it.

The body tests need the ``anny`` package; the first run builds Anny's model data into
``$ANNY_CACHE_DIR`` (default ``<repo>/.cache/anny``, tests/conftest.py): ~70-80 s and ~0.7 GB, later
runs reuse it (< 1 s). The retargeting tests without anny use a rig made from the BVH
skeleton itself, re-posed into an A-pose so that the rest alignment is exercised.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gsavatar.data_schema.rig import BODY_GROUPS
from gsavatar.data_schema.template import validate_template
from gsavatar.geometry.lbs import lbs, pose_joints, pose_to_local_rotations, skinning_transforms
from gsavatar.motion.bvh import bvh_joint_positions, bvh_rest_positions, read_bvh
from gsavatar.motion.retarget import CMU_NAME_MAP, motion_from_bvh_file, retarget_bvh
from conftest import anny_cache_dir

CMU_01_01 = Path("/usr/share/assimp/models/BVH/01_01.bvh")
ANNY_CACHE = anny_cache_dir()
DECIMATE = 3000

# (parent, child) bones whose direction must follow the mocap
MAJOR_BONES = [
    ("LeftArm", "LeftForeArm"), ("RightArm", "RightForeArm"),  # upper arms
    ("LeftForeArm", "LeftHand"), ("RightForeArm", "RightHand"),  # forearms
    ("LeftUpLeg", "LeftLeg"), ("RightUpLeg", "RightLeg"),  # thighs
    ("LeftLeg", "LeftFoot"), ("RightLeg", "RightFoot"),  # shins
    ("LowerBack", "Spine"), ("Spine", "Spine1"),  # spine
]  # fmt: skip


@pytest.fixture(scope="session")
def cmu():
    if not CMU_01_01.exists():
        pytest.skip(f"{CMU_01_01} not installed (apt package assimp-testmodels)")
    return read_bvh(CMU_01_01)


@pytest.fixture(scope="session")
def anny_body():
    pytest.importorskip("anny")
    from gsavatar.synth.body import build_anny_body

    ANNY_CACHE.mkdir(parents=True, exist_ok=True)
    full = build_anny_body(ANNY_CACHE)
    dec = build_anny_body(ANNY_CACHE, decimate_to=DECIMATE)
    return {"full": full, "dec": dec}


def _bone_cos(P_ours, names, Pb, bvh, bones, name_map=CMU_NAME_MAP):
    out = {}
    for a, c in bones:
        vo = P_ours[:, names.index(c)] - P_ours[:, names.index(a)]
        vb = Pb[:, bvh.names.index(name_map.get(c, c))] - Pb[:, bvh.names.index(name_map.get(a, a))]
        out[(a, c)] = (vo * vb).sum(1) / (np.linalg.norm(vo, axis=1) * np.linalg.norm(vb, axis=1))
    return out


def _joints(rig, m):
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float64)  # noqa: E731
    return pose_joints(rig, t(m.pose), t(m.root_rotation), t(m.root_translation)).numpy()


# --------------------------------------------------------------------------------------
# the body
# --------------------------------------------------------------------------------------
def test_anny_template_and_rig(anny_body):
    t, rig = anny_body["full"]
    V, F = len(t.vertices), len(t.faces)
    assert 13000 < V < 14000 and 26000 < F < 28000, (V, F)  # 13492 / 26972 with anny 0.6.2
    validate_template(t, rig.num_joints, Path("anny"))
    # skin weights: K=4, normalised, valid joints
    assert t.skin_weights.shape == (V, 4) and t.skin_indices.shape == (V, 4)
    np.testing.assert_allclose(t.skin_weights.sum(1), 1.0, atol=1e-5)
    assert t.skin_weights.min() >= 0 and 0 <= t.skin_indices.min() and t.skin_indices.max() < rig.num_joints
    # per-corner UVs in [0, 1]
    assert t.uvs is not None and t.face_uvs is not None and t.face_uvs.shape == (F, 3)
    assert t.uvs.min() >= 0 and t.uvs.max() <= 1 and t.face_uvs.max() < len(t.uvs)
    # frame: metres, Y up, feet on y=0, pelvis at x=z=0, facing +Z, left on +X
    h = rig.heads()
    j = rig.joint_index
    assert t.vertices[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    assert 1.5 < t.vertices[:, 1].max() < 1.9
    np.testing.assert_allclose(h[0, [0, 2]], 0.0, atol=1e-6)
    assert h[j("LeftArm"), 0] > 0.1 and h[j("RightArm"), 0] < -0.1
    assert h[j("LeftToeBase"), 2] > h[j("LeftFoot"), 2] + 0.05  # toes point to +Z
    assert h[j("Head"), 1] > h[j("Neck"), 1] > h[j("Spine1"), 1] > h[0, 1]
    # face mask: non-empty, < 10 % of the UV square, and on the front of the head
    m = t.face_uv_mask
    assert m is not None and m.shape == (256, 256) and m.dtype == bool
    assert 0.01 < m.mean() < 0.10, m.mean()
    cuv = t.corner_uvs.mean(1)
    rows = np.clip(((1 - cuv[:, 1]) * 256).astype(int), 0, 255)
    cols = np.clip((cuv[:, 0] * 256).astype(int), 0, 255)
    inside = m[rows, cols]
    cen = t.vertices[t.faces].mean(1)
    assert inside.sum() > 1000
    assert np.all(cen[inside, 1] > h[j("Neck1"), 1] - 0.02)  # nothing below the neck
    assert np.median(cen[inside, 2]) > h[j("Head"), 2] + 0.05  # in front of the head joint
    back = cen[:, 2] < h[j("Head"), 2] - 0.03
    assert not np.any(inside & back & (cen[:, 1] > h[j("Head"), 1]))  # no back of the head


def test_anny_rig_params_and_groups(anny_body):
    _, rig = anny_body["full"]
    assert rig.num_joints == 31
    names = [jt.name for jt in rig.joints]
    cmu_names = {CMU_NAME_MAP.get(n, n) for n in names}
    assert len(cmu_names) == 31  # every anny cmu_mb bone has a CMU BVH joint
    assert rig.joints[0].name == "Hips" and rig.joints[0].parent is None
    assert rig.pose_dim == 90 and len(rig.params) == 90  # 30 non-root joints x (rz, ry, rx)
    assert not any(p.joint == "Hips" for p in rig.params)
    for k in range(0, 90, 3):
        trio = rig.params[k : k + 3]
        assert [p.name.split(".")[-1] for p in trio] == ["rz", "ry", "rx"]
        assert [p.axis for p in trio] == [(0.0, 0.0, 1.0), (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)]
    grouped = [n for g in BODY_GROUPS for n in rig.groups[g]]
    assert sorted(grouped) == sorted(p.name for p in rig.params)  # each param in exactly one group
    counts = {g: len(rig.groups[g]) for g in BODY_GROUPS}
    assert counts == {
        "torso_head": 18,
        "left_leg": 15,
        "right_leg": 15,
        "left_arm": 9,
        "right_arm": 9,
        "left_hand": 12,
        "right_hand": 12,
    }
    assert "LeftForeArm.rx" in rig.groups["left_arm"] and "RThumb.rz" in rig.groups["right_hand"]
    assert "LHipJoint.ry" in rig.groups["left_leg"] and "Neck1.rx" in rig.groups["torso_head"]
    assert len(rig.slot_groups()) == 90


def test_decimated_template(anny_body):
    (full, _), (t, rig) = anny_body["full"], anny_body["dec"]
    V = len(t.vertices)
    assert abs(V - DECIMATE) <= 0.1 * DECIMATE, V
    validate_template(t, rig.num_joints, Path("anny-dec"))
    np.testing.assert_allclose(t.skin_weights.sum(1), 1.0, atol=1e-5)
    assert t.uvs.min() >= 0 and t.uvs.max() <= 1 and t.face_uvs.shape == t.faces.shape
    # no triangle straddles a UV seam (the full mesh's longest UV edge is ~0.06)
    cuv = t.corner_uvs
    longest = np.linalg.norm(cuv - np.roll(cuv, 1, axis=1), axis=2).max(1)
    assert longest.max() < 0.15, longest.max()
    # weights follow the surface: dominant joint agrees with the nearest full-mesh vertex
    from scipy.spatial import cKDTree

    _, nn = cKDTree(full.vertices).query(t.vertices)
    agree = t.skin_indices[:, 0] == full.skin_indices[nn, 0]
    assert agree.mean() > 0.9, agree.mean()
    # UVs follow the surface: corner UV close to the nearest full-mesh vertex's UV (same chart)
    full_vert_uv = np.zeros((len(full.vertices), 2), np.float32)
    full_vert_uv[full.faces.ravel()] = full.corner_uvs.reshape(-1, 2)
    d = np.linalg.norm(t.uvs[t.face_uvs].reshape(-1, 2) - full_vert_uv[nn[t.faces.ravel()]], axis=1)
    assert np.median(d) < 0.02
    assert t.face_uv_mask is not None and t.face_uv_mask.sum() == full.face_uv_mask.sum()


def test_body_cache_returns_the_same_body(anny_body):
    # How fast a cached body loads is not asserted here (timings live in benchmarks/).
    from gsavatar.synth.body import build_anny_body

    t, rig = build_anny_body(ANNY_CACHE, decimate_to=DECIMATE)
    assert len(t.vertices) == len(anny_body["dec"][0].vertices)
    np.testing.assert_array_equal(rig.heads(), anny_body["dec"][1].heads())


# --------------------------------------------------------------------------------------
# retargeting onto the anny rig
# --------------------------------------------------------------------------------------
def test_retarget_cmu_onto_anny_bone_directions(anny_body, cmu):
    _, rig = anny_body["dec"]
    frames = slice(0, cmu.num_frames, 8)  # 344 frames spanning the whole clip
    m = retarget_bvh(cmu, rig, rig.heads(), None, frames)
    F = len(range(*frames.indices(cmu.num_frames)))
    assert m.pose.shape == (F, 90) and m.pose.dtype == np.float32
    assert m.root_rotation.shape == (F, 3) and m.root_translation.shape == (F, 3)
    assert m.fps == pytest.approx(15.0)
    assert np.all(np.isfinite(m.pose)) and np.abs(m.pose).max() < 2 * np.pi
    P = _joints(rig, m)
    Pb = bvh_joint_positions(cmu, frames)
    names = [jt.name for jt in rig.joints]
    for bone, cos in _bone_cos(P, names, Pb, cmu, MAJOR_BONES).items():
        assert cos.min() > 0.98, (bone, cos.min())
    # root follows the mocap root (scaled), feet stay on the ground
    scale = np.linalg.norm(P[:, 0] - P[:1, 0], axis=1)[1:] / np.linalg.norm(Pb[:, 0] - Pb[:1, 0], axis=1)[1:].clip(1e-9)
    moving = np.linalg.norm(Pb[:, 0] - Pb[:1, 0], axis=1)[1:] > 5
    assert np.ptp(scale[moving]) < 1e-3 and 0.04 < scale[moving].mean() < 0.08  # ~0.056 m per CMU unit
    np.testing.assert_allclose(P[0, 0, [0, 2]], 0.0, atol=1e-5)  # starts at x = z = 0
    feet = [rig.joint_index(n) for n in ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")]
    lowest = P[:, feet, 1].min(1)
    assert lowest.min() > rig.heads()[feet, 1].min() - 0.02  # never through the floor
    assert np.median(lowest) < 0.1  # mostly standing on it


def test_retarget_resampling_120_to_30(anny_body, cmu):
    _, rig = anny_body["dec"]
    m120 = retarget_bvh(cmu, rig, None, None, slice(100, 400))
    m30 = retarget_bvh(cmu, rig, None, 30.0, slice(100, 400))
    assert m120.fps == 120.0 and m30.fps == 30.0
    assert len(m120.pose) == 300 and len(m30.pose) == 75
    R120 = pose_to_local_rotations(torch.as_tensor(m120.pose, dtype=torch.float64), rig)
    R30 = pose_to_local_rotations(torch.as_tensor(m30.pose, dtype=torch.float64), rig)
    P120, P30 = _joints(rig, m120), _joints(rig, m30)
    for k in (0, 4, 17):
        np.testing.assert_allclose(R30[k], R120[4 * k], atol=1e-5)
        np.testing.assert_allclose(P30[k], P120[4 * k], atol=1e-5)
        np.testing.assert_allclose(m30.root_translation[k], m120.root_translation[4 * k], atol=1e-6)
        np.testing.assert_allclose(m30.root_rotation[k], m120.root_rotation[4 * k], atol=1e-5)
    # a rate that is not a divisor: in-between frames lie between their neighbours
    m50 = retarget_bvh(cmu, rig, None, 50.0, slice(100, 400))
    assert len(m50.pose) == 1 + int(299 / 120 * 50)
    P50 = _joints(rig, m50)
    k = 1  # t = 0.02 s = source frame 2.4
    lo, hi = P120[2], P120[3]
    assert np.all(P50[k] >= np.minimum(lo, hi) - 2e-3) and np.all(P50[k] <= np.maximum(lo, hi) + 2e-3)


def test_motion_from_bvh_file(anny_body):
    if not CMU_01_01.exists():
        pytest.skip("no CMU BVH")
    _, rig = anny_body["dec"]
    m = motion_from_bvh_file(CMU_01_01, rig, fps_out=30, start=16, count=50)
    assert m.pose.shape == (50, 90) and m.fps == 30
    ref = retarget_bvh(read_bvh(CMU_01_01), rig, None, 30, slice(16, None))
    np.testing.assert_allclose(m.pose[:50], ref.pose[:50], atol=1e-5)
    np.testing.assert_allclose(m.root_translation, ref.root_translation[:50], atol=1e-6)


def test_skinned_body_stays_above_floor(anny_body, cmu):
    t, rig = anny_body["dec"]
    m = retarget_bvh(cmu, rig, None, 10.0, None)
    tt = lambda x: torch.as_tensor(np.asarray(x), dtype=torch.float32)  # noqa: E731
    T = skinning_transforms(rig, tt(m.pose), tt(m.root_rotation), tt(m.root_translation))
    X = lbs(tt(t.vertices), torch.as_tensor(t.skin_indices).long(), tt(t.skin_weights), T).numpy()
    low = X[..., 1].min(1)
    assert low.min() > -0.05 and np.median(low) < 0.05, (low.min(), np.median(low))
    height = X[..., 1].max(1) - low
    assert height.max() < 2.0  # no exploded limbs


# --------------------------------------------------------------------------------------
# retargeting without anny: the BVH skeleton itself, re-posed into an A-pose
# --------------------------------------------------------------------------------------
def test_retarget_onto_a_posed_copy_of_the_bvh_skeleton(cmu):
    from gsavatar.synth.body import make_rig

    names = [{v: k for k, v in CMU_NAME_MAP.items()}.get(n, n) for n in cmu.names]
    rest = bvh_rest_positions(cmu) * 0.05644  # CMU units -> metres
    # rotate both arm chains 45 degrees down about +-Z at the shoulders (T-pose -> A-pose)
    from scipy.spatial.transform import Rotation

    heads = rest.copy()
    for side, sgn in (("Left", -1), ("Right", 1)):
        s = cmu.joint_index(f"{side}Arm")
        Rz = Rotation.from_euler("z", sgn * 45, degrees=True).as_matrix()
        sub = [j for j in range(cmu.num_joints) if _is_descendant(cmu.parents, j, s)]
        heads[sub] = (heads[sub] - heads[s]) @ Rz.T + heads[s]
    heads[:, 1] -= heads[:, 1].min() - 0.05
    rig = make_rig(names, cmu.parents.tolist(), heads)
    frames = slice(0, 2752, 11)
    m = retarget_bvh(cmu, rig, None, None, frames)
    P = _joints(rig, m)
    Pb = bvh_joint_positions(cmu, frames)
    for bone, cos in _bone_cos(P, names, Pb, cmu, MAJOR_BONES).items():
        assert cos.min() > 0.999, (bone, cos.min())
    assert m.pose[:, :3].std() > 0  # something moves


def _is_descendant(parents, j, anc):
    while j >= 0:
        if j == anc:
            return True
        j = int(parents[j])
    return False
