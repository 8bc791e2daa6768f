"""Synthetic captures: renderer vs. naive references, appearance model, ``tiny`` snapshot.

The snapshot (``tests/synth/snapshots/tiny.npz``) pins a few small statistics of the
``tiny`` preset. When the body, retargeting, appearance or renderer change ON PURPOSE,
regenerate it with::

    cd /work/main && ANNY_CACHE_DIR=.cache/anny PYTHONPATH=src .venv/bin/python tests/synth/test_synth_render.py --regen

Tests that need the Anny body use ``$ANNY_CACHE_DIR`` (default ``<repo>/.cache/anny``) and
are skipped when that cache has not been built.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema import Camera, Template
from gsavatar.data_schema.rig import rig_from_json
from gsavatar.geometry.camera import look_at, project
from gsavatar.synth.appearance import AppearanceConfig, AppearanceModel
from gsavatar.synth.cameras import dome_kinds, make_dome, special_cameras
from gsavatar.synth.render import (
    FrameScene,
    box_downsample,
    box_mesh,
    pose_vertices,
    render_view,
    render_views,
    sample_texture,
    supersampled_rays,
    texel_visibility,
)

REPO = Path(__file__).resolve().parents[2]
SNAPSHOT = Path(__file__).parent / "snapshots" / "tiny.npz"


# --------------------------------------------------------------------------- fixtures
def quad(z: float = 0.0, half: float = 0.5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A square in the plane z, UV = (x, y) mapped from [-half, half] to [0, 1] (v up = +y)."""
    V = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    uv = (V[:, :2] + half) / (2 * half)
    return V, F, uv[F]


def front_camera(
    w: int = 64, h: int = 48, f: float = 60.0, dist=np.zeros(5), d: float = 2.0, c: tuple[float, float] = (31.7, 23.4)
) -> Camera:
    """Camera on +z looking at the origin (image x = world +x, image y = world -y)."""
    R, T = look_at(np.array([0.0, 0.0, d]), np.zeros(3))
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])
    return Camera("front", K, R, T, np.asarray(dist, np.float64), w, h)


def ramp_texture(size: int = 32) -> np.ndarray:
    """Texel centres hold (u, v, 0.25): bilinear interpolation reproduces (u, v) exactly inside."""
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32)
    return np.stack([(xs + 0.5) / size, 1 - (ys + 0.5) / size, np.full_like(xs, 0.25)], -1)


def cylinder_body(n_around: int = 40, n_up: int = 48, radius: float = 0.16, height: float = 1.7):
    """Stand-in body: a UV-mapped open cylinder (+Y up, feet at 0) with a Hips/Spine/Head rig."""
    a = np.linspace(0, 2 * np.pi, n_around + 1)
    y = np.linspace(0, height, n_up + 1)
    A, Y = np.meshgrid(a, y)
    V = np.stack([radius * np.sin(A), Y, radius * np.cos(A)], -1).reshape(-1, 3).astype(np.float32)
    UV = np.stack([A / (2 * np.pi) * 0.96 + 0.02, Y / height * 0.96 + 0.02], -1).reshape(-1, 2).astype(np.float32)
    idx = np.arange(len(V)).reshape(n_up + 1, n_around + 1)
    q0, q1, q2, q3 = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    F = np.concatenate([np.stack([q0, q1, q2], -1).reshape(-1, 3), np.stack([q0, q2, q3], -1).reshape(-1, 3)])
    rig = rig_from_json(
        {
            "joints": [
                {"name": "Hips", "parent": None, "head": [0, 0.9, 0]},
                {"name": "Spine", "parent": "Hips", "head": [0, 1.0, 0]},
                {"name": "Head", "parent": "Spine", "head": [0, 1.5, 0]},
            ],
            "pose_params": [
                {"name": "Spine.rx", "joint": "Spine", "kind": "euler", "axis": [1, 0, 0]},
                {"name": "Head.ry", "joint": "Head", "kind": "euler", "axis": [0, 1, 0]},
            ],
            "groups": {"torso_head": ["Spine.rx", "Head.ry"]},
        }
    )
    w1 = np.clip((V[:, 1] - 0.8) / 0.4, 0, 1)
    wh = np.clip((V[:, 1] - 1.45) / 0.1, 0, 1)
    W = np.stack([1 - w1, w1 * (1 - wh), wh], 1).astype(np.float32)
    W /= W.sum(1, keepdims=True)
    I = np.tile(np.arange(3, dtype=np.int32), (len(V), 1))
    return Template(V, F.astype(np.int64), I, W, UV, F.astype(np.int64)), rig


