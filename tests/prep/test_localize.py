from __future__ import annotations

import numpy as np
import pytest

from gsavatar.data_schema.localization import LocalizationMasks
from gsavatar.prep.localize import (
    active_per_point,
    build_localization,
    dilate_mask,
    face_mask,
    geodesic_anchor_adjacency,
    joint_reach,
    knn_anchor_adjacency,
    pose_masks,
    wrist_joint_of_group,
)
from gsavatar.utils.errors import SchemaError
from gsavatar.prep.sample_points import build_hierarchy
from prep_fixtures import arm_rig, arm_template


@pytest.fixture(scope="module")
def setup():
    rig = arm_rig()
    t = arm_template()
    h = build_hierarchy(t, n_anchors=60, n_control=300, n_gaussians=3000, seed=1, min_candidates=3000)
    return rig, t, h


def _col(rig, name):
    names = [p.name for p in rig.params]
    return rig.slot_params().index(names.index(name))


def _skinned(anchors, rig, joints):
    ids = [rig.joint_index(j) for j in joints]
    return np.any(np.isin(anchors.skin_indices, ids) & (anchors.skin_weights > 0), axis=1)


def test_forearm_param_is_local(setup):
    rig, _, h = setup
    a = h.anchors
    m = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=False)
    for slot in range(_col(rig, "LeftForeArm.r"), _col(rig, "LeftForeArm.r") + 3):
        col = m[:, slot]
        # own joint + the child whose parent it is (LeftHand)
        np.testing.assert_array_equal(col, _skinned(a, rig, ["LeftForeArm", "LeftHand"]))
        x = a.position[col, 0]
        # blend zones ±0.05 around the joints (0.4 .. 0.85) plus one 2 cm mesh ring of barycentric transfer
        assert col.sum() > 3 and x.min() >= 0.33 and x.max() <= 0.92
        assert not np.any(col[(a.position[:, 0] < 0.3) | (a.position[:, 0] > 0.95)])
    # ancestor_levels=0: only anchors skinned to the forearm itself
    m0 = pose_masks(
        a.skin_indices, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=False, ancestor_levels=0
    )
    np.testing.assert_array_equal(m0[:, _col(rig, "LeftForeArm.r")], _skinned(a, rig, ["LeftForeArm"]))
    # root-near params stay local too
    sp = m[:, _col(rig, "Spine.rx")]
    assert sp.any() and a.position[sp, 0].max() < 0.47  # torso + its child LeftArm (upper arm)
    # with dilation it grows, but stays near the forearm
    md = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=True, hand_uses_wrist=False)
    col_d = md[:, _col(rig, "LeftForeArm.r")]
    assert col_d.sum() > m[:, _col(rig, "LeftForeArm.r")].sum()
    assert a.position[col_d, 0].min() > 0.15 and not np.any(col_d[a.position[:, 0] < 0.1])


def test_joint_reach():
    rig = arm_rig()
    R = joint_reach(rig, 1)
    j = rig.joint_index
    assert R[j("LeftHand"), j("LeftForeArm")] and R[j("LeftHand"), j("LeftHand")]
    assert not R[j("LeftHand"), j("LeftArm")] and not R[j("LeftForeArm"), j("LeftHand")]
    R2 = joint_reach(rig, 99)
    assert R2[j("LeftFinger"), j("Hips")]


def test_dilation_adds_exactly_the_neighbours(setup):
    rig, _, h = setup
    a = h.anchors
    A = len(a)
    # a synthetic skinning: every anchor on Spine, anchor 17 on LeftFinger
    si = np.full((A, 2), rig.joint_index("Spine"), np.int32)
    sw = np.tile(np.array([[1.0, 0.0]], np.float32), (A, 1))
    si[17, 0] = rig.joint_index("LeftFinger")
    adj = knn_anchor_adjacency(a.position, 6)
    assert np.array_equal(adj, adj.T) and not adj.diagonal().any()
    base = pose_masks(si, sw, rig, a.position, dilate=False, hand_uses_wrist=False)
    dil = pose_masks(si, sw, rig, a.position, dilate=True, hand_uses_wrist=False, k_neighbors=6)
    c = _col(rig, "LeftFinger.rx")
    assert np.flatnonzero(base[:, c]).tolist() == [17]
    # neighbours: 17's 6 nearest plus every anchor that has 17 among its 6 nearest
    d = np.linalg.norm(a.position[:, None] - a.position[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    knn = np.argsort(d, axis=1)[:, :6]
    expect = {17} | set(knn[17].tolist()) | {i for i in range(A) if 17 in knn[i]}
    assert set(np.flatnonzero(dil[:, c]).tolist()) == expect
    # general: explicit loops
    ref = base.copy()
    for i in range(A):
        for n in np.flatnonzero(adj[i]):
            ref[i] |= base[n]
    np.testing.assert_array_equal(dil, ref)
    np.testing.assert_array_equal(dilate_mask(base, adj), ref)


def test_hand_params_reuse_wrist_mask(setup):
    rig, _, h = setup
    a = h.anchors
    assert rig.joints[wrist_joint_of_group(rig, "left_hand")].name == "LeftHand"
    plain = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=False)
    hand = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=True)
    wrist = plain[:, _col(rig, "LeftHand.rx")]  # wrist param's own mask
    np.testing.assert_array_equal(wrist, _skinned(a, rig, ["LeftHand", "LeftFinger"]))
    for p in rig.groups["left_hand"]:
        np.testing.assert_array_equal(hand[:, _col(rig, p)], wrist)
    # finger param alone would only see the finger region
    assert plain[:, _col(rig, "LeftFinger.rx")].sum() < wrist.sum()
    # non-hand params untouched
    others = [_col(rig, p) for p in rig.groups["left_arm"] + rig.groups["torso_head"]]
    np.testing.assert_array_equal(hand[:, others], plain[:, others])
    # the same after dilation
    hd = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=True, hand_uses_wrist=True)
    pd = pose_masks(a.skin_indices, a.skin_weights, rig, a.position, dilate=True, hand_uses_wrist=False)
    for p in rig.groups["left_hand"]:
        np.testing.assert_array_equal(hd[:, _col(rig, p)], pd[:, _col(rig, "LeftHand.rx")])
    # a finger with no anchor at all still gets the wrist region
    si = a.skin_indices.copy()
    si[si == rig.joint_index("LeftFinger")] = rig.joint_index("LeftHand")
    m = pose_masks(si, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=False)
    assert not m[:, _col(rig, "LeftFinger.rx")].any()
    m = pose_masks(si, a.skin_weights, rig, a.position, dilate=False, hand_uses_wrist=True)
    assert m[:, _col(rig, "LeftFinger.rx")].sum() == m[:, _col(rig, "LeftHand.rx")].sum() > 0


