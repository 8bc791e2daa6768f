"""Texel -> triangle maps (vectorised rasteriser vs a naive per-texel loop) and the xatlas unwrap cache."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from gsavatar.data_schema.template import Template
from gsavatar.prep import uv_atlas
from gsavatar.prep.uv_atlas import TexelMap, build_texel_map, ensure_uvs, texel_uv_centers, uv_to_texel
from gsavatar.geometry.primitives import icosphere


# --------------------------------------------------------------------------- fixtures
def jittered_grid(n: int, lo=(0.05, 0.05), hi=(0.6, 0.7), jitter=0.25, seed=0) -> np.ndarray:
    """Corner UVs [F,3,2] of an n x n grid of quads (2 triangles each), interior vertices jittered."""
    rng = np.random.default_rng(seed)
    u = np.linspace(lo[0], hi[0], n + 1)
    v = np.linspace(lo[1], hi[1], n + 1)
    P = np.stack(np.meshgrid(u, v, indexing="xy"), -1)  # [n+1, n+1, 2]
    step = np.array([(hi[0] - lo[0]) / n, (hi[1] - lo[1]) / n])
    P[1:-1, 1:-1] += rng.uniform(-jitter, jitter, P[1:-1, 1:-1].shape) * step
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = P[i, j], P[i, j + 1], P[i + 1, j + 1], P[i + 1, j]
            tris.append([a, b, c])
            tris.append([a, d, c][::-1] if (i + j) % 2 else [a, c, d])  # mixed winding
    return np.array(tris)


def scene_uvs() -> np.ndarray:
    grid = jittered_grid(3)
    extra = np.array(
        [
            [[0.70, 0.10], [0.95, 0.12], [0.80, 0.40]],  # isolated chart
            [[0.72, 0.55], [0.90, 0.55], [0.72, 0.80]],  # two overlapping (mirrored) triangles
            [[0.90, 0.80], [0.72, 0.80], [0.90, 0.55]],
            [[0.70, 0.90], [0.80, 0.90], [0.90, 0.90]],  # degenerate (zero area) sliver
            [[0.852, 0.952], [0.862, 0.953], [0.857, 0.962]],  # tiny: covers no texel centre
        ]
    )
    return np.concatenate([grid, extra])


# --------------------------------------------------------------------------- naive reference
def naive_texel_map(cuv: np.ndarray, size: int, gutter: float) -> TexelMap:
    """Per-texel loop over all triangles, same rules as build_texel_map."""
    P = uv_to_texel(cuv, size)
    F = len(P)
    face = np.full((size, size), -1, np.int32)
    bary = np.zeros((size, size, 3), np.float32)
    interior = np.zeros((size, size), bool)
    eps = 1e-7
    for y in range(size):
        for x in range(size):
            px, py = float(x), float(y)
            best = None  # (score, -face)
            for f in range(F):
                (x0, y0), (x1, y1), (x2, y2) = P[f]
                den = (y1 - y2) * (x0 - x2) + (x2 - x1) * (y0 - y2)
                if abs(den) <= 1e-12:
                    continue
                l0 = ((y1 - y2) * (px - x2) + (x2 - x1) * (py - y2)) / den
                l1 = ((y2 - y0) * (px - x2) + (x0 - x2) * (py - y2)) / den
                b = [l0, l1, 1.0 - l0 - l1]
                s = min(b)
                if s >= -eps and (best is None or s > best[0]):
                    best = (s, f, b)
            if best is not None:
                b = np.clip(np.array(best[2]), 0, None)
                face[y, x], bary[y, x], interior[y, x] = best[1], b / b.sum(), True
                continue
            if gutter <= 0:
                continue
            near = None
            for f in range(F):
                fd, fb = math.inf, None
                for i, j in ((0, 1), (1, 2), (2, 0)):
                    ax, ay = P[f, i]
                    ex, ey = P[f, j, 0] - ax, P[f, j, 1] - ay
                    L = ex * ex + ey * ey
                    t = ((px - ax) * ex + (py - ay) * ey) / L if L > 0 else 0.0
                    t = min(max(t, 0.0), 1.0)
                    dx, dy = ax + t * ex - px, ay + t * ey - py
                    d = dx * dx + dy * dy
                    if d < fd:
                        fd, fb = d, np.zeros(3)
                        fb[i], fb[j] = 1.0 - t, t
                if fd <= gutter * gutter + 1e-9 and (near is None or fd < near[0]):
                    near = (fd, f, fb)
            if near is not None:
                face[y, x], bary[y, x] = near[1], near[2]
    return TexelMap(face, bary, size, interior)


@pytest.mark.parametrize("gutter", [0.0, 1.0, 1.5])
def test_matches_naive_reference(gutter):
    cuv = scene_uvs()
    got = build_texel_map(None, cuv, 24, gutter=gutter)
    ref = naive_texel_map(cuv, 24, gutter)
    np.testing.assert_array_equal(got.face, ref.face)
    np.testing.assert_array_equal(got.interior, ref.interior)
    np.testing.assert_allclose(got.bary, ref.bary, atol=1e-6)
    assert got.size == 24 and got.face.dtype == np.int32 and got.bary.dtype == np.float32
    assert got.interior.sum() > 150
    if gutter > 0:
        assert (got.valid & ~got.interior).sum() > 30
    else:
        assert np.array_equal(got.valid, got.interior)


def test_full_square_is_all_interior_and_reproduces_uv():
    cuv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], np.float64)
    tm = build_texel_map(None, cuv, 37)
    assert tm.interior.all() and (tm.face >= 0).all()
    uv = (cuv[tm.face] * tm.bary[..., None]).sum(-2)
    np.testing.assert_allclose(uv, texel_uv_centers(37), atol=1e-6)
    # convention: row 0 is the top of the texture (v close to 1), column 0 is u close to 0
    assert uv[0, 0, 1] > 0.98 and uv[0, 0, 0] < 0.02


def test_barycentrics_reproduce_texel_centres_and_gutter_is_clamped():
    cuv = jittered_grid(12, seed=4)
    size = 64
    tm = build_texel_map(None, cuv, size, gutter=1.0)
    uv = (cuv[np.maximum(tm.face, 0)] * tm.bary[..., None].astype(np.float64)).sum(-2)
    centre = texel_uv_centers(size)
    inner = tm.interior
    np.testing.assert_allclose(uv[inner], centre[inner], atol=1e-6)
    g = tm.valid & ~tm.interior
    assert g.sum() > 50
    assert np.all(tm.bary[g] >= 0) and np.allclose(tm.bary[g].sum(-1), 1, atol=1e-6)
    dist_texels = np.linalg.norm((uv[g] - centre[g]) * size, axis=1)
    assert dist_texels.max() <= 1.0 + 1e-6
    assert np.all(tm.bary[~tm.valid] == 0)
    # every texel within 1 texel of the chart is valid: the 3x3-dilated interior is covered
    import cv2

    dil = cv2.dilate(inner.astype(np.uint8), np.ones((3, 3), np.uint8), iterations=1).astype(bool)
    cross = cv2.dilate(inner.astype(np.uint8), np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)).astype(bool)
    assert tm.valid[cross].all()
    assert not tm.valid[~cv2.dilate(dil.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)].any()


def test_chunking_does_not_change_result(monkeypatch):
    cuv = jittered_grid(9, seed=2)
    a = build_texel_map(None, cuv, 48)
    monkeypatch.setattr(uv_atlas, "_CHUNK", 7)
    b = build_texel_map(None, cuv, 48)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_template_input_and_errors():
    cuv = np.array([[[0, 0], [1, 0], [1, 1]], [[0, 0], [1, 1], [0, 1]]], np.float32)
    uvs = cuv.reshape(-1, 2)
    t = Template(
        np.zeros((4, 3), np.float32),
        np.array([[0, 1, 2], [0, 2, 3]]),
        np.zeros((4, 1), np.int32),
        np.ones((4, 1), np.float32),
        uvs,
        np.arange(6).reshape(2, 3),
    )
    assert build_texel_map(t, size=8).interior.all()
    with pytest.raises(ValueError):
        build_texel_map(Template(t.vertices, t.faces, t.skin_indices, t.skin_weights), size=8)
    with pytest.raises(ValueError):
        build_texel_map(None, cuv[:, :2], 8)
    with pytest.raises(ValueError):
        build_texel_map(None, cuv, 0)


# --------------------------------------------------------------------------- xatlas
def test_ensure_uvs_unwraps_once_and_caches(tmp_path, monkeypatch):
    V, F = icosphere(2)
    t = Template(V, F, np.zeros((len(V), 1), np.int32), np.ones((len(V), 1), np.float32))
    u = ensure_uvs(t, tmp_path)
    assert u.uvs is not None and u.face_uvs is not None and u.face_uvs.shape == F.shape
    assert u.uvs.min() >= 0 and u.uvs.max() <= 1
    assert np.array_equal(u.faces, F) and u.vertices is t.vertices
    files = list(tmp_path.glob("uv_atlas_*.npz"))
    assert len(files) == 1
    # UV triangles are not degenerate and the charts do not overlap: summed UV area == covered area
    cuv = u.corner_uvs.astype(np.float64)
    e1, e2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    assert (area > 0).mean() > 0.99
    tm = build_texel_map(u, size=256, gutter=0)
    assert abs(tm.interior.mean() - area.sum()) < 0.02
    assert len(u.uvs) >= len(V)  # seams split vertices

    def boom(*a, **k):
        raise AssertionError("cache not used")

    monkeypatch.setattr(uv_atlas, "unwrap_xatlas", boom)
    u2 = ensure_uvs(t, tmp_path)
    np.testing.assert_array_equal(u2.uvs, u.uvs)
    np.testing.assert_array_equal(u2.face_uvs, u.face_uvs)
    # a template that already has UVs is returned as is (no unwrap, no cache)
    assert ensure_uvs(u2, tmp_path / "other") is u2
    # a different mesh misses the cache
    with pytest.raises(AssertionError, match="cache not used"):
        ensure_uvs(Template(V * 2, F, t.skin_indices, t.skin_weights), tmp_path)


@pytest.mark.slow
def test_speed_30k_triangles_1024():
    cuv = jittered_grid(123, lo=(0.0, 0.0), hi=(1.0, 1.0), jitter=0.3)  # 30258 triangles
    t0 = time.perf_counter()
    tm = build_texel_map(None, cuv, 1024)
    dt = time.perf_counter() - t0
    assert tm.interior.mean() > 0.99
    assert dt < 10, dt