def anny_cache() -> Path:
    return Path(os.environ.get("ANNY_CACHE_DIR", REPO / ".cache" / "anny"))


@pytest.fixture(scope="session")
def anny_cache_dir() -> Path:
    # anny is installed by scripts/setup.sh; the first use builds its cache (~75 s), later ones reuse it
    pytest.importorskip("anny")
    return anny_cache()


@pytest.fixture(scope="session")
def tiny_capture(anny_cache_dir, tmp_path_factory) -> Path:
    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset

    return make_capture(preset("tiny"), tmp_path_factory.mktemp("tiny_a") / "cap", anny_cache_dir, progress=False)


# --------------------------------------------------------------------------- renderer
def test_sample_texture_bilinear_is_exact_on_a_ramp():
    tex = ramp_texture(32)
    rng = np.random.default_rng(0)
    uv = rng.uniform(0.5 / 32, 1 - 0.5 / 32, (500, 2)).astype(np.float32)  # inside the texel-centre hull
    got = sample_texture(tex, uv)
    np.testing.assert_allclose(got[:, :2], uv, atol=1e-5)
    np.testing.assert_allclose(got[:, 2], 0.25, atol=1e-6)
    # OBJ convention: v = 1 is the TOP row; clamp-to-edge outside.
    corner = sample_texture(tex, np.array([[0.0, 1.0], [1.0, 0.0]], np.float32))
    np.testing.assert_allclose(corner[0, :2], [0.5 / 32, 1 - 0.5 / 32], atol=1e-6)
    np.testing.assert_allclose(corner[1, :2], [1 - 0.5 / 32, 0.5 / 32], atol=1e-6)


def naive_quad_render(cam: Camera, half: float = 0.5):
    """Reference: intersect every pixel-centre ray with the plane z=0 analytically (no distortion)."""
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    xn = (xs - cam.K[0, 2]) / cam.K[0, 0]
    yn = (ys - cam.K[1, 2]) / cam.K[1, 1]
    d = np.stack([xn, yn, np.ones_like(xn)], -1) @ cam.R  # world directions
    o = cam.center
    t = -o[2] / d[..., 2]
    p = o + t[..., None] * d
    inside = (np.abs(p[..., 0]) < half) & (np.abs(p[..., 1]) < half)
    uv = (p[..., :2] + half) / (2 * half)
    return inside, uv


def test_render_quad_matches_analytic_texture():
    V, F, cuv = quad()
    cam = front_camera()
    scene = FrameScene(V, F, cuv, nthreads=1)
    out = render_view(scene, cam, ramp_texture(32), supersample=1, shading=None, background=(0.1, 0.2, 0.3))
    inside, uv = naive_quad_render(cam)
    core = inside & np.all((uv > 1 / 32) & (uv < 1 - 1 / 32), -1)
    assert core.sum() > 500
    np.testing.assert_allclose(out.image[core][:, :2], uv[core], atol=2e-4)
    np.testing.assert_allclose(out.image[core][:, 2], 0.25, atol=1e-6)
    np.testing.assert_allclose(
        out.image[~inside], np.broadcast_to([0.1, 0.2, 0.3], (int((~inside).sum()), 3)), atol=1e-6
    )
    assert np.all(out.mask[inside] == 1) and np.all(out.mask[~inside] == 0)