def test_face_mask_hand_checked(setup):
    _, t, h = setup
    # fixture mask [32, 16]: True for rows 0..7 (v > 0.75) and cols 0..7 (u < 0.5)
    uv = np.array([[0.1, 0.9], [0.6, 0.9], [0.1, 0.7], [0.49, 0.76], [0.5, 0.8], [0.0, 1.0], [1.0, 0.0], [0.3, 0.74]])
    np.testing.assert_array_equal(face_mask(uv, t.face_uv_mask), [True, False, False, True, False, True, False, False])
    assert not face_mask(uv, None).any()
    fm = face_mask(h.anchors.uv, t.face_uv_mask)
    u, v = h.anchors.uv[:, 0], h.anchors.uv[:, 1]
    np.testing.assert_array_equal(fm, (u < 0.5) & (v > 0.75))
    assert 0 < fm.sum() < len(fm)


def test_geodesic_adjacency_does_not_bridge_gaps():
    import dataclasses

    t = arm_template()
    # two parallel cylinders 2 cm apart (surface to surface)
    V2 = t.vertices + np.array([0, 0.12, 0], np.float32)
    t2 = dataclasses.replace(
        t,
        vertices=np.concatenate([t.vertices, V2]),
        faces=np.concatenate([t.faces, t.faces + len(t.vertices)]),
        skin_indices=np.concatenate([t.skin_indices] * 2),
        skin_weights=np.concatenate([t.skin_weights] * 2),
        uvs=None,
        face_uvs=None,
    )
    h = build_hierarchy(t2, n_anchors=80, n_control=200, n_gaussians=500, seed=0, min_candidates=4000)
    side = h.anchors.position[:, 1] > 0.06
    knn = knn_anchor_adjacency(h.anchors.position, 6)
    geo = geodesic_anchor_adjacency(t2.vertices, t2.faces, h.anchors.face_idx, h.anchors.bary)
    assert np.array_equal(geo, geo.T) and not geo.diagonal().any()
    assert np.any(knn & (side[:, None] != side[None, :]))
    assert not np.any(geo & (side[:, None] != side[None, :]))
    assert geo.sum(1).min() >= 2  # every anchor has neighbours on its own cylinder
    d = np.linalg.norm(h.anchors.position[:, None] - h.anchors.position[None], axis=-1)
    assert d[geo].max() < 0.2


def test_build_save_load(tmp_path, setup):
    rig, t, h = setup
    lm = build_localization(h, rig, t.face_uv_mask)
    assert lm.pose.shape == (len(h.anchors), rig.pose_dim) and lm.face.shape == (len(h.anchors),)
    assert lm.pose.dtype == bool
    p = tmp_path / "loc.npz"
    lm.save(p)
    back = LocalizationMasks.load(p)
    np.testing.assert_array_equal(back.pose, lm.pose)
    np.testing.assert_array_equal(back.face, lm.face)
    assert back.param_names == lm.param_names and back.settings == lm.settings
    np.savez(tmp_path / "bad.npz", header=np.array('{"format": "gsavatar-localization", "version": 9}'))
    with pytest.raises(SchemaError, match="version"):
        LocalizationMasks.load(tmp_path / "bad.npz")
    lg = build_localization(h, rig, t.face_uv_mask, adjacency="geodesic", template=t)
    assert lg.pose.shape == lm.pose.shape
    # Gaussians inherit activity from their anchors
    c = lm.slot_of(rig, "LeftForeArm.r")
    g = active_per_point(lm.pose[:, c], h.gauss_anchor_idx)
    assert g.shape == (len(h.gaussians),) and 0 < g.sum() < len(g)
    np.testing.assert_array_equal(g, lm.pose[h.gauss_anchor_idx, c].any(1))
