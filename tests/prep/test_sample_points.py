from __future__ import annotations

import numpy as np
import pytest

from gsavatar.data_schema.hierarchy import Hierarchy
from gsavatar.prep.sample_points import (
    _fps_numpy,
    build_hierarchy,
    farthest_point_sampling,
    idw_weights,
    nearest_others,
    sample_surface,
    transfer_skin_weights,
)
from gsavatar.utils.errors import SchemaError
from prep_fixtures import RADIUS, X0, X1, arm_template


@pytest.fixture(scope="module")
def tmpl():
    return arm_template()


@pytest.fixture(scope="module")
def hier(tmpl):
    return build_hierarchy(tmpl, n_anchors=40, n_control=600, n_gaussians=4000, seed=3, min_candidates=3000)


def test_counts_and_shapes(hier, tmpl):
    K = tmpl.skin_indices.shape[1]
    for ps, n in ((hier.anchors, 40), (hier.control, 600), (hier.gaussians, 4000)):
        assert len(ps) == n
        assert ps.position.shape == (n, 3) and ps.normal.shape == (n, 3) and ps.uv.shape == (n, 2)
        assert ps.face_idx.shape == (n,) and ps.bary.shape == (n, 3)
        assert ps.skin_indices.shape == (n, K) and ps.skin_weights.shape == (n, K)
        np.testing.assert_allclose(np.linalg.norm(ps.normal, axis=1), 1.0, atol=1e-5)
        np.testing.assert_allclose(ps.skin_weights.sum(1), 1.0, atol=1e-5)
        assert np.all(ps.bary >= -1e-7) and np.allclose(ps.bary.sum(1), 1.0, atol=1e-6)
    assert hier.gauss_anchor_idx.shape == (4000, 3) and hier.ctrl_anchor_idx.shape == (600, 3)
    assert hier.gauss_ctrl_idx.shape == (4000, 3) and hier.ctrl_neighbors.shape == (600, 5)


def test_points_on_surface(hier, tmpl):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(tmpl.vertices.astype(np.float32)), o3d.core.Tensor(tmpl.faces.astype(np.uint32))
    )
    for ps in (hier.anchors, hier.control, hier.gaussians):
        d = scene.compute_distance(o3d.core.Tensor(ps.position.astype(np.float32))).numpy()
        assert d.max() < 1e-6
        # cylinder: radius of (y, z) close to R (chord of a 24-gon is slightly inside)
        r = np.linalg.norm(ps.position[:, 1:], axis=1)
        assert np.all(r <= RADIUS + 1e-6) and np.all(r > RADIUS * np.cos(np.pi / 24) - 1e-6)
        # normals point outwards
        assert np.all(np.einsum("ij,ij->i", ps.normal[:, 1:], ps.position[:, 1:]) > 0)


def test_interpolation_weights(hier):
    for idx, w, tgt, src in (
        (hier.gauss_anchor_idx, hier.gauss_anchor_w, hier.anchors, hier.gaussians),
        (hier.ctrl_anchor_idx, hier.ctrl_anchor_w, hier.anchors, hier.control),
        (hier.gauss_ctrl_idx, hier.gauss_ctrl_w, hier.control, hier.gaussians),
    ):
        assert np.all(w > 0)
        np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-6)
        d = np.linalg.norm(src.position[:, None] - tgt.position[idx], axis=-1)
        # these are the 3 nearest targets
        dall = np.linalg.norm(src.position[:, None] - tgt.position[None], axis=-1)
        np.testing.assert_allclose(np.sort(dall, 1)[:, :3], d, atol=1e-6)
        ref = (1 / d) / (1 / d).sum(1, keepdims=True)
        np.testing.assert_allclose(w, ref, rtol=1e-4)
    # smoothness neighbours: 5 nearest others, never self
    nb = hier.ctrl_neighbors
    assert not np.any(nb == np.arange(len(nb))[:, None])
    p = hier.control.position
    dall = np.linalg.norm(p[:, None] - p[None], axis=-1)
    np.fill_diagonal(dall, np.inf)
    np.testing.assert_allclose(
        np.sort(np.linalg.norm(p[:, None] - p[nb], axis=-1), 1), np.sort(dall, 1)[:, :5], atol=1e-6
    )


