"""The compiled z-buffer path of project-uv (``ProjectConfig.visibility="zbuffer"``) against its oracles.

- each kernel against a naive reference on tiny inputs: the rasterizer against brute-force ray
  casting of every pixel centre, the one-tap mask against the four eroded-mask taps, the fusion
  against ``fuse_samples`` (itself tested against a per-texel python loop);
- without occlusion the z-buffer sampler equals the numpy reference sampler (same tests, same
  float32 arithmetic);
- with occlusion it agrees with the open3d ray path (``visibility="rays"``) except near occluding
  contours: the depth buffer decides by the triangle at the nearest pixel centre, the rays by the
  exact segment, so texels within about a pixel of a contour can differ (and gaps thinner than
  ``occlusion_eps`` along the ray). Asserted: < 1.5 % of the seen (texel, view) pairs (measured 0.12 %
  on the closed-sphere scene); colours identical to 1e-6 on samples both paths keep.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from gsavatar.prep.project_uv import ProjectConfig, UVProjector, erode_mask, fuse_samples, is_closed, project_uv
from gsavatar.prep.uv_atlas import build_texel_map
from gsavatar.prep import zbuffer as zb

from prep.test_project_uv import make_cam, merge, quad, render  # shared scene helpers (tests/ is on sys.path)


# --------------------------------------------------------------------------- scenes
def occluder_scene(size=96):
    """Quad + floating occluder + tilted quad (the naive-reference scene of test_project_uv), 3 views."""
    main = quad((0, 0, 0), 1.0, (0.0, 0.0), (0.7, 1.0))
    occl = quad((0.1, 0.05, 0.5), 0.3, (0.75, 0.0), (1.0, 0.3))
    tilted = quad((0, 0, 0), 0.4, (0.75, 0.5), (1.0, 0.9))
    R = np.array([[1, 0, 0], [0, math.cos(1.2), -math.sin(1.2)], [0, math.sin(1.2), math.cos(1.2)]])
    tilted = ((tilted[0] @ R.T) + np.array([0.0, -0.9, 0.2]), tilted[1], tilted[2])
    V, F, C = merge(main, occl, tilted)
    cams = [
        make_cam("a", (0.3, 0.3, 2.5), size=size, f=size * 1.05),
        make_cam("b", (-1.2, -0.2, 2.0), size=size, f=size * 1.15),
        make_cam("c", (0.5, -2.0, 1.0), size=size, f=size * 0.95, dist=[-0.1, 0.02, 0.0, 0.0, 0.0]),
    ]
    return V, F, C, cams


def sphere_scene(tmp_path, size=160, tex=128):
    """Closed, self-occluding mesh (sphere + small sphere in front), xatlas UVs, 6 views around."""
    import open3d as o3d

    from gsavatar.data_schema.template import Template
    from gsavatar.prep.project_uv import prepare_texel_map

    s = o3d.geometry.TriangleMesh.create_sphere(0.5, resolution=24)
    a = o3d.geometry.TriangleMesh.create_sphere(0.12, resolution=10)
    a.translate((0.0, 0.0, 0.75))
    V = np.concatenate([np.asarray(s.vertices), np.asarray(a.vertices)]).astype(np.float32)
    F = np.concatenate([np.asarray(s.triangles), np.asarray(a.triangles) + len(s.vertices)]).astype(np.int64)
    t = Template(V, F, np.zeros((len(V), 1), np.int32), np.ones((len(V), 1), np.float32))
    cfg = ProjectConfig(tex_size=tex, erode_px=3)
    t, tm = prepare_texel_map(t, cfg, tmp_path)
    cams = []
    for i in range(6):
        ang = 2 * np.pi * i / 6
        eye = (2.2 * math.sin(ang), 0.4 * (-1) ** i, 2.2 * math.cos(ang))
        dist = [-0.08, 0.01, 0.0, 0.0, 0.0] if i == 1 else None
        cams.append(make_cam(f"s{i}", eye, size=size, f=size * 1.3, dist=dist))
    return t, tm, cfg, cams


def _views(V, F, C, cams):
    return [(c, *render(V, F, C, c)) for c in cams]


def _render_closed(t, cams):
    """Views of a template whose colour is a function of the 3D hit point (no UVs needed)."""
    import open3d as o3d

    from gsavatar.geometry.camera import pixel_rays

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(t.vertices.astype(np.float32)), o3d.core.Tensor(t.faces.astype(np.uint32)))
    out = []
    for cam in cams:
        rays = pixel_rays(cam.K, cam.R, cam.T, cam.width, cam.height, cam.dist)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        th = hit["t_hit"].numpy()
        m = np.isfinite(th)
        p = rays[..., :3] + rays[..., 3:] * np.where(m, th, 0)[..., None]
        img = np.full((cam.height, cam.width, 3), 0.1, np.float32)
        img[m] = 0.5 + 0.3 * np.stack([np.sin(6 * p[m][:, 0] + 1), np.cos(5 * p[m][:, 1]), np.sin(4 * p[m][:, 2])], -1)
        out.append((cam, img, m.astype(np.float32)))
    return out


# --------------------------------------------------------------------------- kernels vs naive references
def _naive_raster(vc, F, H, W, fx, cx, fy, cy):
    """Front triangle at every pixel centre by brute force (camera space, pinhole grid, no clipping needed)."""
    out = np.full((H, W), -1, np.int64)
    best = np.full((H, W), np.inf)
    for y in range(H):
        for x in range(W):
            d = np.array([(x - cx) / fx, (y - cy) / fy, 1.0])  # ray X = s d, depth s
            for f, (a, b, c) in enumerate(F):
                A, B, Cc = vc[a], vc[b], vc[c]
                e1, e2 = B - A, Cc - A
                p = np.cross(d, e2)
                det = e1 @ p
                if abs(det) < 1e-15:
                    continue
                u = (-A @ p) / det
                q = np.cross(-A, e1)
                v = (d @ q) / det
                s = (e2 @ q) / det
                if u >= -1e-9 and v >= -1e-9 and u + v <= 1 + 1e-9 and 0 < s < best[y, x]:
                    best[y, x], out[y, x] = s, f
    return out


def test_rasterizer_matches_brute_force_ray_casting():
    rng = np.random.default_rng(0)
    # random triangles in front of the camera, overlapping, plus one crossing the near plane
    n = 14
    centres = rng.uniform([-0.6, -0.6, 1.0], [0.6, 0.6, 3.0], (n, 1, 3))
    V = (centres + rng.normal(0, 0.35, (n, 3, 3))).reshape(-1, 3)
    V[2::3, 2] = np.maximum(V[2::3, 2], 0.3)
    V = np.concatenate(
        [V, [[0.35, 0.3, 0.9], [0.55, 0.3, 1.0], [0.45, 0.45, -0.3]]]
    )  # crosses z = 0: a wedge to a corner
    F = np.arange(len(V)).reshape(-1, 3)
    H, W, fx, cx, fy, cy = 40, 48, 30.0, 23.3, 28.0, 19.6
    tri = np.full((H, W), -1, np.int32)
    invz = np.zeros((H, W), np.float32)
    planes = np.empty((len(F), 4))
    zb.rasterize(V.astype(np.float64), F, fx, 0.0, cx, fy, cy, 1e-6, False, tri, invz, planes)
    ref = _naive_raster(V, F, H, W, fx, cx, fy, cy)
    covered = ref >= 0
    assert covered.sum() > 250 and len(np.unique(ref[covered])) > 6
    same = tri == ref
    assert same.mean() > 0.99, same.mean()
    # where they differ: a pixel centre on a silhouette edge (coverage ties between the edge-function and the
    # Moller-Trumbore tolerance), or two triangles at the same depth up to float32 (intersection line)
    for y, x in zip(*np.nonzero(~same)):
        if tri[y, x] < 0 or ref[y, x] < 0:
            continue
        d = np.array([(x - cx) / fx, (y - cy) / fy, 1.0])
        za = planes[tri[y, x], 3] / (planes[tri[y, x], :3] @ d)
        zr = planes[ref[y, x], 3] / (planes[ref[y, x], :3] @ d)
        assert abs(za - zr) < 1e-4 * abs(zr)
    # the near-plane-crossing triangle is drawn (its visible part is in front of everything)
    assert (tri == len(F) - 1).sum() > 20
    # planes: n . X = d holds at the vertices
    for f, (a, b, c) in enumerate(F):
        for k in (a, b, c):
            assert abs(planes[f, :3] @ V[k] - planes[f, 3]) < 1e-9


def test_back_face_culling_changes_nothing_on_a_closed_mesh(tmp_path):
    t, tm, cfg, cams = sphere_scene(tmp_path, size=64, tex=32)
    assert is_closed(t.faces) and not is_closed(t.faces[:-1])
    cam = cams[0]
    vc = zb.transform(t.vertices.astype(np.float64), cam.R.astype(np.float64), cam.T.astype(np.float64))
    bufs = []
    for cull in (False, True):
        tri = np.full((64, 64), -1, np.int32)
        zb.rasterize(
            vc,
            t.faces,
            cam.K[0, 0],
            0.0,
            cam.K[0, 2],
            cam.K[1, 1],
            cam.K[1, 2],
            1e-6,
            cull,
            tri,
            np.zeros((64, 64), np.float32),
            np.empty((len(t.faces), 4)),
        )
        bufs.append(tri)
    assert (bufs[0] >= 0).sum() > 1000
    np.testing.assert_array_equal(bufs[0], bufs[1])


@pytest.mark.parametrize("erode_px", [0, 1, 3, 4, 5])
def test_quad_foreground_equals_four_eroded_taps(erode_px):
    rng = np.random.default_rng(erode_px)
    H, W = 37, 41
    mask = (rng.uniform(size=(H, W)) > 0.15).astype(np.float32)
    mask[10:20, 5:30] = 1.0
    E = erode_mask(mask, (H, W), erode_px, 0.5)
    ref = np.zeros((H, W), bool)
    ref[:-1, :-1] = E[:-1, :-1] & E[:-1, 1:] & E[1:, :-1] & E[1:, 1:]
    q = zb.quad_foreground(mask, (H, W), erode_px, 0.5)
    # the sampler only reads (x, y) with x <= W-2, y <= H-2
    np.testing.assert_array_equal(q[:-1, :-1], ref[:-1, :-1])
    assert ref[:-1, :-1].any() and not ref[:-1, :-1].all()


@pytest.mark.parametrize("fusion", ["median_band", "mean"])
def test_fuse_kernel_equals_fuse_samples(fusion):
    rng = np.random.default_rng(5)
    N, C = 4000, 7
    base = rng.uniform(0.05, 0.9, (N, 1, 3))
    gain = rng.choice([1.0, 1.0, 0.95, 1.05, 0.6, 1.5, 1.3, 0.85, 1.12], size=(N, C, 1))
    rgb = np.clip(base * gain + rng.normal(0, 0.01, (N, C, 3)), 0, 1).astype(np.float32)
    rgb[:50] = rgb[:50, :1]  # ties
    rgb[50:60] = 0.0
    ok = rng.uniform(size=(N, C)) < rng.uniform(0, 1, (N, 1))
    ok[:20] = False
    ok[60:70] = False
    ok[60:70, :2] = True  # even count, far apart -> fallback
    rgb[60:70, 1] *= 2.5
    ref = fuse_samples(rgb, ok, fusion, (0.8, 1.1))
    col, cnt, seen = np.zeros((N, 3), np.float32), np.zeros(N, np.int64), np.zeros(N, np.int64)
    zb.set_threads()
    zb.fuse(
        np.ascontiguousarray(rgb.transpose(1, 0, 2)),
        np.ascontiguousarray(ok.T),
        fusion == "median_band",
        0.8,
        1.1,
        col,
        cnt,
        seen,
    )
    np.testing.assert_array_equal(cnt, ref[1])
    np.testing.assert_array_equal(seen, ref[2])
    np.testing.assert_array_equal(col, ref[0])  # same float64 accumulation order: bit-identical


# --------------------------------------------------------------------------- sampler vs the numpy reference
def test_zbuffer_sampler_without_occlusion_equals_reference():
    V, F, C, cams = occluder_scene()
    views = _views(V, F, C, cams)
    tm = build_texel_map(V, C, 24)
    ref = UVProjector(F, tm, ProjectConfig(tex_size=24, erode_px=3, visibility="rays"))
    new = UVProjector(F, tm, ProjectConfig(tex_size=24, erode_px=3, visibility="zbuffer"))
    r_rgb, r_ok = ref.samples(V, views, occlusion=False)
    n_rgb, n_ok = new.samples(V, views, occlusion=False)
    assert r_ok.sum() > 300
    np.testing.assert_array_equal(n_ok, r_ok)
    np.testing.assert_array_equal(n_rgb, r_rgb)


def _agreement(V, F, tm, views, cfg):
    rays = UVProjector(F, tm, replace(cfg, visibility="rays"))
    zbuf = UVProjector(F, tm, replace(cfg, visibility="zbuffer"))
    r_rgb, r_ok = rays.samples(V, views)
    z_rgb, z_ok = zbuf.samples(V, views)
    _, no_occ = rays.samples(V, views, occlusion=False)
    both = r_ok & z_ok
    np.testing.assert_allclose(z_rgb[both], r_rgb[both], atol=1e-6)
    assert np.all(z_ok <= no_occ)  # the z-buffer only removes samples the geometric/mask tests kept
    return rays, zbuf, r_ok, z_ok, no_occ


def test_zbuffer_visibility_agrees_with_rays_occluder_scene():
    V, F, C, cams = occluder_scene(size=128)
    views = _views(V, F, C, cams)
    tm = build_texel_map(V, C, 48)
    cfg = ProjectConfig(tex_size=48, erode_px=3)
    rays, zbuf, r_ok, z_ok, no_occ = _agreement(V, F, tm, views, cfg)
    occluded = no_occ & ~r_ok
    assert occluded.sum() > 200  # the occluder really hides texels
    # the z-buffer hides the same texels: disagreement is a thin band along the occluder's outline
    assert (z_ok != r_ok).mean() < 0.015, (z_ok != r_ok).mean()
    assert (occluded & z_ok).sum() < 0.1 * occluded.sum()
    fr, fz = rays.project(V, views), zbuf.project(V, views)
    m = fr.valid & fz.valid & (fr.seen == fz.seen)
    np.testing.assert_allclose(fz.texture[m], fr.texture[m], atol=1e-5)
    assert m.sum() > 0.95 * fr.valid.sum()


def test_zbuffer_visibility_agrees_with_rays_closed_mesh(tmp_path):
    t, tm, cfg, cams = sphere_scene(tmp_path)
    views = _render_closed(t, cams)
    assert is_closed(t.faces)
    rays, zbuf, r_ok, z_ok, no_occ = _agreement(t.vertices, t.faces, tm, views, cfg)
    assert r_ok.sum() > 5000 and (no_occ & ~r_ok).sum() > 300  # the small sphere occludes the big one
    diff = z_ok != r_ok
    assert diff.sum() / r_ok.sum() < 0.015, diff.sum() / r_ok.sum()
    fr, fz = rays.project(t.vertices, views), zbuf.project(t.vertices, views)
    m = fr.valid & fz.valid & (fr.seen == fz.seen)
    np.testing.assert_allclose(fz.texture[m], fr.texture[m], atol=1e-5)
    assert m.sum() > 0.95 * fr.valid.sum()
    # texture-level agreement including the differing texels (PSNR between the two paths)
    both = fr.valid & fz.valid
    mse = float(np.mean((fr.texture[both].astype(np.float64) - fz.texture[both]) ** 2))
    assert 10 * math.log10(1 / max(mse, 1e-20)) > 45


def test_project_equals_samples_then_fuse(tmp_path):
    """The fused block kernel (project) equals sample_view per view followed by fuse_samples."""
    t, tm, cfg, cams = sphere_scene(tmp_path, size=96, tex=64)
    views = _render_closed(t, cams)
    proj = UVProjector(t.faces, tm, cfg)
    rgb, ok = proj.samples(t.vertices, views)
    col, cnt, seen = fuse_samples(rgb, ok, cfg.fusion, cfg.band)
    fus = proj.project(t.vertices, (v for v in views))  # a generator, like iter_frame_views
    S = tm.size
    flat = np.zeros((S * S, 3), np.float32)
    flat[proj.texels] = col
    np.testing.assert_array_equal(fus.texture.reshape(-1, 3), flat)
    c2 = np.zeros(S * S, np.int64)
    c2[proj.texels] = seen
    np.testing.assert_array_equal(fus.seen.ravel(), c2)
    assert fus.valid.sum() > 1000


def test_uint8_images_equal_float_images():
    V, F, C, cams = occluder_scene()
    views = _views(V, F, C, cams)
    views8 = [(c, np.round(im * 255).astype(np.uint8), m) for c, im, m in views]
    viewsf = [(c, im.astype(np.float32) / np.float32(255), m) for c, im, m in views8]
    tm = build_texel_map(V, C, 24)
    a = project_uv(V, F, tm, views8, ProjectConfig(tex_size=24, erode_px=3))
    b = project_uv(V, F, tm, viewsf, ProjectConfig(tex_size=24, erode_px=3))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_image_with_foreground_packs_rgb_and_the_flag():
    rng = np.random.default_rng(0)
    for dtype in (np.uint8, np.float32):
        img = rng.integers(0, 256, (7, 9, 3)).astype(dtype)
        fg = rng.random((7, 9)) > 0.4
        out = zb.image_with_foreground(img, fg)
        assert out.shape == (63, 4) and out.dtype == dtype
        np.testing.assert_array_equal(out[:, :3], img.reshape(-1, 3))
        np.testing.assert_array_equal(out[:, 3] != 0, fg.ravel())


@pytest.mark.parametrize("erode_px", [0, 1, 3, 5])
def test_region_rgba_is_the_whole_image_buffer_cut_to_the_foreground(erode_px):
    """The kernels' RGBA buffer of the mask's region equals the whole-image buffer there, and every flag
    outside the region is 0 in the whole-image buffer (so rejecting taps outside the region is exact)."""
    rng = np.random.default_rng(erode_px)
    H, W = 60, 80
    img = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    cases = {
        "inside": (slice(20, 40), slice(30, 55)),
        "at the border": (slice(0, 25), slice(60, 80)),
        "whole": (slice(0, H), slice(0, W)),
    }
    for name, (ys, xs) in cases.items():
        mask = np.zeros((H, W), np.float32)
        mask[ys, xs] = rng.uniform(size=mask[ys, xs].shape) > 0.1
        mask[ys.start + 2 : ys.stop - 2, xs.start + 2 : xs.stop - 2] = 1.0
        full = zb.image_with_foreground(img, zb.quad_foreground(mask, (H, W), erode_px)).reshape(H, W, 4)
        rgba, (x0, y0, w, h) = zb.region_rgba(img, mask, erode_px)
        np.testing.assert_array_equal(rgba.reshape(h, w, 4), full[y0 : y0 + h, x0 : x0 + w], err_msg=name)
        outside = np.ones((H, W), bool)
        outside[y0 : y0 + h, x0 : x0 + w] = False
        assert not full[..., 3][outside].any(), name
        assert full[..., 3].any() and (name == "whole" or outside.any())
    assert zb.region_rgba(img, np.zeros((H, W), np.float32), erode_px) is None
    rgba, box = zb.region_rgba(img, None, erode_px)
    assert box == (0, 0, W, H) and rgba[:, 3].all()
    # a buffer from an earlier, larger view is reused
    buf = np.empty((H * W, 4), np.uint8)
    rgba2, _ = zb.region_rgba(img, mask, erode_px, out=buf)
    assert np.shares_memory(rgba2, buf)


def test_block_facing_bound_never_culls_a_facing_texel(tmp_path):
    """_faces_away against the texels' own facing test, on blocks of a closed sphere scene seen from 6
    sides (incl. zero normals and a negative min_cos); then project_frame with small blocks (culling active)
    equals sample_view per view followed by fuse."""
    from numba.typed import List

    t, tm, cfg, cams = sphere_scene(tmp_path, size=96, tex=64)
    views = _render_closed(t, cams)
    proj = UVProjector(t.faces, tm, cfg)
    zf = proj._zbuffer_views(t.vertices, views, 0)
    P, Nrm = zf.P.copy(), zf.Nrm.copy()
    Nrm[:, 5] = 0.0  # a zero normal: its block must never be culled
    N, block = P.shape[1], 32
    culled = 0
    for min_cos in (0.1, 0.0, -0.3):
        for s0 in range(0, N, block):
            n = min(N, s0 + block) - s0
            bnd = np.empty(zb.BND_SIZE)
            zb._block_bounds(P, Nrm, s0, n, bnd)
            for cp in zf.cams:
                if zb._faces_away(bnd, cp, min_cos):
                    culled += 1
                    tv = cp[[zb.CAM_CENTER_X, zb.CAM_CENTER_Y, zb.CAM_CENTER_Z], None] - P[:, s0 : s0 + n]
                    nt = (Nrm[:, s0 : s0 + n] * tv).sum(0)
                    assert not np.any(nt >= min_cos * np.linalg.norm(tv, axis=0)), (s0, min_cos)
                    assert not (s0 <= 5 < s0 + n)
    assert culled > 0.2 * 3 * len(zf.cams) * (N // block)  # a sphere seen from around: many blocks face away
    rgb, ok = np.zeros((len(zf.cams), N, 3), np.float32), np.zeros((len(zf.cams), N), bool)
    u8 = zf.imgs[0].dtype == np.uint8
    for k in range(len(zf.cams)):
        zb.sample_view(
            P,
            Nrm,
            proj._z_tri,
            proj.faces,
            zf.cams[k],
            zf.imgs[k],
            u8,
            True,
            zf.tri_ids[k],
            zf.planes[k],
            cfg.occlusion_eps,
            cfg.min_cos,
            rgb[k],
            ok[k],
        )
    ref = [np.zeros((N, 3), np.float32), np.zeros(N, np.int64), np.zeros(N, np.int64)]
    zb.fuse(rgb, ok, True, cfg.band[0], cfg.band[1], *ref)
    out = [np.zeros((N + 3, 3), np.float32), np.zeros(N + 3, np.uint8), np.zeros(N + 3, np.uint8)]
    perm = np.random.default_rng(0).permutation(N + 3)[:N]  # results land at out_index
    for b in (block, 7):
        zb.project_frame(
            P,
            Nrm,
            proj._z_tri,
            proj.faces,
            np.stack(zf.cams),
            List(zf.imgs),
            u8,
            True,
            List(zf.tri_ids),
            List(zf.planes),
            cfg.occlusion_eps,
            cfg.min_cos,
            True,
            cfg.band[0],
            cfg.band[1],
            b,
            perm,
            *out,
        )
        for r, o in zip(ref, out):
            np.testing.assert_array_equal(o[perm], r.astype(o.dtype))
    assert ok.sum() > 2000


def test_read_image_keep_uint8_is_the_float_read_times_255(tmp_path):
    import cv2

    from gsavatar.utils.io import read_image

    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    for name in ("a.png", "a.jpg"):
        cv2.imwrite(str(tmp_path / name), rgb[..., ::-1])
        u8 = read_image(tmp_path / name, keep_uint8=True)
        f = read_image(tmp_path / name)
        assert u8.dtype == np.uint8 and u8.shape == f.shape
        np.testing.assert_array_equal(u8.astype(np.float32) / np.float32(255), f)
    cv2.imwrite(str(tmp_path / "b.png"), (rgb.astype(np.uint16) * 257)[..., ::-1])  # 16-bit: float either way
    assert read_image(tmp_path / "b.png", keep_uint8=True).dtype == np.float32


def test_visibility_config_validated():
    with pytest.raises(ValueError, match="visibility"):
        ProjectConfig(visibility="raster")  # type: ignore[arg-type]


def test_dataset_projected_before_the_zbuffer_keeps_its_method_and_id(tiny_capture, tiny_dataset, tmp_path, capsys):
    """A dataset whose project-uv record predates ``visibility`` (ray cast by an older gsavatar) is complete:
    re-running prep neither recomputes it (which would change the content id and strand every run trained
    on it) nor records a new config; --force recomputes with the configured method."""
    import json
    import shutil

    from gsavatar.data_schema.dataset import dataset_fingerprint
    from gsavatar.prep.cli import main

    ds = tmp_path / "dataset"
    shutil.copytree(tiny_dataset, ds)
    obj = json.loads((ds / "dataset.json").read_text())
    assert obj["stages"]["project-uv"]["config"].pop("visibility") == "zbuffer"
    (ds / "dataset.json").write_text(json.dumps(obj, indent=1))
    before = dataset_fingerprint(ds)
    args = [
        "project-uv",
        "--capture",
        str(tiny_capture),
        "--out",
        str(ds),
        "--workers",
        "1",
        "--project.tex-size",
        "128",
    ]
    capsys.readouterr()
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "keeping its ray-cast visibility" in out and "complete, skipping" in out
    assert dataset_fingerprint(ds) == before
    assert main([*args, "--force"]) == 0  # recomputed with the z-buffer and recorded as such
    assert json.loads((ds / "dataset.json").read_text())["stages"]["project-uv"]["config"]["visibility"] == "zbuffer"
