"""UV texel projection (supp. C) against analytic scenes and naive per-texel references.

Scenes are small textured meshes (a 1 m planar quad plus optional extra charts) whose
views are rendered analytically: every pixel ray is intersected with the mesh and the
known texture function is evaluated at the hit's exact UV. Projection must recover
the texture function at the texel centres.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import replace

import numpy as np
import pytest

from gsavatar.data_schema.capture import Camera
from gsavatar.geometry.camera import look_at, pixel_rays, project
from gsavatar.prep.project_uv import (
    ProjectConfig,
    UVProjector,
    fuse_samples,
    load_frame_views,
    project_uv,
    vertex_normals,
)
from gsavatar.prep.uv_atlas import build_texel_map, texel_uv_centers


# --------------------------------------------------------------------------- scene helpers
def tex_fn(uv: np.ndarray) -> np.ndarray:
    """Smooth analytic texture on UV space. [..., 2] -> [..., 3] in [0.2, 0.8]."""
    u, v = uv[..., 0], uv[..., 1]
    r = 0.5 + 0.25 * np.sin(2 * np.pi * (1.5 * u + 0.1))
    g = 0.5 + 0.25 * np.cos(2 * np.pi * (1.2 * v + 0.3 * u))
    b = 0.5 + 0.2 * np.sin(2 * np.pi * (u + v))
    return np.stack([r, g, b], axis=-1)


def quad(center, size, uv_lo, uv_hi, facing=+1.0):
    """Axis-aligned quad in a z = const plane; normal +z (facing=+1) or -z. -> V [4,3], F [2,3], cuv [2,3,2]."""
    cx, cy, cz = center
    h = size / 2
    V = np.array([[cx - h, cy - h, cz], [cx + h, cy - h, cz], [cx + h, cy + h, cz], [cx - h, cy + h, cz]], np.float64)
    (u0, v0), (u1, v1) = uv_lo, uv_hi
    UV = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], np.float64)
    F = np.array([[0, 1, 2], [0, 2, 3]]) if facing > 0 else np.array([[0, 2, 1], [0, 3, 2]])
    return V, F, UV[F]


def merge(*parts):
    Vs, Fs, Cs, off = [], [], [], 0
    for V, F, C in parts:
        Vs.append(V)
        Fs.append(F + off)
        Cs.append(C)
        off += len(V)
    return np.concatenate(Vs), np.concatenate(Fs), np.concatenate(Cs)


def make_cam(name, eye, target=(0.0, 0.0, 0.0), size=256, f=300.0, dist=None, up=(0.0, 1.0, 0.0)):
    R, T = look_at(np.asarray(eye, float), np.asarray(target, float), np.asarray(up, float))
    K = np.array([[f, 0, (size - 1) / 2], [0, f, (size - 1) / 2], [0, 0, 1.0]])
    return Camera(name, K, R, T, np.zeros(5) if dist is None else np.asarray(dist, float), size, size)


def render(V, F, cuv, cam, fg_faces=None, bg=(0.1, 0.9, 0.1)):
    """Analytic render: image [H,W,3] float32 = tex_fn(uv at the exact hit), mask [H,W] float32."""
    import open3d as o3d

    rays = pixel_rays(cam.K, cam.R, cam.T, cam.width, cam.height, cam.dist)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    t = hit["t_hit"].numpy()
    hitm = np.isfinite(t)
    # exact hit point in float64, then barycentrics of it in the hit triangle
    r64 = rays.astype(np.float64)
    p = r64[..., :3] + r64[..., 3:] * np.where(hitm, t, 0)[..., None]
    img = np.tile(np.asarray(bg, np.float32), (cam.height, cam.width, 1))
    ys, xs = np.nonzero(hitm)
    tri = prim[ys, xs]
    a, b, c = V[F[tri, 0]], V[F[tri, 1]], V[F[tri, 2]]
    q = p[ys, xs]
    v0, v1, v2 = b - a, c - a, q - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    l1 = (d11 * d20 - d01 * d21) / den
    l2 = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - l1 - l2, l1, l2], 1)
    uv = (cuv[tri] * bary[:, :, None]).sum(1)
    img[ys, xs] = tex_fn(uv).astype(np.float32)
    mask = np.zeros((cam.height, cam.width), np.float32)
    fgm = np.ones(len(tri), bool) if fg_faces is None else np.isin(tri, fg_faces)
    mask[ys[fgm], xs[fgm]] = 1.0
    return img, mask


def psnr(a, b):
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10 * math.log10(1.0 / max(mse, 1e-20))


def gt_texture(size):
    return tex_fn(texel_uv_centers(size))


CAMS3 = [((0.0, 0.0, 2.5), "c0"), ((1.2, 0.5, 2.2), "c1"), ((-1.0, -0.6, 2.2), "c2")]


@pytest.fixture(scope="module")
def plane():
    V, F, C = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    tm = build_texel_map(V, C, 64)
    cams = [make_cam(n, e) for e, n in CAMS3]
    views = [(c, *render(V, F, C, c)) for c in cams]
    return V, F, C, tm, views


def interior_eval(tm, fus, gt):
    m = fus.valid & tm.interior
    return psnr(fus.texture[m], gt[m]), m


# --------------------------------------------------------------------------- recovery
def test_plane_recovers_texture(plane):
    V, F, C, tm, views = plane
    fus = project_uv(V, F, tm, views, ProjectConfig(tex_size=64))
    gt = gt_texture(64)
    p, m = interior_eval(tm, fus, gt)
    assert p > 35, p
    assert m.mean() > 0.8  # nearly all texels recovered (border ring lost to mask erosion)
    assert fus.texture.dtype == np.float32 and fus.count.dtype == np.uint8 and fus.seen.dtype == np.uint8
    assert np.all(fus.count <= fus.seen)
    assert np.all(fus.texture[~fus.valid] == 0)
    assert fus.seen[32, 32] == 3


def test_distorted_camera_recovers_texture():
    V, F, C = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    tm = build_texel_map(V, C, 64)
    cams = [
        make_cam("d0", (0.2, 0.1, 1.3), f=200, dist=[-0.25, 0.08, 0.002, -0.001, 0.0]),
        make_cam("d1", (-0.5, 0.1, 1.3), f=200, dist=[0.15, -0.05, 0.0, 0.003, 0.01]),
    ]
    views = [(c, *render(V, F, C, c)) for c in cams]
    # sanity: the distortion is not negligible in these views
    c0 = replace(cams[0], dist=np.zeros(5))
    shift = np.abs(
        project(V, cams[0].K, cams[0].R, cams[0].T, cams[0].dist).pixels - project(V, c0.K, c0.R, c0.T).pixels
    ).max()
    assert shift > 5
    fus = project_uv(V, F, tm, views, ProjectConfig(tex_size=64))
    p, m = interior_eval(tm, fus, gt_texture(64))
    assert p > 35, p
    assert m.mean() > 0.8
    # ignoring the distortion must be clearly worse (the test has teeth)
    nod = [(replace(c, dist=np.zeros(5)), im, mk) for c, im, mk in views]
    fus2 = project_uv(V, F, tm, nod, ProjectConfig(tex_size=64))
    p2, _ = interior_eval(tm, fus2, gt_texture(64))
    assert p2 < p - 5


def test_corrupted_view_median_band_beats_mean(plane):
    V, F, C, tm, views = plane
    cam, img, mask = views[1]
    cast = np.clip(img * np.array([1.6, 1.3, 1.1], np.float32), 0, 1)  # strong warm cast, luminance ~x1.35
    bad = [views[0], (cam, cast, mask), views[2]]
    gt = gt_texture(64)
    med = project_uv(V, F, tm, bad, ProjectConfig(tex_size=64, fusion="median_band"))
    mean = project_uv(V, F, tm, bad, ProjectConfig(tex_size=64, fusion="mean"))
    m = med.valid & tm.interior & (med.seen == 3)
    assert m.sum() > 1000
    p_med, p_mean = psnr(med.texture[m], gt[m]), psnr(mean.texture[m], gt[m])
    assert p_med > 35 and p_med > p_mean + 10, (p_med, p_mean)
    assert np.all(med.count[m] == 2)  # the cast view is dropped everywhere it was seen
    assert np.all(mean.count[m] == 3)


def test_mean_fusion_also_recovers_clean_views(plane):
    V, F, C, tm, views = plane
    fus = project_uv(V, F, tm, views, ProjectConfig(tex_size=64, fusion="mean"))
    assert interior_eval(tm, fus, gt_texture(64))[0] > 35
    assert np.array_equal(fus.count, fus.seen)


# --------------------------------------------------------------------------- coverage edge cases
def test_zero_and_one_view_texels():
    # main quad in u in [0, 0.6]; a chart hidden behind it; a chart facing away from all cameras
    main = quad((0, 0, 0), 1.0, (0.0, 0.0), (0.6, 1.0))
    hidden = quad((0, 0, -0.3), 0.4, (0.7, 0.0), (1.0, 0.3))
    away = quad((2.0, 0, 0), 0.4, (0.7, 0.5), (1.0, 0.8), facing=-1)
    V, F, C = merge(main, hidden, away)
    tm = build_texel_map(V, C, 64)
    camA, camB = make_cam("A", (0.2, 0.1, 2.5)), make_cam("B", (-0.4, 0.2, 2.4))
    imgA, maskA = render(V, F, C, camA)
    imgB, maskB = render(V, F, C, camB)
    # camera B only has foreground on the image's left half -> the quad's right part is seen by A only
    maskB[:, 128:] = 0
    fus = project_uv(V, F, tm, [(camA, imgA, maskA), (camB, imgB, maskB)], ProjectConfig(tex_size=64))
    uvc = texel_uv_centers(64)
    gt = tex_fn(uvc)
    in_hidden = (uvc[..., 0] > 0.72) & (uvc[..., 1] < 0.28)
    in_away = (uvc[..., 0] > 0.72) & (uvc[..., 1] > 0.52) & (uvc[..., 1] < 0.78)
    assert tm.valid[in_hidden].all() and tm.valid[in_away].all()
    for region in (in_hidden, in_away):
        assert not fus.valid[region].any()
        assert np.all(fus.seen[region] == 0) and np.all(fus.count[region] == 0)
        assert np.all(fus.texture[region] == 0)
    one = fus.valid & tm.interior & (fus.seen == 1)
    two = fus.valid & tm.interior & (fus.seen == 2)
    assert one.sum() > 200 and two.sum() > 200
    assert np.all(fus.count[one] == 1)
    assert psnr(fus.texture[one], gt[one]) > 35
    # the one-view texels are on the +x side of the quad (B's right image half masked out)
    assert uvc[..., 0][one].mean() > uvc[..., 0][two].mean()


def test_grazing_camera_is_ignored():
    V, F, C = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    tm = build_texel_map(V, C, 32)
    # elevation ~3 deg above the plane: cos(normal, view) ~ 0.05 < 0.1
    g = make_cam("graze", (2.5 * math.cos(math.radians(3)), 0.0, 2.5 * math.sin(math.radians(3))), f=600)
    front = make_cam("front", (0.0, 0.0, 2.5))
    views = [(c, *render(V, F, C, c)) for c in (front, g)]
    assert views[1][2].sum() > 50  # the grazing camera does see the quad
    proj = UVProjector(F, tm, ProjectConfig(tex_size=32, erode_px=1))
    _, ok = proj.samples(V, views)
    assert ok[:, 0].sum() > 0 and ok[:, 1].sum() == 0
    _, ok0 = UVProjector(F, tm, ProjectConfig(tex_size=32, erode_px=1, min_cos=0.0)).samples(V, views)
    assert ok0[:, 1].sum() > 0


def test_background_mask_and_cameras_that_see_nothing(plane):
    V, F, C, tm, views = plane
    cfg = ProjectConfig(tex_size=64)
    ref = project_uv(V, F, tm, views, cfg)
    cam0, img0, mask0 = views[0]
    all_bg = (replace(cam0, name="bg"), img0, np.zeros_like(mask0))
    # behind the quad, looking away from it: every texel has z <= 0
    away = make_cam("away", (0, 0, -2.0), target=(0, 0, -5.0))
    # behind the quad, looking at it: all texels back-facing
    behind = make_cam("behind", (0, 0, -2.5))
    extra = [all_bg, (away, *render(V, F, C, away)), (behind, *render(V, F, C, behind))]
    assert extra[2][2].sum() > 100  # the quad is in view of 'behind', just back-facing
    proj = UVProjector(F, tm, cfg)
    _, ok = proj.samples(V, views + extra)
    assert ok[:, 3:].sum() == 0
    out = proj.project(V, views + extra)
    for a, b in zip(ref, out):
        np.testing.assert_array_equal(a, b)
    # only useless views: nothing valid, no crash
    none = proj.project(V, extra)
    assert not none.valid.any() and none.texture.max() == 0 and none.seen.max() == 0
    empty = proj.project(V, [])
    assert not empty.valid.any()


def test_nan_vertex_raises_naming_frame(plane):
    V, F, C, tm, views = plane
    Vn = V.copy()
    Vn[2, 1] = np.nan
    with pytest.raises(ValueError, match="frame 17"):
        project_uv(Vn, F, tm, views, ProjectConfig(tex_size=64), frame=17)


def test_face_region_masked(plane):
    V, F, C, tm, views = plane
    face = np.zeros((16, 16), bool)
    face[:8, :8] = True  # top-left quadrant (high v, low u)
    fus = project_uv(V, F, tm, views, ProjectConfig(tex_size=64), face_uv_mask=face)
    assert not fus.valid[:32, :32].any() and np.all(fus.texture[:32, :32] == 0)
    assert fus.valid[40:60, 40:60].all()
    off = project_uv(V, F, tm, views, ProjectConfig(tex_size=64, mask_face=False), face_uv_mask=face)
    assert off.valid[5:30, 5:30].all()


def test_chunking_and_generator_views_do_not_change_result(plane):
    V, F, C, tm, views = plane
    a = project_uv(V, F, tm, views, ProjectConfig(tex_size=64))
    b = project_uv(V, F, tm, (v for v in views), ProjectConfig(tex_size=64, chunk=333))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_config_validation():
    with pytest.raises(ValueError):
        ProjectConfig(band=(1.2, 1.5))
    with pytest.raises(ValueError):
        ProjectConfig(fusion="max")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        ProjectConfig(erode_px=-1)


# --------------------------------------------------------------------------- naive references
def naive_fuse(rgb, ok, fusion, band):
    """Per-texel python loop implementation of the fusion rule."""
    N, Cn = ok.shape
    out = np.zeros((N, 3), np.float32)
    count = np.zeros(N, int)
    seen = np.zeros(N, int)
    for i in range(N):
        idx = [c for c in range(Cn) if ok[i, c]]
        seen[i] = len(idx)
        if not idx:
            continue
        if fusion == "mean":
            keep = idx
        else:
            L = {
                c: 0.2126 * float(rgb[i, c, 0]) + 0.7152 * float(rgb[i, c, 1]) + 0.0722 * float(rgb[i, c, 2])
                for c in idx
            }
            med = statistics.median(L.values())
            keep = [c for c in idx if band[0] * med <= L[c] <= band[1] * med]
            if not keep:
                srt = sorted(idx, key=lambda c: L[c])  # stable, like the vectorised argsort
                k = len(srt)
                keep = sorted({srt[(k - 1) // 2], srt[k // 2]})
        count[i] = len(keep)
        acc = [0.0, 0.0, 0.0]
        for c in keep:
            for ch in range(3):
                acc[ch] += float(rgb[i, c, ch])
        out[i] = [a / len(keep) for a in acc]
    return out, count, seen


@pytest.mark.parametrize("fusion", ["median_band", "mean"])
def test_fusion_matches_naive_reference(fusion):
    rng = np.random.default_rng(3)
    N, Cn = 3000, 6
    base = rng.uniform(0.05, 0.9, (N, 1, 3))
    gain = rng.choice([1.0, 1.0, 0.95, 1.05, 0.6, 1.5, 1.3, 0.85, 1.12], size=(N, Cn, 1))
    rgb = np.clip(base * gain + rng.normal(0, 0.01, (N, Cn, 3)), 0, 1).astype(np.float32)
    rgb[:50] = rgb[:50, :1]  # exact ties
    rgb[50:60] = 0.0  # black texels (median 0)
    ok = rng.uniform(size=(N, Cn)) < rng.uniform(0, 1, (N, 1))
    ok[:20] = False
    ok[20:40] = False
    ok[20:40, 2] = True  # single view
    rgb[~ok] = rng.uniform(size=(int((~ok).sum()), 3))  # garbage where not ok must be ignored
    col, cnt, seen = fuse_samples(rgb, ok, fusion, (0.8, 1.1))
    ref_col, ref_cnt, ref_seen = naive_fuse(rgb, ok, fusion, (0.8, 1.1))
    np.testing.assert_array_equal(cnt, ref_cnt)
    np.testing.assert_array_equal(seen, ref_seen)
    np.testing.assert_allclose(col, ref_col, rtol=0, atol=1e-6)
    assert np.all(col[:20] == 0) and np.all(cnt[20:40] == 1)
    if fusion == "median_band":
        assert (cnt < seen).sum() > 500  # the band did drop samples in this data


def test_fusion_even_count_fallback():
    # two samples far apart: median 1.5 x, band [1.2, 1.65] x keeps neither -> both middle samples averaged
    rgb = np.array([[[0.2, 0.2, 0.2], [0.4, 0.4, 0.4]]], np.float32)
    col, cnt, seen = fuse_samples(rgb, np.ones((1, 2), bool))
    assert cnt[0] == 2 and seen[0] == 2
    np.testing.assert_allclose(col[0], 0.3, atol=1e-7)
    # close pair: the brighter one (1.3x) is outside [0.8, 1.1] x median(1.15x) -> dropped
    rgb = np.array([[[0.2, 0.2, 0.2], [0.26, 0.26, 0.26]]], np.float32)
    col, cnt, _ = fuse_samples(rgb, np.ones((1, 2), bool))
    assert cnt[0] == 1 and np.allclose(col[0], 0.2)


def _naive_samples(V, F, tm, views, cfg):
    """Per-texel, per-view loop reference of the sampling stage (own ray/triangle test)."""
    import cv2

    Vd = np.asarray(V, np.float64)
    vn = np.zeros_like(Vd)
    for f in F:
        n = np.cross(Vd[f[1]] - Vd[f[0]], Vd[f[2]] - Vd[f[0]])
        for k in f:
            vn[k] += n
    vn = np.array([n / np.linalg.norm(n) if np.linalg.norm(n) > 0 else n for n in vn])
    texels = np.flatnonzero(tm.face.ravel() >= 0)
    out_rgb = np.zeros((len(texels), len(views), 3))
    out_ok = np.zeros((len(texels), len(views)), bool)

    def occluded(o, d):  # any hit with t in [0, 1] (Moller-Trumbore)
        for f in F:
            a, b, c = Vd[f[0]], Vd[f[1]], Vd[f[2]]
            e1, e2 = b - a, c - a
            p = np.cross(d, e2)
            det = e1 @ p
            if abs(det) < 1e-15:
                continue
            s = o - a
            u = (s @ p) / det
            if u < 0 or u > 1:
                continue
            q = np.cross(s, e1)
            v = (d @ q) / det
            if v < 0 or u + v > 1:
                continue
            t = (e2 @ q) / det
            if 0 <= t <= 1:
                return True
        return False

    for ci, (cam, img, mask) in enumerate(views):
        fg = (mask > cfg.mask_threshold).astype(np.uint8)
        if cfg.erode_px > 1:
            fg = cv2.erode(
                fg, np.ones((cfg.erode_px, cfg.erode_px), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1
            )
        C = -cam.R.T @ cam.T
        for ti, t in enumerate(texels):
            y, x = divmod(int(t), tm.size)
            tri = F[tm.face[y, x]]
            bc = tm.bary[y, x].astype(np.float64)
            P = sum(bc[k] * Vd[tri[k]] for k in range(3))
            n = sum(bc[k] * vn[tri[k]] for k in range(3))
            n = n / np.linalg.norm(n)
            to = C - P
            if (n @ to) / np.linalg.norm(to) < cfg.min_cos:
                continue
            pr = project(P[None], cam.K, cam.R, cam.T, cam.dist)
            if pr.depth[0] <= 1e-6:
                continue
            px, py = pr.pixels[0]
            if not (0 <= px <= cam.width - 1 and 0 <= py <= cam.height - 1):
                continue
            x0, y0 = min(int(math.floor(px)), cam.width - 2), min(int(math.floor(py)), cam.height - 2)
            if not (fg[y0, x0] and fg[y0, x0 + 1] and fg[y0 + 1, x0] and fg[y0 + 1, x0 + 1]):
                continue
            o = P + cfg.occlusion_eps * to / np.linalg.norm(to)
            if occluded(o, C - o):
                continue
            fx, fy = px - x0, py - y0
            val = (
                img[y0, x0] * (1 - fx) * (1 - fy)
                + img[y0, x0 + 1] * fx * (1 - fy)
                + img[y0 + 1, x0] * (1 - fx) * fy
                + img[y0 + 1, x0 + 1] * fx * fy
            )
            out_rgb[ti, ci] = val
            out_ok[ti, ci] = True
    return out_rgb, out_ok


def test_sampling_matches_naive_reference_with_occluder():
    main = quad((0, 0, 0), 1.0, (0.0, 0.0), (0.7, 1.0))
    occl = quad((0.1, 0.05, 0.5), 0.3, (0.75, 0.0), (1.0, 0.3))  # floats in front of the quad: casts 'shadows'
    tilted = quad((0, 0, 0), 0.4, (0.75, 0.5), (1.0, 0.9))
    R = np.array([[1, 0, 0], [0, math.cos(1.2), -math.sin(1.2)], [0, math.sin(1.2), math.cos(1.2)]])
    tilted = ((tilted[0] @ R.T) + np.array([0.0, -0.9, 0.2]), tilted[1], tilted[2])
    V, F, C = merge(main, occl, tilted)
    tm = build_texel_map(V, C, 24)
    cams = [
        make_cam("a", (0.3, 0.3, 2.5), size=96, f=100),
        make_cam("b", (-1.2, -0.2, 2.0), size=96, f=110),
        make_cam("c", (0.5, -2.0, 1.0), size=96, f=90, dist=[-0.1, 0.02, 0.0, 0.0, 0.0]),
    ]
    views = [(c, *render(V, F, C, c)) for c in cams]
    # the ray path is exact (zbuffer vs rays: tests/prep/test_project_uv_zbuffer.py)
    cfg = ProjectConfig(tex_size=24, erode_px=3, visibility="rays")
    proj = UVProjector(F, tm, cfg)
    rgb, ok = proj.samples(V, views)
    ref_rgb, ref_ok = _naive_samples(V, F, tm, views, cfg)
    assert ok.sum() > 300
    # the occluder hides part of the quad from every camera: some front-facing, in-mask texels are rejected
    _, ok_no_occ = proj.samples(V, views, occlusion=False)
    assert np.all(ok_no_occ.sum(0) > ok.sum(0) + 20)
    np.testing.assert_array_equal(ok, ref_ok)
    np.testing.assert_allclose(rgb[ok], ref_rgb[ok], atol=1e-5)
    assert np.all(rgb[~ok] == 0)
    # and the full fusion equals the naive fusion of the naive samples
    fus = proj.project(V, views)
    col, cnt, seen = naive_fuse(ref_rgb.astype(np.float32), ref_ok, "median_band", cfg.band)
    flat = np.zeros((24 * 24, 3), np.float32)
    flat[proj.texels] = col
    np.testing.assert_allclose(fus.texture.reshape(-1, 3), flat, atol=1e-5)
    c2 = np.zeros(24 * 24, int)
    c2[proj.texels] = cnt
    np.testing.assert_array_equal(fus.count.ravel(), c2)


def test_vertex_normals_plane():
    V, F, _ = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    np.testing.assert_allclose(vertex_normals(V, F), np.tile([0, 0, 1.0], (4, 1)))


# --------------------------------------------------------------------------- loading
def test_load_frame_views_roundtrip(tmp_path):
    from gsavatar.data_schema.capture import Capture
    from gsavatar.utils.errors import SchemaError
    from gsavatar.utils.io import write_image

    V, F, C = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    cams = {n: make_cam(n, e, size=64, f=80) for e, n in CAMS3[:2]}
    for n, cam in cams.items():
        img, mask = render(V, F, C, cam)
        write_image(tmp_path / "images" / n / "00000003.png", img)
        write_image(tmp_path / "masks" / n / "00000003.png", mask)
    cap = Capture(tmp_path, 30.0, 5, cams, None, None, None, {}, {n: ".png" for n in cams})  # type: ignore[arg-type]
    views = load_frame_views(cap, 3)
    assert [v[0].name for v in views] == ["c0", "c1"]
    for cam, img, mask in views:
        assert img.shape == (64, 64, 3) and img.dtype == np.float32 and mask.shape == (64, 64)
        ref_img, ref_mask = render(V, F, C, cam)
        assert np.abs(img - ref_img).max() <= 0.5 / 255 + 1e-6
        np.testing.assert_array_equal(mask, ref_mask)
    assert [v[0].name for v in load_frame_views(cap, 3, ["c1"])] == ["c1"]
    write_image(tmp_path / "images" / "c1" / "00000003.png", np.zeros((32, 64, 3)))
    with pytest.raises(SchemaError, match="c1"):
        load_frame_views(cap, 3)


def test_prefetched_frame_views_equal_sequential_reads_and_raise_at_their_frame(tmp_path):
    from gsavatar.data_schema.capture import Capture
    from gsavatar.prep.project_uv import prefetched_frame_views
    from gsavatar.utils.errors import SchemaError
    from gsavatar.utils.io import write_image

    V, F, C = quad((0, 0, 0), 1.0, (0, 0), (1, 1))
    cams = {n: make_cam(n, e, size=48, f=60) for e, n in CAMS3[:2]}
    for fr in range(4):
        for n, cam in cams.items():
            img, mask = render(V, F, C, cam)
            write_image(tmp_path / "images" / n / f"{fr:08d}.png", np.clip(img * (0.5 + 0.1 * fr), 0, 1))
            write_image(tmp_path / "masks" / n / f"{fr:08d}.png", mask)
    cap = Capture(tmp_path, 30.0, 4, cams, None, None, None, {}, {n: ".png" for n in cams})  # type: ignore[arg-type]
    for ahead in (True, False):
        got = list(prefetched_frame_views(cap, [2, 0, 3], uint8=True, ahead=ahead))
        assert [f for f, _ in got] == [2, 0, 3]
        for f, views in got:
            for (c, img, m), (c2, img2, m2) in zip(views, load_frame_views(cap, f, uint8=True)):
                assert c.name == c2.name and img.dtype == np.uint8
                np.testing.assert_array_equal(img, img2)
                np.testing.assert_array_equal(m, m2)
    write_image(tmp_path / "images" / "c1" / "00000003.png", np.zeros((32, 48, 3)))  # frame 3 is bad
    for ahead in (True, False):
        it = prefetched_frame_views(cap, [0, 3], ahead=ahead)
        assert next(it)[0] == 0  # frame 0 arrives although frame 3, read meanwhile, is bad
        with pytest.raises(SchemaError, match="c1"):
            next(it)
    it = prefetched_frame_views(cap, [0, 1, 3])
    next(it)
    it.close()  # stopping early waits for the read in flight and drops it


# --------------------------------------------------------------------------- closed mesh with an xatlas atlas
def test_closed_mesh_with_xatlas_atlas(tmp_path):
    """A self-occluding closed mesh (sphere + 'arm' in front of it), xatlas UVs with seams,
    cameras all around: texels seen by >= 2 views recover a 3D-position texture."""
    import open3d as o3d

    from gsavatar.data_schema.template import Template
    from gsavatar.prep.project_uv import prepare_texel_map

    s = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=24)
    a = o3d.geometry.TriangleMesh.create_sphere(0.12, resolution=10)
    a.translate((0.0, 0.0, 0.75))
    Vs, Fs = np.asarray(s.vertices), np.asarray(s.triangles)
    Va, Fa = np.asarray(a.vertices), np.asarray(a.triangles)
    V = np.concatenate([Vs, Va]).astype(np.float32)
    F = np.concatenate([Fs, Fa + len(Vs)]).astype(np.int64)
    t = Template(V, F, np.zeros((len(V), 1), np.int32), np.ones((len(V), 1), np.float32))

    def f3(p):
        return 0.5 + 0.3 * np.stack(
            [np.sin(3 * p[..., 0] + 1), np.cos(2.5 * p[..., 1]), np.sin(2 * p[..., 2] - p[..., 0])], -1
        )

    cfg = ProjectConfig(tex_size=128, erode_px=3)
    t, tm = prepare_texel_map(t, cfg, tmp_path)
    assert t.corner_uvs is not None and tm.size == 128
    with pytest.raises(ValueError, match="tex_size"):
        UVProjector(F, tm, ProjectConfig(tex_size=64))

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(F.astype(np.uint32)))
    views = []
    for i in range(8):
        ang = 2 * np.pi * i / 8
        eye = (2.2 * np.sin(ang), 0.6 if i % 2 else -0.5, 2.2 * np.cos(ang))
        cam = make_cam(f"r{i}", eye, size=200, f=260)
        hit = scene.cast_rays(o3d.core.Tensor(pixel_rays(cam.K, cam.R, cam.T, 200, 200)))
        m = np.isfinite(hit["t_hit"].numpy())
        prim = hit["primitive_ids"].numpy().astype(np.int64)[m]
        buv = hit["primitive_uvs"].numpy().astype(np.float64)[m]
        w = np.stack([1 - buv[:, 0] - buv[:, 1], buv[:, 0], buv[:, 1]], 1)
        img = np.zeros((200, 200, 3), np.float32)
        img[m] = f3((V[F[prim]].astype(np.float64) * w[..., None]).sum(1))
        views.append((cam, img, m.astype(np.float32)))
    fus = project_uv(V, F, tm, views, cfg)
    gt = np.zeros((128, 128, 3))
    vm = tm.valid
    gt[vm] = f3((V[F[tm.face[vm]]].astype(np.float64) * tm.bary[vm][..., None]).sum(1))
    m = fus.valid & (fus.seen >= 2)
    assert m.sum() > 0.6 * vm.sum()
    assert psnr(fus.texture[m], gt[m]) > 35
    assert fus.valid.sum() > 0.9 * vm.sum()  # cameras all around: almost every texel is seen
