"""Prep on the real anny body (opt-in: ``ANNY_CACHE_DIR=... pytest -m slow tests/test_prep_anny.py``)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not os.environ.get("ANNY_CACHE_DIR"), reason="set ANNY_CACHE_DIR to the anny cache to run"),
]


@pytest.fixture(scope="module")
def body():
    from gsavatar.prep.localize import build_localization
    from gsavatar.prep.sample_points import build_hierarchy
    from gsavatar.synth.body import build_anny_body

    t, rig = build_anny_body(Path(os.environ["ANNY_CACHE_DIR"]))
    h = build_hierarchy(t, seed=0)
    return t, rig, h, build_localization(h, rig, t.face_uv_mask)


def test_hierarchy_on_anny(body):
    t, _, h, _ = body
    assert (h.num_anchors, h.num_control, h.num_gaussians) == (300, 10_000, 200_000)
    for w in (h.gauss_anchor_w, h.ctrl_anchor_w, h.gauss_ctrl_w):
        assert np.all(w > 0) and np.allclose(w.sum(1), 1, atol=1e-5)
    for ps in (h.anchors, h.control, h.gaussians):
        assert np.allclose(ps.skin_weights.sum(1), 1, atol=1e-5)
        assert ps.uv is not None and np.all((ps.uv >= -1e-6) & (ps.uv <= 1 + 1e-6))
    from scipy.spatial import cKDTree

    d = cKDTree(h.anchors.position).query(h.anchors.position, k=2)[0][:, 1]
    assert d.min() > 0.6 * d.mean()  # FPS: even coverage


def test_masks_on_anny(body):
    t, rig, h, lm = body
    names = [p.name for p in rig.params]
    y = h.anchors.position[:, 1]
    neck = lm.pose[:, names.index("Neck.ry")]
    assert 10 < neck.sum() < 80 and y[neck].min() > 1.1  # head/neck/shoulders only (body is 1.63 m)
    wrist = lm.pose[:, names.index("LeftHand.rx")]
    for p in rig.groups["left_hand"]:
        np.testing.assert_array_equal(lm.pose[:, names.index(p)], wrist)
    assert wrist.any() and np.all(h.anchors.position[wrist, 0] > 0.2)  # left hand is on +x
    assert 0 < lm.face.sum() < 30 and y[lm.face].min() > 1.35


def test_local_pca_on_anny_rig(body):
    from gsavatar.prep.pca import fit_pose_pca

    _, rig, _, _ = body
    rng = np.random.default_rng(0)
    poses = rng.normal(size=(500, rig.pose_dim)) * 0.3
    pca = fit_pose_pca(poses, rig)
    assert all(v == 5 for v in pca.components_per_group().values())
    assert pca.project(poses).shape == poses.shape