def test_coinciding_point_weight_one():
    rng = np.random.default_rng(0)
    tg = rng.normal(size=(10, 3))
    pts = np.concatenate([tg[[4]], tg[[7]] + 1e-9, rng.normal(size=(3, 3))])
    idx, w = idw_weights(pts, tg, 3)
    assert idx[0, 0] == 4 and w[0, 0] == 1.0 and np.all(w[0, 1:] == 0)
    assert idx[1, 0] == 7 and w[1, 0] > 0.999999
    assert np.all(np.isfinite(w)) and np.allclose(w.sum(1), 1)
    # duplicates: self still excluded
    dup = np.concatenate([tg, tg[:2]])
    nb = nearest_others(dup, 3)
    assert not np.any(nb == np.arange(len(dup))[:, None])
    assert nb[0, 0] == 10 and nb[10, 0] == 0


def _naive_attributes(t, f, b):
    V, Fc, cuv = t.vertices.astype(np.float64), t.faces, t.corner_uvs
    K = t.skin_indices.shape[1]
    pos = sum(b[c] * V[Fc[f, c]] for c in range(3))
    uv = sum(b[c] * cuv[f, c] for c in range(3))
    acc: dict[int, float] = {}
    for c in range(3):
        for k in range(K):
            acc[int(t.skin_indices[Fc[f, c], k])] = acc.get(int(t.skin_indices[Fc[f, c], k]), 0.0) + b[c] * float(
                t.skin_weights[Fc[f, c], k]
            )
    top = sorted(((w, j) for j, w in acc.items() if w > 0), reverse=True)[:K]
    s = sum(w for w, _ in top)
    return pos, uv, {j: w / s for w, j in top}