def test_mask_coverage_matches_projected_area():
    # Edges at fractional pixel positions; 4x4 supersampling estimates the covered area.
    V, F, cuv = quad(half=0.37)
    cam = front_camera(f=57.3)
    out = render_view(FrameScene(V, F, cuv), cam, ramp_texture(8), supersample=4, shading=None)
    side_px = 57.3 * 0.74 / 2.0
    assert abs(out.mask.sum() - side_px**2) / side_px**2 < 0.01
    # A pixel cut in half by a vertical edge: edge at pixel x = c + f * 0.37 / 2.
    cam2 = front_camera(f=60.0, c=(32.0 + 60 * 0.37 / 2, 24.0))  # left edge through the centre of column 32
    m = render_view(FrameScene(V, F, cuv), cam2, ramp_texture(8), supersample=4, shading=None).mask
    np.testing.assert_allclose(m[24, 32], 0.5, atol=1e-6)
    assert m[24, 31] == 0 and m[24, 33] == 1


def test_distorted_rays_hit_where_points_project():
    V, F, cuv = quad(half=2.0)
    cam = front_camera(w=80, h=60, f=45.0, dist=np.array([0.05, -0.01, 1e-3, -5e-4, 0.0]), c=(40.3, 29.6))
    scene = FrameScene(V, F, cuv, nthreads=1)
    rays = supersampled_rays(cam, 1)
    pix = np.array([[0, 0], [79, 0], [0, 59], [79, 59], [40, 30], [11, 47]])
    r = rays[pix[:, 1], pix[:, 0]]
    hits = scene.cast(r)
    assert np.all(hits.geometry == 0)
    hit = np.einsum("nk,nkc->nc", hits.bary, V[F[hits.primitive]])
    proj = project(hit.astype(np.float64), cam.K, cam.R, cam.T, cam.dist)
    np.testing.assert_allclose(proj.pixels, pix, atol=1e-3)
    # Distortion matters here: the undistorted projection is off by pixels at the corners.
    plain = project(hit.astype(np.float64), cam.K, cam.R, cam.T, None)
    assert np.abs(plain.pixels - pix).max() > 0.5


