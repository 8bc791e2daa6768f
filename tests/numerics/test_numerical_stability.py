"""Hard numerical cases through the real functions: outputs AND gradients stay finite.

Each case is isolated (one hard Gaussian, one extreme parameter, one degenerate
fit) and, where the right answer is known, the answer is asserted too. The
random-scene finiteness checks already in tests/render/test_rasterize.py
(``test_degenerate_inputs_stay_finite``), tests/train/test_losses.py (``kl_loss`` at logvar ±50
and ±1e4) and tests/prep/test_pca.py
(constant / rank-1 groups, F < P) are not repeated here.

Conventions: cameras are OpenCV (+z forward, +y down), ``viewmats`` are
cam_from_world, quaternions wxyz. Tolerances: float64 answers are asserted to
1e-9 relative, float32 ones to 1e-5 (rounding of ``exp`` and of the 2x3 footprint
factor; nothing here accumulates over many terms).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gsavatar.data_schema.dataset import ShardSpec, ShardStore, stage_dir
from gsavatar.data_schema.prepared import ProjectedTextures
from gsavatar.data_schema.pose_pca import pca_project
from gsavatar.data_schema.rig import BODY_GROUPS
from gsavatar.geometry.rotations import quat_to_matrix
from gsavatar.models import GaussianAvatar, model_preset
from gsavatar.models import gaussians as gm
from gsavatar.models.encoder import LOGVAR_RANGE, AppearanceEncoder, mask_texture, reparameterize, sample_at_uv
from gsavatar.models.predictor import AppearancePredictor, PredictorConfig, fit_latent_pca, latent_pca_project
from gsavatar.prep.pca import fit_pose_pca
from gsavatar.render import project_gaussians, rasterize
from gsavatar.train.losses import cpt_smoothness_loss, kl_loss, l1_loss, opacity_loss, scale_loss
from prep_fixtures import arm_avatar_inputs, body_rig

DTYPES = [torch.float64, torch.float32]
DTYPE_IDS = ["f64", "f32"]
RTOL = {torch.float64: 1e-9, torch.float32: 1e-5}
EPS2D = 0.3  # gsplat's low-pass dilation (px^2), the rasterizer's default

# A 16x12 pinhole camera at the world origin looking down +z; pixel (row 6, col 8)
# has its centre exactly on the optical axis (cx = 8.5, cy = 6.5).
W, H, F_PX = 16, 12, 40.0
GRAD_NAMES = ("means", "quats", "scales", "opacities", "colors", "backgrounds")


def assert_finite(name: str, *tensors: torch.Tensor | None) -> None:
    for i, t in enumerate(tensors):
        if t is not None:
            assert torch.isfinite(t).all(), f"{name}[{i}] has NaN/Inf"


def camera(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """viewmats [1, 4, 4] (identity: camera frame = world frame), Ks [1, 3, 3]."""
    K = torch.tensor([[F_PX, 0.0, W / 2 + 0.5], [0.0, F_PX, H / 2 + 0.5], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype)[None], K[None]


def gaussians(dtype: torch.dtype, *specs: dict) -> dict[str, torch.Tensor]:
    """Leaf tensors (requires_grad) for Gaussians given as dicts of mean/scale/quat/opacity/color."""

    def col(key, default):
        return torch.tensor([s.get(key, default) for s in specs], dtype=dtype)

    scene = {
        "means": col("mean", [0.0, 0.0, 2.0]),
        "quats": col("quat", [1.0, 0.0, 0.0, 0.0]),
        "scales": col("scale", [0.05, 0.05, 0.05]),
        "opacities": col("opacity", 0.8),
        "colors": col("color", [0.9, 0.2, 0.1]),
        "backgrounds": torch.tensor([[0.1, 0.3, 0.5]], dtype=dtype),
    }
    return {k: v.requires_grad_(True) for k, v in scene.items()}


def render_and_grads(scene: dict, dtype: torch.dtype, **kwargs):
    """Render, then backprop a loss touching every pixel; asserts everything is finite."""
    viewmats, Ks = camera(dtype)
    out = rasterize(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["colors"],
        viewmats,
        Ks,
        W,
        H,
        backgrounds=scene["backgrounds"],
        backend="torch",
        **kwargs,
    )
    assert_finite("render", out.colors, out.alphas)
    assert (out.alphas >= 0).all() and (out.alphas <= 1).all()
    g = torch.Generator().manual_seed(0)
    wc = torch.randn(out.colors.shape, generator=g, dtype=dtype)
    loss = (out.colors * wc).sum() + out.alphas.square().sum()
    grads = dict(zip(GRAD_NAMES, torch.autograd.grad(loss, [scene[k] for k in GRAD_NAMES], allow_unused=True)))
    for k, v in grads.items():
        assert v is None or torch.isfinite(v).all(), f"grad of {k} has NaN/Inf"
    return out, grads


# --------------------------------------------------------------------------- renderer: culling

WITNESS = {"mean": [0.02, -0.01, 2.0], "scale": [0.04, 0.03, 0.02], "quat": [0.9, 0.1, -0.2, 0.3]}
CULLED = {
    # name: the hard Gaussian; gsplat's rules give it no contribution at all
    "behind_camera": {"mean": [0.0, 0.0, -2.0], "scale": [1.0, 1.0, 1.0]},
    "exactly_on_camera_plane": {"mean": [0.1, 0.05, 0.0]},
    "at_camera_centre_huge": {"mean": [0.0, 0.0, 0.0], "scale": [1e3, 1e3, 1e3]},
    "inside_near_plane": {"mean": [0.0, 0.0, 0.005], "scale": [1e-3, 1e-3, 1e-3]},
    "beyond_far_plane": {"mean": [0.0, 0.0, 1e11], "scale": [1e3, 1e3, 1e3]},
    "far_off_axis": {"mean": [1e20, 0.0, 1e20]},
}


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("case", list(CULLED.values()), ids=list(CULLED))
def test_culled_gaussian_contributes_nothing(case, dtype):
    alone, _ = render_and_grads(gaussians(dtype, WITNESS), dtype)
    out, grads = render_and_grads(gaussians(dtype, WITNESS, case), dtype)
    assert not out.meta["valid"][0, 1]
    # Culled before compositing: the image is bit-identical to the witness alone...
    assert torch.equal(out.colors, alone.colors) and torch.equal(out.alphas, alone.alphas)
    # ...and the hard Gaussian's gradients are exactly zero (not NaN * 0).
    for k in ("means", "quats", "scales", "opacities", "colors"):
        assert (grads[k][1] == 0).all(), k
        assert grads[k][0].abs().sum() > 0, k


# --------------------------------------------------------------------------- renderer: footprints


def conic_of(dtype, spec, eps2d=EPS2D) -> tuple[torch.Tensor, bool]:
    """(conic [3] = inverse 2D covariance (a, b, c) in px^-2, valid) of one Gaussian."""
    viewmats, Ks = camera(dtype)
    s = gaussians(dtype, spec)
    proj = project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], viewmats, Ks, W, H, eps2d=eps2d)
    return proj.conics[0, 0], bool(proj.valid[0, 0])


def _on_axis(scale, z=2.0, opacity=0.8):
    """A Gaussian on the optical axis, ``z`` metres in front of the camera, identity rotation."""
    return {"mean": [0.0, 0.0, z], "scale": scale, "opacity": opacity}


# name: (Gaussian on the optical axis, expected 2D covariance diag (px^2)). On the axis
# the Jacobian is diag(f/z, f/z) with a zero depth column, so cov2d = (f s_xy / z)^2 + eps2d.
FOOTPRINTS = {
    "point_1e-8m": (_on_axis([1e-8] * 3), (EPS2D, EPS2D)),
    "needle_along_view": (_on_axis([1e-8, 1e-8, 1.0]), (EPS2D, EPS2D)),
    "needle_across_view": (_on_axis([1.0, 1e-8, 1e-8]), ((F_PX / 2.0) ** 2 + EPS2D, EPS2D)),
    "edge_on_flat": (_on_axis([0.0, 0.1, 0.1]), (EPS2D, (F_PX * 0.1 / 2.0) ** 2 + EPS2D)),
    "far_1e9m": (_on_axis([0.05] * 3, z=1e9), (EPS2D, EPS2D)),
    "huge_1e3m": (_on_axis([1e3] * 3), ((F_PX * 1e3 / 2.0) ** 2 + EPS2D,) * 2),
}


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("case", list(FOOTPRINTS.values()), ids=list(FOOTPRINTS))
def test_degenerate_footprints_have_the_analytic_conic(case, dtype):
    spec, (var_x, var_y) = case
    conic, valid = conic_of(dtype, spec)
    assert valid
    want = torch.tensor([1.0 / var_x, 0.0, 1.0 / var_y], dtype=torch.float64)
    torch.testing.assert_close(conic.double(), want, rtol=RTOL[dtype], atol=1e-12)
    render_and_grads(gaussians(dtype, spec), dtype)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_subpixel_gaussian_is_a_fixed_dot_on_the_background(dtype):
    # gsplat's classic mode has no antialiasing compensation: the 0.3 px^2 dilation
    # turns any sub-pixel Gaussian into the same dot, whatever its true size, and
    # every pixel outside the dot's 3x3 neighbourhood is exactly the background.
    outs = [render_and_grads(gaussians(dtype, _on_axis([s] * 3, opacity=0.5)), dtype)[0] for s in (1e-8, 1e-6)]
    torch.testing.assert_close(outs[0].colors, outs[1].colors, rtol=0, atol=RTOL[dtype])
    out = outs[0]
    alpha = out.alphas[0, :, :, 0]
    assert alpha[6, 8].item() == pytest.approx(0.5, rel=RTOL[dtype])
    assert alpha[6, 9].item() == pytest.approx(0.5 * math.exp(-0.5 / EPS2D), rel=RTOL[dtype])
    dot = torch.zeros(H, W, dtype=torch.bool)
    dot[5:8, 7:10] = True
    bg = out.colors.new_tensor([0.1, 0.3, 0.5])
    assert (alpha[~dot] == 0).all()
    assert torch.equal(out.colors[0][~dot], bg.expand(int((~dot).sum()), 3))


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("scale", [1e3, 1e10, 1e19], ids=["1e3m", "1e10m", "1e19m"])
def test_huge_gaussian_covers_the_image_uniformly(scale, dtype):
    # The conic is ~0: every pixel gets alpha = opacity. (float32 used to overflow the
    # 2D determinant from ~1e10 m on, culling the Gaussian with NaN gradients.) The
    # tolerance is the true falloff of the 1e3 m one at the image corner, ~1e-7.
    out, _ = render_and_grads(gaussians(dtype, _on_axis([scale] * 3, opacity=0.6)), dtype)
    torch.testing.assert_close(out.alphas, torch.full_like(out.alphas, 0.6), rtol=0, atol=1e-6)
    want = 0.6 * torch.tensor([0.9, 0.2, 0.1], dtype=dtype) + 0.4 * torch.tensor([0.1, 0.3, 0.5], dtype=dtype)
    torch.testing.assert_close(out.colors, want.expand_as(out.colors), rtol=0, atol=1e-6)


# name: (scales on the optical axis, cov2d diagonal without dilation (px^2), dtypes that cull it)
SINGULAR = {
    "point_1e-8m": ([1e-8] * 3, (4e-14, 4e-14), (torch.float32,)),
    "needle": ([1.0, 1e-8, 1e-8], (400.0, 4e-14), (torch.float32,)),
    "edge_on_flat": ([0.0, 0.1, 0.1], None, DTYPES),  # det exactly 0: culled, as gsplat's det <= 0
    "point_1mm": ([1e-3] * 3, (4e-4, 4e-4), ()),
}


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("case", list(SINGULAR.values()), ids=list(SINGULAR))
def test_singular_2d_covariance_without_dilation(case, dtype):
    # eps2d = 0 leaves needle/flat/point footprints (nearly) singular. gsplat's CUDA
    # kernel inverts det as is; the former 1e-10 floor made a 1e-8 m point a 50 px
    # blob. Where 1/det or its gradient would overflow (float32: widths below ~1e-4 px)
    # the Gaussian is culled instead.
    scale, var, culled_in = case
    spec = _on_axis(scale)
    conic, valid = conic_of(dtype, spec, eps2d=0.0)
    assert valid == (dtype not in culled_in)
    if valid:
        want = torch.tensor([1.0 / var[0], 0.0, 1.0 / var[1]], dtype=torch.float64)
        torch.testing.assert_close(conic.double(), want, rtol=RTOL[dtype], atol=1e-12)
    render_and_grads(gaussians(dtype, spec), dtype, eps2d=0.0)


# --------------------------------------------------------------------------- quaternions

UNIT = [0.5, 0.5, -0.5, 0.5]
QUAT_MAGNITUDES = {"zero": 0.0, "1e-30": 1e-30, "1e-8": 1e-8, "1e20": 1e20, "1e30": 1e30, "max/8": None}


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("mag", list(QUAT_MAGNITUDES.values()), ids=list(QUAT_MAGNITUDES))
def test_quaternion_magnitudes_in_the_renderer(mag, dtype):
    mag = torch.finfo(dtype).max / 8 if mag is None else mag
    q = (torch.tensor(UNIT, dtype=torch.float64) * mag).to(dtype).requires_grad_(True)
    rot = quat_to_matrix(q)  # what the renderer's covariance uses
    (g,) = torch.autograd.grad((rot * torch.arange(9.0, dtype=dtype).reshape(3, 3)).sum(), q)
    assert_finite("R", rot, g)
    if mag >= 1e-8:  # R is scale invariant (gsplat normalises q too): the unit quaternion's rotation
        torch.testing.assert_close(rot, quat_to_matrix(torch.tensor(UNIT, dtype=dtype)), rtol=0, atol=RTOL[dtype])
    else:  # |q| <= 1e-12: treated as "no rotation"
        torch.testing.assert_close(rot, torch.eye(3, dtype=dtype), rtol=0, atol=1e-3)
    if mag == 0.0:
        assert torch.equal(rot, torch.eye(3, dtype=dtype)) and (g == 0).all()

    spec = {"mean": [0.0, 0.0, 2.0], "scale": [0.08, 0.01, 0.03], "quat": [v * mag for v in UNIT]}
    out, _ = render_and_grads(gaussians(dtype, spec), dtype)
    if mag >= 1e20:
        ref, _ = render_and_grads(gaussians(dtype, dict(spec, quat=UNIT)), dtype)
        torch.testing.assert_close(out.colors, ref.colors, rtol=0, atol=RTOL[dtype])


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("mag", list(QUAT_MAGNITUDES.values()), ids=list(QUAT_MAGNITUDES))
def test_quaternion_activation(mag, dtype):
    mag = torch.finfo(dtype).max / 8 if mag is None else mag
    x = (torch.tensor([UNIT, [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64) * mag).to(dtype).requires_grad_(True)
    q = gm.activate_quat(x)
    rot = gm.quat_to_matrix(q)
    (g,) = torch.autograd.grad((rot * torch.arange(9.0, dtype=dtype).reshape(3, 3)).sum(), x)
    assert_finite("activate_quat", q, rot, g)
    if mag == 0.0:
        assert (q == 0).all() and torch.equal(rot, torch.eye(3, dtype=dtype).expand(2, 3, 3))
    elif mag >= 1e-8:  # normalised to the unit quaternion (float32 >= 1e20 used to give 0)
        want = torch.tensor([UNIT, [1.0, 0.0, 0.0, 0.0]], dtype=dtype)
        torch.testing.assert_close(q, want, rtol=0, atol=RTOL[dtype])
        # quat_to_matrix takes any norm too: the raw huge x gives the same rotation.
        torch.testing.assert_close(gm.quat_to_matrix(x.detach()), rot.detach(), rtol=0, atol=RTOL[dtype])


# --------------------------------------------------------------------------- scales


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("log_scale", [-1e4, -100.0, math.log(1e-8), math.log(1e3), 100.0, 1e4])
def test_scale_activation_extremes(log_scale, dtype):
    scale_max = 0.05
    x = torch.tensor([log_scale, math.log(scale_max) - 1.0], dtype=dtype, requires_grad=True)
    s = gm.activate_scale(x, scale_max)
    (g,) = torch.autograd.grad(s.sum(), x)
    assert_finite("activate_scale", s, g)  # exp overflowed to inf -> 0 * inf = NaN before
    assert (s >= 0).all() and (s <= scale_max).all()
    if log_scale >= math.log(scale_max):
        assert s[0].item() == pytest.approx(scale_max, rel=1e-6) and g[0] == 0
    else:
        tiny = torch.finfo(dtype).tiny  # exp(-100) is subnormal in float32
        assert s[0].item() == pytest.approx(math.exp(log_scale), rel=RTOL[dtype], abs=tiny)
        assert g[0].item() == pytest.approx(math.exp(log_scale), rel=RTOL[dtype], abs=tiny)


# --------------------------------------------------------------------------- avatar end to end


@pytest.fixture(scope="module")
def arm_avatar_parts():
    # a constant group (torso): zero local PCA components there
    return arm_avatar_inputs(
        n_anchors=12, n_control=60, n_gaussians=300, min_candidates=1000, n_poses=40, constant_torso=True
    )


AVATAR_CASES = {
    # name: parameter overrides (applied in no_grad) and extreme latents
    "tiny_scales": ({"scale_bias": math.log(1e-8)}, 0.0),
    "huge_scale_logits": ({"scale_bias": 1e4}, 0.0),  # clamped to scale_max; was NaN grad
    "zero_quaternions": ({"rotation_bias": 0.0, "rotation_basis": 0.0}, 0.0),  # exactly 0 -> identity
    "huge_quaternions": ({"rotation_bias": 1e30}, 0.0),
    "huge_latents": ({}, 1e6),
}


@pytest.mark.parametrize("case", list(AVATAR_CASES.values()), ids=list(AVATAR_CASES))
def test_avatar_render_loss_backward_is_finite(arm_avatar_parts, case):
    overrides, latent_value = case
    rig, h, masks, pl, pg = arm_avatar_parts
    av = GaussianAvatar(h, masks, rig, pl, pg, model_preset("tiny")).train()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, p in av.named_parameters():  # non-zero correctives: the MLP path matters
            if not name.startswith("pose_head.mlp") and not name.endswith("_bias"):
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)
        for name, v in overrides.items():
            getattr(av, name).fill_(v)
    B, A = 2, h.num_anchors
    pose = torch.randn(B, rig.pose_dim, generator=g) * 0.5
    latents = torch.full((B, A, av.config.latent_dim), latent_value)
    out = av(pose, torch.zeros(B, 3), torch.zeros(B, 3), latents=latents)
    assert_finite("avatar", *out)

    # The arm runs along +x from -0.2 to 1.0 m; look at it from 2 m.
    vm = torch.eye(4)
    vm[:3, 3] = torch.tensor([-0.4, 0.0, 2.0])
    K = torch.tensor([[24.0, 0.0, 16.0], [0.0, 24.0, 6.0], [0.0, 0.0, 1.0]])
    images, alphas = [], []
    for b in range(B):
        r = rasterize(
            out.means[b],
            out.quats[b],
            out.scales[b],
            out.opacities[b],
            out.sh[b],
            vm[None],
            K[None],
            32,
            12,
            backgrounds=torch.ones(1, 3),
            sh_degree=av.config.sh_degree,
            backend="torch",
        )
        images.append(r.colors[0].permute(2, 0, 1))
        alphas.append(r.alphas[0].permute(2, 0, 1))
    pred, alpha = torch.stack(images), torch.stack(alphas)
    loss = (
        l1_loss(pred, torch.full_like(pred, 0.3))
        + opacity_loss(alpha, torch.ones_like(alpha))
        + scale_loss(out.scales, 0.025)
        + cpt_smoothness_loss(out.ctrl_disp, av.ctrl_neighbors)
    )
    loss.backward()
    assert torch.isfinite(loss)
    for name, p in av.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    if overrides.get("scale_bias", 0.0) > 0:
        torch.testing.assert_close(out.scales, torch.full_like(out.scales, av.config.scale_max), rtol=1e-6, atol=0)


# --------------------------------------------------------------------------- fp16 textures and the encoder

FP16 = torch.finfo(torch.float16)
TEXTURES = {
    # name: fill of an fp16 [S, S, 3] texture as stored by avatar-prep's project-uv stage
    "fp16_max": FP16.max,
    "smallest_subnormal": 2.0**-24,
    "smallest_normal": FP16.smallest_normal,
    "zero": 0.0,
    "mixed": None,  # max / subnormal / 0 / 1 checkerboard
}


def _fp16_texture(fill, S=64) -> np.ndarray:
    if fill is not None:
        return np.full((S, S, 3), fill, dtype=np.float16)
    vals = np.array([FP16.max, 2.0**-24, 0.0, 1.0], dtype=np.float16)
    ii, jj = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
    return np.repeat(vals[(ii + 2 * jj) % 4][..., None], 3, axis=2)


@pytest.mark.parametrize("fill", list(TEXTURES.values()), ids=list(TEXTURES))
def test_fp16_textures_through_loader_encoder_and_losses(tmp_path, fill):
    # Store two frames as an fp16 project-uv shard and read them back the way the
    # training data set does (ProjectedTextures: fp16 -> float32, exact; ViewDataset's fp16 cache is exact too).
    tex16 = np.stack([_fp16_texture(fill), _fp16_texture(None)])
    store = ShardStore(stage_dir(tmp_path, "project-uv"), "project-uv")
    spec = ShardSpec(0, [0, 1])
    store.write(spec, {"texture": tex16}, "test")
    store.merge_manifest([spec])
    reader = ProjectedTextures(tmp_path)
    tex = [reader.get(f) for f in (0, 1)]
    assert all(t.dtype == np.float32 for t in tex)
    np.testing.assert_array_equal(tex[0], tex16[0].astype(np.float32))  # max and subnormals survive

    torch.manual_seed(0)
    enc = AppearanceEncoder(latent_dim=4).train()
    x = torch.from_numpy(np.stack(tex)).permute(0, 3, 1, 2).contiguous()  # [2, 3, S, S]
    x = mask_texture(x, torch.zeros(8, 8, dtype=torch.bool).index_fill_(0, torch.tensor([0]), True))
    grid = [n // enc.downsample for n in x.shape[-2:]]
    eps = torch.randn(x.shape[0], 4, *grid, generator=torch.Generator().manual_seed(0))
    o = enc(x, eps)
    assert_finite("encoder", o.latent_map, o.mu, o.logvar)
    z = sample_at_uv(o.latent_map, torch.rand(7, 2, generator=torch.Generator().manual_seed(1)))
    loss = kl_loss(o.mu, o.logvar) + l1_loss(x, torch.zeros_like(x)) + z.square().mean()
    loss.backward()
    assert torch.isfinite(loss)
    for name, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_losses_reduce_fp16_inputs_in_float32():
    # Reductions over >65504 in float16 overflowed: opacity_loss's mask sum turned
    # the loss into 0 and kl_loss into inf. Inputs at the fp16 max / subnormals.
    B, S = 2, 256
    alpha = torch.full((B, 1, S, S), 0.5, dtype=torch.float16, requires_grad=True)
    opac = opacity_loss(alpha, torch.ones(B, 1, S, S, dtype=torch.float16))
    mu = torch.full((B, 16, 32, 32), 3.0, dtype=torch.float16, requires_grad=True)
    logvar = torch.zeros(B, 16, 32, 32, dtype=torch.float16, requires_grad=True)
    kl = kl_loss(mu, logvar)
    big = torch.full((B, 3, 8, 8), FP16.max, dtype=torch.float16, requires_grad=True)
    tiny = torch.full((B, 3, 8, 8), 2.0**-24, dtype=torch.float16)
    l1 = l1_loss(big, tiny)
    sc = scale_loss(torch.full((B, 10, 3), FP16.max, dtype=torch.float16, requires_grad=True), 0.01)
    disp = torch.full((B, 6, 3), 2.0**-24, dtype=torch.float16, requires_grad=True)
    cpt = cpt_smoothness_loss(disp, torch.randint(0, 6, (6, 5), generator=torch.Generator().manual_seed(0)))
    for v in (opac, kl, l1, sc, cpt):
        assert v.dtype == torch.float32 and torch.isfinite(v)
    assert opac.item() == pytest.approx(0.5)
    assert kl.item() == pytest.approx(0.5 * 9.0 * 16 * 32 * 32)
    assert l1.item() == pytest.approx(FP16.max, rel=1e-6)
    (opac + 1e-6 * kl + l1 + sc + cpt).backward()
    assert_finite("fp16 grads", alpha.grad, mu.grad, logvar.grad, big.grad, disp.grad)


# --------------------------------------------------------------------------- extreme log-variances


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("lv", [1e4, -1e4, 1e10])
def test_kl_loss_at_huge_logvar(lv, dtype):
    mu = torch.zeros(2, 4, 3, 3, dtype=dtype, requires_grad=True)
    logvar = torch.full((2, 4, 3, 3), lv, dtype=dtype, requires_grad=True)
    v = kl_loss(mu, logvar)
    g_mu, g_lv = torch.autograd.grad(v, [mu, logvar])
    assert_finite("kl", v, g_mu, g_lv)
    n = 4 * 3 * 3
    if lv < 0:  # exact: 0.5 * n * (e^lv - 1 - lv), e^lv = 0
        assert v.item() == pytest.approx(0.5 * n * (-1.0 - lv), rel=RTOL[dtype])
        assert (g_lv == -0.5 / 2).all()  # d/dlv 0.5 (e^lv - 1 - lv) / B
    else:  # exp continued linearly above 50: a positive, finite push back down
        assert v.item() > 0.5 * n * (math.exp(50.0) - 51.0)
        assert (g_lv > 0).all()


def test_kl_loss_exact_up_to_50_and_continuous_beyond():
    assert kl_loss(torch.zeros(3, 5), torch.zeros(3, 5)).item() == 0.0
    lv = torch.tensor([[50.0 - 1e-9, 50.0, 50.0 + 1e-9, 20.0]], dtype=torch.float64, requires_grad=True)
    kl = 0.5 * (torch.exp(lv.detach()) - 1.0 - lv.detach())  # per element, mu = 0
    v = kl_loss(torch.zeros_like(lv), lv)
    (g,) = torch.autograd.grad(v, lv)
    torch.testing.assert_close(v, kl.sum(), rtol=1e-12, atol=0)
    torch.testing.assert_close(g, 0.5 * (torch.exp(lv.detach()) - 1.0), rtol=1e-8, atol=0)


@pytest.mark.parametrize("lv", [50.0, -50.0, 1e4, -1e4])
def test_reparameterize_at_extreme_logvar(lv):
    mu = torch.randn(2, 4, 3, 3, requires_grad=True)
    logvar = torch.full((2, 4, 3, 3), lv, requires_grad=True)
    eps = torch.randn(mu.shape, generator=torch.Generator().manual_seed(0))
    z = reparameterize(mu, logvar, eps)
    g_mu, g_lv = torch.autograd.grad((z * torch.randn_like(z)).sum(), [mu, logvar])
    assert_finite("reparameterize", z, g_mu, g_lv)
    std = math.exp(0.5 * min(lv, LOGVAR_RANGE[1]))
    torch.testing.assert_close(z, mu.detach() + std * eps, rtol=1e-6, atol=1e-6 * std)


@pytest.mark.parametrize("bias", [1e4, -1e4, 50.0, -50.0])
def test_encoder_with_extreme_logvar_head(bias):
    torch.manual_seed(0)
    enc = AppearanceEncoder(latent_dim=4).train()
    with torch.no_grad():
        enc.logvar_head.bias.fill_(bias)
    o = enc(torch.rand(2, 3, 64, 64), torch.randn(2, 4, 2, 2, generator=torch.Generator().manual_seed(0)))
    assert_finite("encoder", o.latent_map, o.mu, o.logvar)
    assert (o.logvar >= LOGVAR_RANGE[0]).all() and (o.logvar <= LOGVAR_RANGE[1]).all()
    loss = kl_loss(o.mu, o.logvar) + o.latent_map.square().mean()
    loss.backward()
    assert torch.isfinite(loss)
    for name, p in enc.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


# --------------------------------------------------------------------------- rank-deficient pose PCA


def _group_slots(rig, name):
    return np.flatnonzero(rig.slot_groups() == BODY_GROUPS.index(name))


def _train_poses(rig, F, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(F, rig.pose_dim)) @ (rng.normal(size=(rig.pose_dim, rig.pose_dim)) * 0.1)


RANK_CASES = ["duplicated_columns", "near_constant_joint", "two_frames", "single_frame", "all_constant", "huge_offsets"]


@pytest.mark.parametrize("mode", ["local", "global"])
@pytest.mark.parametrize("case", RANK_CASES)
def test_rank_deficient_pose_pca_is_finite_and_differentiable(case, mode):
    rig = body_rig()
    lh, rh, la = (_group_slots(rig, g) for g in ("left_hand", "right_hand", "left_arm"))
    tr = _train_poses(rig, 30)
    if case == "duplicated_columns":
        tr[:, lh[1:]] = tr[:, lh[:1]]  # every left-hand slot is one and the same column
        tr[:, rh[1::2]] = tr[:, rh[0::2][: len(rh[1::2])]]  # pairs of equal columns
    elif case == "near_constant_joint":
        tr[:, la] = 0.2 + 1e-15 * np.random.default_rng(1).normal(size=(len(tr), len(la)))
    elif case == "two_frames":
        tr = tr[:2]
    elif case == "single_frame":
        tr = tr[:1]
    elif case == "all_constant":
        tr[:] = tr[:1]
    elif case == "huge_offsets":
        tr = tr + 1e6  # a large common offset (radians) must not cost precision or finiteness
    pca = fit_pose_pca(tr, rig, n_components=5, mode=mode)
    assert np.all(np.isfinite(pca.basis)) and np.all(np.isfinite(pca.sigma)) and np.all(pca.sigma > 0)
    np.testing.assert_allclose(pca.basis.T @ pca.basis, np.eye(pca.num_components), atol=1e-9)
    cpg = pca.components_per_group()
    if case == "duplicated_columns" and mode == "local":
        assert cpg["left_hand"] == 1
    if case == "near_constant_joint" and mode == "local":
        assert cpg["left_arm"] == 0  # 1e-15 noise is numerically constant: dropped, never sigma ~ 0
    if case in ("single_frame", "all_constant"):
        assert pca.num_components == 0
    if case == "two_frames":
        assert max(cpg.values()) == 1

    x = np.concatenate([tr[:3], tr[:1] + 50.0 * np.random.default_rng(2).normal(size=(2, rig.pose_dim))])
    y = pca.project(x)
    assert np.all(np.isfinite(y))
    coeffs = pca.transform(y)
    assert np.all(np.abs(coeffs) <= pca.clamp_sigma * pca.sigma * (1 + 1e-9) + 1e-9)
    if case == "duplicated_columns":  # the projection stays in the span of the data: equal columns stay equal
        np.testing.assert_allclose(y[:, lh], np.repeat(y[:, lh[:1]], len(lh), 1), atol=1e-9)
    if case in ("single_frame", "all_constant"):
        np.testing.assert_allclose(y, np.repeat(tr[:1], len(x), 0), rtol=1e-12)

    # The avatar's conditioning path (float32 buffers), with gradients.
    pose = torch.tensor(x, dtype=torch.float32, requires_grad=True)
    f32 = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    out = pca_project(pose, f32(pca.mean), f32(pca.basis), f32(pca.clamp_sigma * pca.sigma))
    (g,) = torch.autograd.grad((out * torch.linspace(-1, 1, out.shape[1])).sum(), pose)
    assert_finite("pca_project", out, g)
    if pca.num_components == 0:
        assert (g == 0).all()


# --------------------------------------------------------------------------- latent PCA clamp

A_, L_ = 4, 6


def _latents(case: str, F: int = 20) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    lat = torch.randn(F, A_, L_, generator=g)
    if case == "constant_dims":
        lat[:, :, 3:] = 0.7  # zero-variance dims in every anchor
    elif case == "constant_anchor":
        lat[:, 1] = torch.linspace(-1, 1, L_)  # anchor 1 never changes
    elif case == "duplicated_dims":
        lat[:, :, 1:] = lat[:, :, :1]  # rank 1 per anchor
    elif case == "single_frame":
        lat = lat[:1]
    elif case == "all_constant":
        lat[:] = 2.5
    return lat


LATENT_CASES = ["constant_dims", "constant_anchor", "duplicated_dims", "single_frame", "all_constant"]


@pytest.mark.parametrize("case", LATENT_CASES)
def test_latent_pca_clamp_with_zero_variance_components(case):
    lat = _latents(case)
    pca = fit_latent_pca(lat, components=4)
    assert_finite("latent pca", pca.mean, pca.basis, pca.sigma)
    zero = pca.sigma == 0  # [A, K] missing components: zero column, zero limit
    assert (pca.basis.transpose(1, 2)[zero] == 0).all()
    if case in ("single_frame", "all_constant"):
        assert zero.all()
    if case == "constant_anchor":
        assert zero[1].all()
    if case == "duplicated_dims":
        assert (zero.sum(1) == 3).all()
    limit = 2.0 * pca.sigma
    x = (torch.randn(5, A_, L_, generator=torch.Generator().manual_seed(1)) * 1e3).requires_grad_(True)
    y = latent_pca_project(x, pca.mean, pca.basis, limit)
    (g,) = torch.autograd.grad((y * torch.randn_like(y)).sum(), x)
    assert_finite("latent_pca_project", y, g)
    c = torch.einsum("nal,alk->nak", y - pca.mean, pca.basis)
    assert (c.abs() <= limit + 1e-3).all()
    if zero.all():  # nothing to move along: every latent collapses onto the training mean
        torch.testing.assert_close(y, pca.mean.expand_as(y), rtol=0, atol=1e-6)
        assert (g == 0).all()


@pytest.mark.parametrize("case", ["all_constant", "constant_anchor"])
def test_predictor_fit_on_constant_latents_stays_finite(case):
    lat = _latents(case)
    cfg = PredictorConfig(
        history=4, width=16, heads=2, ff=32, latent_dim=L_, token_hidden=8, latent_pca_components=4, initial_hidden=8
    )
    m = AppearancePredictor(cfg, A_, [0, 2, 3], 5, seed=0)
    m.fit_latent_statistics(lat)  # std 0 -> scale floored (1e-8 when everything is constant)
    assert_finite("latent_scale", m.latent_scale)
    assert (m.latent_scale > 0).all()
    g = torch.Generator().manual_seed(2)
    prev = lat[:2] + 10.0 * torch.randn(2, A_, L_, generator=g)  # far from the (constant) training latents
    out = m(
        torch.randn(2, 4, 5, generator=g),
        torch.randn(2, 4, 3, generator=g) * 0.1,
        torch.randn(2, 4, 3, generator=g) * 0.1,
        prev,
    )
    out.square().sum().backward()
    assert_finite("predictor", out)
    for name, p in m.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    if case == "all_constant":  # a zero-size clamp box: exactly the training mean
        torch.testing.assert_close(out, lat[:2], rtol=0, atol=1e-5)
    else:
        torch.testing.assert_close(out[:, 1], lat[:2, 1], rtol=0, atol=1e-5)