def test_attributes_match_naive_loop(hier, tmpl):
    for ps in (hier.anchors, hier.gaussians):
        for i in range(0, len(ps), max(1, len(ps) // 150)):
            pos, uv, sk = _naive_attributes(tmpl, int(ps.face_idx[i]), ps.bary[i].astype(np.float64))
            np.testing.assert_allclose(ps.position[i], pos, atol=1e-6)
            np.testing.assert_allclose(ps.uv[i], uv, atol=1e-6)
            got = {int(j): float(w) for j, w in zip(ps.skin_indices[i], ps.skin_weights[i]) if w > 0}
            assert got.keys() == sk.keys()
            for j in sk:
                assert abs(got[j] - sk[j]) < 1e-5
    # UV on the cylinder: v follows x; u follows the angle (seam-safe, in [0, 1])
    g = hier.gaussians
    np.testing.assert_allclose(g.uv[:, 1], (g.position[:, 0] - X0) / (X1 - X0), atol=1e-5)
    ang = np.mod(np.arctan2(g.position[:, 2], g.position[:, 1]), 2 * np.pi) / (2 * np.pi)
    du = np.abs(g.uv[:, 0] - ang)
    assert np.all(np.minimum(du, 1 - du) < 0.02) and np.all((g.uv[:, 0] >= 0) & (g.uv[:, 0] <= 1))


def test_skin_transfer_topk_renormalises():
    # three vertices with 2 slots each, 4 distinct joints -> top-2 after merging
    idx = np.array([[0, 1], [1, 2], [3, 1]], np.int32)
    w = np.array([[0.6, 0.4], [0.5, 0.5], [0.9, 0.1]], np.float32)
    faces = np.array([[0, 1, 2]])
    bi, bw = transfer_skin_weights(idx, w, faces, np.array([0]), np.array([[0.5, 0.3, 0.2]]))
    # joint totals: 0: .30, 1: .20+.15+.02=.37, 2: .15, 3: .18 -> keep 1 and 0
    assert list(bi[0]) == [1, 0]
    np.testing.assert_allclose(bw[0], [0.37 / 0.67, 0.30 / 0.67], rtol=1e-6)
    # a point at a vertex reproduces that vertex's weights; unused slots weight 0
    bi, bw = transfer_skin_weights(idx, w, faces, np.array([0]), np.array([[0.0, 0.0, 1.0]]))
    assert list(bi[0]) == [3, 1] and np.allclose(bw[0], [0.9, 0.1])
    idx1 = np.array([[2, 0], [2, 0], [2, 0]], np.int32)
    w1 = np.array([[1.0, 0.0]] * 3, np.float32)
    bi, bw = transfer_skin_weights(idx1, w1, faces, np.array([0]), np.array([[0.2, 0.3, 0.5]]))
    assert list(bi[0]) == [2, 2] and np.allclose(bw[0], [1.0, 0.0])


def test_sampling_area_uniform(tmpl):
    rng = np.random.default_rng(0)
    f, b = sample_surface(tmpl.vertices, tmpl.faces, 200_000, rng)
    x = (tmpl.vertices[tmpl.faces[f]] * b[:, :, None]).sum(1)[:, 0]
    hist, _ = np.histogram(x, bins=12, range=(X0, X1))
    assert hist.min() > 0.95 * hist.mean() and hist.max() < 1.05 * hist.mean()


def test_fps_even_coverage_and_matches_numpy():
    rng = np.random.default_rng(1)
    pts = rng.random((3000, 3))
    a = farthest_point_sampling(pts, 200)
    b = _fps_numpy(pts, 200)
    np.testing.assert_array_equal(np.sort(a), np.sort(b))  # open3d returns index order
    assert len(np.unique(a)) == 200
    # FPS covering radius beats random subsets clearly
    from scipy.spatial import cKDTree

    cov = cKDTree(pts[a]).query(pts)[0].max()
    rnd = cKDTree(pts[rng.choice(3000, 200, replace=False)]).query(pts)[0].max()
    assert cov < 0.7 * rnd


def test_determinism_and_seed(tmpl, hier):
    h2 = build_hierarchy(tmpl, n_anchors=40, n_control=600, n_gaussians=4000, seed=3, min_candidates=3000)
    for lvl in ("anchors", "control", "gaussians"):
        np.testing.assert_array_equal(getattr(hier, lvl).position, getattr(h2, lvl).position)
        np.testing.assert_array_equal(getattr(hier, lvl).skin_weights, getattr(h2, lvl).skin_weights)
    np.testing.assert_array_equal(hier.gauss_ctrl_idx, h2.gauss_ctrl_idx)
    h3 = build_hierarchy(tmpl, n_anchors=40, n_control=600, n_gaussians=4000, seed=4, min_candidates=3000)
    assert not np.array_equal(hier.anchors.position, h3.anchors.position)


def test_save_load(tmp_path, hier):
    p = tmp_path / "h.npz"
    hier.save(p)
    back = Hierarchy.load(p)
    assert back.meta == hier.meta
    for lvl in ("anchors", "control", "gaussians"):
        for f in ("position", "normal", "face_idx", "bary", "uv", "skin_indices", "skin_weights"):
            a, b = getattr(getattr(hier, lvl), f), getattr(getattr(back, lvl), f)
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.ctrl_neighbors, hier.ctrl_neighbors)
    np.testing.assert_array_equal(back.gauss_anchor_w, hier.gauss_anchor_w)
    # byte-reproducible
    hier.save(tmp_path / "h2.npz")
    assert (tmp_path / "h2.npz").read_bytes() == p.read_bytes()
    np.savez(tmp_path / "bad.npz", x=np.zeros(2))
    with pytest.raises(SchemaError, match="header"):
        Hierarchy.load(tmp_path / "bad.npz")


def test_no_uvs(tmpl, tmp_path):
    import dataclasses

    t = dataclasses.replace(tmpl, uvs=None, face_uvs=None)
    h = build_hierarchy(t, n_anchors=10, n_control=50, n_gaussians=100, seed=0, min_candidates=500)
    assert h.anchors.uv is None and h.gaussians.uv is None
    h.save(tmp_path / "h.npz")
    back = Hierarchy.load(tmp_path / "h.npz")
    assert back.control.uv is None and np.array_equal(back.control.position, h.control.position)
