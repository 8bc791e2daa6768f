"""The anchor / control point / Gaussian hierarchy on the template surface.

Paper fig. 2 and supplementary A (after Zhan et al., Spatial MLPs): 300 anchors, 10k
control points and 200k Gaussians are sampled on the template mesh (counts
configurable).

Sampling
--------
- All points are surface samples ``(face, barycentrics)``: a face is drawn with
  probability proportional to its area, barycentrics uniformly on the triangle
  (``sqrt`` trick), so samples are area-uniform.
- Anchors and control points: farthest-point sampling (FPS, Euclidean) from a dense
  area-uniform candidate set of ``max(min_candidates, candidate_factor * n)`` points
  (20k / 50k for 300 / 10k), which gives even coverage. FPS runs in open3d's C++
  ``farthest_point_down_sample`` (exact FPS, ~0.5 s for 10k of 50k on one core),
  started at candidate 0 (the candidates are random, so the start is seeded too).
- Gaussians: area-uniform random samples.

Attributes per point (:class:`PointSet`): position, unit normal (barycentric blend
of area-weighted vertex normals, face normal where that degenerates), face index,
barycentrics, UV (per-corner UVs of the face blended with the barycentrics; the
three corners of one face always lie in one UV chart, so seams are handled), and
skinning weights: the three corner vertices' (joint, weight) entries are blended
with the barycentrics, weights of the same joint summed, the ``K`` largest kept
(``K`` = the template's) and renormalised to sum 1; unused slots get weight 0 and
the index of the strongest joint.

Interpolation (supp. eq. 1): a point ``x_i`` uses its 3 Euclidean-nearest targets
with ``t_ij = d_ij / sum_k d_ik``, ``d_ij = 1 / ||x_i - x_j||``; a point closer than
``1e-12`` m to a target takes weight 1 on it. Tables: Gaussian -> anchor,
control point -> anchor, Gaussian -> control point. For the control-point smoothness
loss every control point lists its 5 nearest other control points.

Everything is deterministic for a given ``seed`` (numpy ``default_rng``).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from gsavatar.data_schema.hierarchy import Hierarchy, PointSet
from gsavatar.data_schema.template import Template


# --- surface sampling ----------------------------------------------------------
def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas.  # [F] float64"""
    v = vertices.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=1)


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform surface samples -> (face_idx [n] int64, bary [n, 3] float64)."""
    area = face_areas(vertices, faces)
    total = area.sum()
    if not total > 0:
        raise ValueError("mesh has zero surface area")
    cdf = np.cumsum(area / total)
    cdf[-1] = 1.0
    face_idx = np.minimum(np.searchsorted(cdf, rng.random(n), side="right"), len(faces) - 1).astype(np.int64)
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    return face_idx, bary


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; zero where undefined).  # [V, 3] float64"""
    v = vertices.astype(np.float64)
    fn = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])  # 2*area*n
    vn = np.zeros_like(v)
    for c in range(3):
        np.add.at(vn, faces[:, c], fn)
    nrm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(nrm > 0, vn / np.maximum(nrm, 1e-300), 0.0)