def test_supersampled_rays_average_to_pixel_rays():
    cam = front_camera(dist=np.array([0.03, 0.0, 0.0, 0.0, 0.0]))
    r1 = supersampled_rays(cam, 1)
    r3 = supersampled_rays(cam, 3)
    # The middle sub-sample of a 3x3 block is the pixel centre.
    np.testing.assert_allclose(r3[1::3, 1::3], r1, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("s", [1, 2, 3, 5])
def test_box_downsample_is_numpys_block_mean_bit_for_bit(s, dtype):
    """The fast supersample filter against its oracle, numpy's mean over the block axes: the same bits (so captures
    rendered before and after it are byte-identical), odd sizes and magnitudes included."""
    rng = np.random.default_rng(s)
    for H, W, scale in ((1, 1, 1.0), (7, 13, 1e-3), (33, 20, 1e3), (64, 64, 1.0)):
        x = (rng.random((H * s, W * s, 3)) * scale).astype(dtype)
        want = x.reshape(H, s, W, s, 3).mean((1, 3))
        got = box_downsample(x, s)
        assert got.dtype == want.dtype and got.shape == (H, W, 3)
        assert np.array_equal(got, want)
    with pytest.raises(ValueError, match="does not split"):
        box_downsample(np.zeros((5, 4, 3), dtype), 2)


def test_shading_is_mild_and_two_sided():
    V, F, cuv = quad()
    cam = front_camera()
    scene = FrameScene(V, F, cuv)
    tex = np.full((8, 8, 3), 0.8, np.float32)
    lit = render_view(scene, cam, tex, supersample=1).image
    flat = render_view(scene, cam, tex, supersample=1, shading=None).image
    inside = naive_quad_render(cam)[0]
    ratio = lit[inside] / flat[inside]
    assert np.all(ratio >= 0.65 - 1e-6) and np.all(ratio <= 1.0 + 1e-6)
    back = render_view(scene, front_camera(d=-2.0), tex, supersample=1).image  # behind the quad
    assert back.max() > 0.5  # two-sided: no black back faces


def test_occluder_hides_the_body_in_its_view_only():
    V, F, cuv = quad()
    cam = front_camera()
    other = Camera("other", cam.K, cam.R, cam.T, cam.dist, cam.width, cam.height)
    box = box_mesh((-0.5, 0.0, 0.6), (1.0, 2.0, 0.2), color=(0.0, 1.0, 0.0))  # covers x < 0 of the quad
    out = render_views(
        V,
        F,
        cuv,
        ramp_texture(8),
        {"front": cam, "other": other},
        supersample=1,
        shading=None,
        occluders={"front": [box]},
    )
    inside, uv = naive_quad_render(cam)
    left, right = inside & (uv[..., 0] < 0.4), inside & (uv[..., 0] > 0.6)
    assert np.all(out["front"].mask[left] == 0) and np.all(out["front"].mask[right] == 1)
    np.testing.assert_allclose(out["front"].image[left], np.broadcast_to([0, 1, 0], (int(left.sum()), 3)))
    assert np.all(out["other"].mask[inside] == 1)


def test_texel_visibility_matches_occlusion_and_frustum():
    V, F, cuv = quad()
    cam = front_camera()
    rng = np.random.default_rng(1)
    face = rng.integers(0, 2, 400)
    bary = rng.dirichlet(np.ones(3), 400).astype(np.float32)
    p = np.einsum("nk,nkc->nc", bary, V[F[face]])
    assert texel_visibility(FrameScene(V, F, cuv), face, bary, cam).all()
    box = box_mesh((-0.5, 0.0, 0.6), (1.0, 2.0, 0.2))
    vis = texel_visibility(FrameScene(V, F, cuv, extras=[box]), face, bary, cam)
    np.testing.assert_array_equal(vis[np.abs(p[:, 0]) > 0.05], p[np.abs(p[:, 0]) > 0.05, 0] > 0)
    narrow = front_camera(w=16, h=16, c=(8.0, 8.0))  # sees only |x|, |y| < ~0.27
    vis = texel_visibility(FrameScene(V, F, cuv), face, bary, narrow)
    far = np.abs(p[:, :2]).max(1) > 0.3
    assert not vis[far].any() and vis[np.abs(p[:, :2]).max(1) < 0.2].all()


def test_pose_vertices_rest_pose_is_identity():
    t, rig = cylinder_body()
    z = np.zeros((2, rig.pose_dim), np.float32)
    v = pose_vertices(t, rig, z, np.zeros((2, 3)), np.array([[0, 0, 0], [1.0, 0, 0]]))
    np.testing.assert_allclose(v[0], t.vertices, atol=1e-5)
    np.testing.assert_allclose(v[1] - v[0], np.broadcast_to([1.0, 0, 0], v[0].shape), atol=1e-5)


# --------------------------------------------------------------------------- cameras
def test_dome_is_evenly_split_and_sees_the_body():
    assert dome_kinds(12) == ["full"] * 4 + ["upper"] * 4 + ["lower"] * 4
    assert dome_kinds(7).count("full") == 3
    cams = make_dome(9, 64, 64, 1.7, seed=1, distortion=True, reach=0.6)
    assert sum(np.any(c.dist) for c in cams.values()) >= 1
    for name, c in cams.items():
        assert np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-9)
        y = 0.85 if name.startswith("full") else (1.3 if name.startswith("upper") else 0.4)
        p = project(np.array([[0.0, y, 0.0]]), c.K, c.R, c.T, c.dist)
        assert p.depth[0] > 0 and np.all((p.pixels[0] > 0) & (p.pixels[0] < 64)), name
    away = special_cameras(["away"], 32, 32, 1.7)["away"]
    assert project(np.array([[0.0, 1.0, 0.0]]), away.K, away.R, away.T).depth[0] < 0


# --------------------------------------------------------------------------- appearance
def coupled_model(seed: int = 0, n: int = 3000, n_train: int = 2400, dwell: float = 1.5):
    t, rig = cylinder_body()
    rng = np.random.default_rng(123)
    # A smooth, wandering "wrist" angle.
    signal = np.convolve(rng.normal(0, 1, n + 60), np.ones(60) / 60, mode="valid")[:n]
    m = AppearanceModel(
        t,
        n,
        train_frames=range(n_train),
        coupling_signal=signal,
        rig=rig,
        seed=seed,
        tex_size=64,
        fps=30.0,
        config=AppearanceConfig(fold_dwell_s=dwell),
    )
    return m, signal, n_train