def transfer_skin_weights(
    skin_indices: np.ndarray,
    skin_weights: np.ndarray,
    faces: np.ndarray,
    face_idx: np.ndarray,
    bary: np.ndarray,
    chunk: int = 65536,
) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric transfer of vertex skin weights with same-joint merging and re-top-K.

    -> (indices [N, K] int32, weights [N, K] float32, rows sum to 1)
    """
    K = skin_indices.shape[1]
    N = len(face_idx)
    out_i = np.empty((N, K), np.int32)
    out_w = np.empty((N, K), np.float32)
    for s in range(0, N, chunk):
        f = faces[face_idx[s : s + chunk]]  # [n, 3]
        ids = skin_indices[f].reshape(len(f), 3 * K).astype(np.int64)  # [n, 3K]
        w = (skin_weights[f].astype(np.float64) * bary[s : s + chunk, :, None]).reshape(len(f), 3 * K)
        same = ids[:, :, None] == ids[:, None, :]  # [n, 3K, 3K]
        summed = (same * w[:, None, :]).sum(-1)  # total weight of this entry's joint
        first = ~np.tril(same, k=-1).any(-1)  # first occurrence of each joint in the row
        score = np.where(first, summed, -1.0)
        order = np.argsort(-score, axis=1, kind="stable")[:, :K]
        top_w = np.maximum(np.take_along_axis(score, order, 1), 0.0)
        top_i = np.take_along_axis(ids, order, 1)
        top_i = np.where(top_w > 0, top_i, top_i[:, :1])
        tot = top_w.sum(1, keepdims=True)
        bad = tot[:, 0] <= 0
        if bad.any():  # all-zero weights (should not happen for valid templates): bind to the first joint
            top_w[bad] = 0.0
            top_w[bad, 0] = 1.0
            tot[bad] = 1.0
        out_i[s : s + chunk] = top_i
        out_w[s : s + chunk] = top_w / tot
    return out_i, out_w


def surface_points(
    template: Template, face_idx: np.ndarray, bary: np.ndarray, vnormals: np.ndarray | None = None
) -> PointSet:
    """All per-point attributes of surface samples ``(face_idx [N], bary [N, 3])``."""
    faces = template.faces
    face_idx = np.asarray(face_idx, np.int64)
    bary = np.asarray(bary, np.float64)
    pos = barycentric_interpolate(template.vertices.astype(np.float64), faces, face_idx, bary)
    if vnormals is None:
        vnormals = vertex_normals(template.vertices, faces)
    nrm = barycentric_interpolate(vnormals, faces, face_idx, bary)
    ln = np.linalg.norm(nrm, axis=1)
    weak = ln < 1e-6
    if weak.any():  # opposite-facing corner normals (thin sheets): use the face normal
        v = template.vertices.astype(np.float64)
        f = faces[face_idx[weak]]
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        nrm[weak] = fn
        ln = np.linalg.norm(nrm, axis=1)
    nrm = nrm / np.maximum(ln, 1e-300)[:, None]
    cuv = template.corner_uvs
    uv = None if cuv is None else (cuv[face_idx].astype(np.float64) * bary[:, :, None]).sum(1).astype(np.float32)
    si, sw = transfer_skin_weights(template.skin_indices, template.skin_weights, faces, face_idx, bary)
    return PointSet(pos.astype(np.float32), nrm.astype(np.float32), face_idx, bary.astype(np.float32), uv, si, sw)


def barycentric_interpolate(
    values: np.ndarray, faces: np.ndarray, face_idx: np.ndarray, bary: np.ndarray
) -> np.ndarray:
    """Per-vertex values at surface points, as ``geometry.lbs.barycentric_interpolate``
    (numpy only, so prep does not import torch). [V, C], [F, 3], [N], [N, 3] -> [N, C]"""
    f = faces[face_idx]
    return values[f[:, 0]] * bary[:, 0:1] + values[f[:, 1]] * bary[:, 1:2] + values[f[:, 2]] * bary[:, 2:3]


# --- farthest-point sampling and neighbourhoods -------------------------------------
def farthest_point_sampling(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """Exact Euclidean FPS from ``points[start]``: ascending indices [k] into ``points`` [N, 3].

    Runs open3d's C++ implementation; falls back to a vectorised numpy loop when
    open3d is missing or duplicate positions make its output ambiguous.
    """
    N = len(points)
    if not 0 < k <= N:
        raise ValueError(f"cannot pick {k} of {N} points")
    try:
        import open3d as o3d
    except ImportError:  # pragma: no cover - open3d is a dependency
        return np.sort(_fps_numpy(points, k, start))
    pts = np.ascontiguousarray(points, dtype=np.float64)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    sel = np.asarray(pc.farthest_point_down_sample(int(k), int(start)).points)
    d, idx = cKDTree(pts).query(sel, k=1)
    if len(np.unique(idx)) != k or d.max() > 0:
        # duplicate candidate positions make the position->index map ambiguous
        return np.sort(_fps_numpy(points, k, start))
    return np.sort(idx).astype(np.int64)


def _fps_numpy(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    p = np.asarray(points, np.float64)
    x, y, z = (np.ascontiguousarray(p[:, i]) for i in range(3))
    idx = np.empty(k, np.int64)
    idx[0] = start
    d = (x - x[start]) ** 2 + (y - y[start]) ** 2 + (z - z[start]) ** 2
    for i in range(1, k):
        j = int(np.argmax(d))
        idx[i] = j
        np.minimum(d, (x - x[j]) ** 2 + (y - y[j]) ** 2 + (z - z[j]) ** 2, out=d)
    return idx


def idw_weights(
    points: np.ndarray, targets: np.ndarray, k: int = 3, tree: cKDTree | None = None, eps: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """Supp. eq. 1: k nearest targets and weights ``(1/d_j) / sum_k (1/d_k)``.

    -> (indices [N, k] int64 sorted by distance, weights [N, k] float32 rows sum to 1).
    A point within ``eps`` of its nearest target gets weight 1 on it.
    """
    if len(targets) < k:
        raise ValueError(f"need at least {k} targets, got {len(targets)}")
    tree = tree or cKDTree(np.asarray(targets, np.float64))
    d, idx = tree.query(np.asarray(points, np.float64), k=k)
    d = d.reshape(len(points), k)
    idx = idx.reshape(len(points), k)
    coincide = d[:, 0] <= eps
    inv = 1.0 / np.maximum(d, eps)
    w = inv / inv.sum(1, keepdims=True)
    w[coincide] = 0.0
    w[coincide, 0] = 1.0
    return idx.astype(np.int64), w.astype(np.float32)


def nearest_others(points: np.ndarray, n: int, tree: cKDTree | None = None) -> np.ndarray:
    """The ``n`` nearest other points of every point (self excluded).  # [N, n] int64"""
    if len(points) <= n:
        raise ValueError(f"need more than {n} points, got {len(points)}")
    tree = tree or cKDTree(np.asarray(points, np.float64))
    _, idx = tree.query(np.asarray(points, np.float64), k=n + 1)
    is_self = idx == np.arange(len(points))[:, None]
    # self is usually column 0, but not with duplicate positions: move it to the end
    order = np.argsort(is_self, axis=1, kind="stable")
    return np.take_along_axis(idx, order, 1)[:, :n].astype(np.int64)