def test_appearance_is_deterministic_and_in_range():
    t, rig = cylinder_body()
    a = AppearanceModel(t, 40, seed=5, tex_size=64, rig=rig)
    b = AppearanceModel(t, 40, seed=5, tex_size=64, rig=rig)
    c = AppearanceModel(t, 40, seed=6, tex_size=64, rig=rig)
    for f in (0, 17, 39):
        ta = a.texture(f)
        assert ta.shape == (64, 64, 3) and ta.dtype == np.float32
        assert ta.min() >= 0 and ta.max() <= 1
        np.testing.assert_array_equal(ta, b.texture(f))
        assert a.state(f) == b.state(f)
    assert not np.array_equal(a.texture(0), c.texture(0))
    with pytest.raises(ValueError, match="frame"):
        a.texture(40)


def test_fold_states_switch_over_time_and_change_the_texture():
    m, _, _ = coupled_model()
    switches = np.flatnonzero(np.diff(m.shirt_fold) != 0)
    mean_dwell_s = len(m.shirt_fold) / (len(switches) + 1) / 30.0
    assert 0.8 < mean_dwell_s < 3.0
    f = int(switches[0])
    shirt = m.regions["shirt"] > 0.9
    d = np.abs(m.texture(f) - m.texture(f + 1)).max(-1)
    assert d[shirt].max() > 0.05  # the crease pattern of the shirt changed
    # The hair/back-patch drift is slow: consecutive frames barely differ there.
    hair = m.regions["hair"] > 0.9
    same = np.flatnonzero((np.diff(m.shirt_fold) == 0) & (np.diff(m.trouser_fold) == 0))[0]
    assert np.abs(m.texture(same) - m.texture(same + 1)).max(-1)[hair].max() < 0.05


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_spurious_coupling_only_in_train_frames(seed):
    # Long test segment (5 min at 30 fps, ~200 fold switches) so chance correlations stay small.
    m, sig, n_train = coupled_model(seed, n=9000, n_train=3000)
    lo, hi = m.coupling_states
    tr, te = slice(0, n_train), slice(n_train, None)
    above = (sig > m.coupling_threshold).astype(float)

    def corr(a, b):
        return float(np.corrcoef(a, b)[0, 1])

    assert m.coupled[tr].all() and not m.coupled[te].any()
    # Train: the trouser folds follow the wrist (up to the hysteresis band).
    assert corr(above[tr], (m.trouser_fold[tr] == hi).astype(float)) > 0.9
    assert set(np.unique(m.trouser_fold[tr])) <= {lo, hi}
    # Test: the same rule predicts nothing, and all K states occur.
    assert abs(corr(above[te], (m.trouser_fold[te] == hi).astype(float))) < 0.2
    assert len(np.unique(m.trouser_fold[te])) == m.config.num_fold_states
    # The shirt folds never depend on pose.
    for s in range(m.config.num_fold_states):
        assert abs(corr(above[tr], (m.shirt_fold[tr] == s).astype(float))) < 0.3


def test_face_embedding_drives_only_the_face_region():
    m, _, _ = coupled_model(n=200, n_train=150)
    assert m.face_embedding.shape == (200, 4) and np.abs(m.face_embedding).max() <= 1.0 + 1e-6
    # Two frames with the same fold states: differences outside face/hair/back patch are zero.
    s = np.flatnonzero((m.shirt_fold[1:] == m.shirt_fold[0]) & (m.trouser_fold[1:] == m.trouser_fold[0]))[-1] + 1
    d = np.abs(m.texture(0) - m.texture(int(s))).max(-1).ravel()
    changing = np.zeros(d.shape, bool)
    changing[m._face_idx] = changing[m._hair_idx] = changing[m._patch_idx] = True
    assert d[~changing].max() < 1e-6
    assert d[m._face_idx].max() > 0.01


# --------------------------------------------------------------------------- tiny preset (needs Anny)
def snapshot_arrays(cap_dir: Path) -> dict[str, np.ndarray]:
    """Small statistics of a tiny capture that the snapshot pins."""
    import cv2

    from gsavatar.data_schema import load_capture
    from gsavatar.utils.io import read_image, read_mask

    cap = load_capture(cap_dir)
    names = sorted(cap.cameras)
    img0 = {c: read_image(cap.image_path(c, 0)) for c in names}
    first = names[0]
    return {
        "mean_color_frame0": np.stack([img0[c].reshape(-1, 3).mean(0) for c in names]),
        "mask_mean_frame0": np.array([read_mask(cap.mask_path(c, 0)).mean() for c in names]),
        "down8_frame0": cv2.resize(img0[first], (8, 8), interpolation=cv2.INTER_AREA),
        "texture_mean": np.stack(
            [
                read_image(cap_dir / "gt" / "textures" / f"{f:08d}.png").reshape(-1, 3).mean(0)
                for f in (0, cap.num_frames - 1)
            ]
        ),
        "pose_frame0": cap.motion.pose[0],
    }


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def test_tiny_capture_is_valid_and_complete(tiny_capture):
    import json

    from gsavatar.data_schema import check_images, load_capture

    cap = load_capture(tiny_capture)
    check_images(cap)
    assert len(cap.cameras) == 6 and cap.num_frames == 12
    assert cap.motion.face is not None and cap.motion.face.shape == (12, 4)
    assert set(cap.splits["train"].frames).isdisjoint(cap.splits["test"].frames)
    assert max(cap.splits["train"].frames) < min(cap.splits["test"].frames)  # test = held-out tail
    assert set(cap.splits["train"].cameras).isdisjoint(cap.splits["test"].cameras)
    gt = json.loads((tiny_capture / "gt" / "states.json").read_text())
    assert len(gt["frames"]) == 12
    assert gt["coupled_frames"] == cap.splits["train"].frames
    assert len(list((tiny_capture / "gt" / "textures").glob("*.png"))) == 12


def test_config_json_round_trip():
    from gsavatar.synth.presets import PRESETS, SynthConfig

    for name, cfg in PRESETS.items():
        assert SynthConfig.from_json(cfg.to_json()) == cfg, name


def test_tiny_capture_is_byte_identical_for_a_seed(tiny_capture, anny_cache_dir, tmp_path):
    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset

    again = make_capture(preset("tiny"), tmp_path / "cap", anny_cache_dir, progress=False)
    assert tree_digest(tiny_capture) == tree_digest(again)


def test_tiny_capture_matches_snapshot(tiny_capture):
    if not SNAPSHOT.exists():
        pytest.skip(f"no snapshot at {SNAPSHOT}; generate it (see module docstring)")
    got = snapshot_arrays(tiny_capture)
    with np.load(SNAPSHOT) as z:
        for k, v in got.items():
            np.testing.assert_allclose(
                v,
                z[k],
                # the 8x8 thumbnail: a few silhouette pixels move between set-ups (4e-3 on a fresh AVX-512 FP16 Xeon
                # with unpinned numpy 2.4.6 at the snapshot's own commit; cause not isolated), averages stay 1e-3
                atol=1e-2 if k == "down8_frame0" else 1e-3,
                err_msg=f"{k} differs from the snapshot; if the change is intended, regenerate (see module docstring)",
            )


if __name__ == "__main__":
    if "--regen" not in sys.argv:
        sys.exit("usage: python tests/synth/test_synth_render.py --regen   (rewrites tests/synth/snapshots/tiny.npz)")
    import tempfile

    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset
    from gsavatar.utils.io import atomic_save_npz

    with tempfile.TemporaryDirectory() as d:
        cap = make_capture(preset("tiny"), Path(d) / "cap", anny_cache(), progress=True)
        atomic_save_npz(SNAPSHOT, **snapshot_arrays(cap))
    print(f"wrote {SNAPSHOT}")