# --- the hierarchy -----------------------------------------------------------------
def build_hierarchy(
    template: Template,
    n_anchors: int = 300,
    n_control: int = 10_000,
    n_gaussians: int = 200_000,
    seed: int = 0,
    k_interp: int = 3,
    n_smooth_neighbors: int = 5,
    candidate_factor: int = 5,
    min_candidates: int = 20_000,
) -> Hierarchy:
    """Sample anchors / control points / Gaussians on ``template`` and their interpolation tables."""
    if min(n_anchors, n_control) < k_interp:
        raise ValueError(f"need at least k_interp={k_interp} anchors and control points")
    if n_control <= n_smooth_neighbors or n_gaussians < 1:
        raise ValueError("too few control points / Gaussians")
    rng = np.random.default_rng(seed)
    V, Fc = template.vertices, template.faces
    vn = vertex_normals(V, Fc)
    timings: dict[str, float] = {}

    def fps_level(n: int) -> PointSet:
        m = max(min_candidates, candidate_factor * n)
        fi, b = sample_surface(V, Fc, m, rng)
        cand = (V[Fc[fi]].astype(np.float64) * b[:, :, None]).sum(1)
        sel = farthest_point_sampling(cand, n, start=0)
        return surface_points(template, fi[sel], b[sel], vn)

    t0 = time.perf_counter()
    anchors = fps_level(n_anchors)
    timings["anchors_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    control = fps_level(n_control)
    timings["control_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    fi, b = sample_surface(V, Fc, n_gaussians, rng)
    gaussians = surface_points(template, fi, b, vn)
    timings["gaussians_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    atree = cKDTree(anchors.position.astype(np.float64))
    ctree = cKDTree(control.position.astype(np.float64))
    ga_i, ga_w = idw_weights(gaussians.position, anchors.position, k_interp, atree)
    ca_i, ca_w = idw_weights(control.position, anchors.position, k_interp, atree)
    gc_i, gc_w = idw_weights(gaussians.position, control.position, k_interp, ctree)
    nb = nearest_others(control.position, n_smooth_neighbors, ctree)
    timings["tables_s"] = time.perf_counter() - t0
    meta = {
        "seed": int(seed),
        "n_anchors": int(n_anchors),
        "n_control": int(n_control),
        "n_gaussians": int(n_gaussians),
        "k_interp": int(k_interp),
        "n_smooth_neighbors": int(n_smooth_neighbors),
        "candidate_factor": int(candidate_factor),
        "min_candidates": int(min_candidates),
        "template_vertices": int(len(V)),
        "template_faces": int(len(Fc)),
    }
    return Hierarchy(anchors, control, gaussians, ga_i, ga_w, ca_i, ca_w, gc_i, gc_w, nb, meta, timings)
