"""Tests of the CPU renderer against a naive dense reference and gsplat's rules.

The reference below is deliberately simple: it projects with textbook formulas
(normalised quaternion, Sigma = R S S R^T, J W Sigma W^T J^T + 0.3 I, matrix
inverse), then evaluates every pixel against every Gaussian, sorted by depth,
with gsplat's compositing rules (1/255 skip, 0.999 clamp, stop once
T * (1 - alpha) <= 1e-4, stopping Gaussian excluded), all with plain autograd.
"""

from __future__ import annotations

import math

import pytest
import torch

from gsavatar.render import eval_sh_colors, project_gaussians, rasterize

# Per-dtype tolerances for tiled-vs-dense comparisons. float32 runs are compared
# with a float64 reference on the same (float32-representable) inputs, so they
# absorb float32 rounding in projection, exp and the transmittance product
# (observed <= 1e-6); gradients are compared relative to the largest entry of each
# gradient because means/scales grads span orders of magnitude (observed <= 1e-5:
# float32 suffix sums over ~100 layers, as in gsplat's own backward). A flip of the
# 1/255 threshold would cost ~4e-3 and is deliberately NOT tolerated: the fixed
# seeds have none, a failure here means the rules diverged.
TOLERANCES = {
    torch.float64: {"fwd_atol": 1e-12, "grad_rel": 1e-10},
    torch.float32: {"fwd_atol": 1e-5, "grad_rel": 5e-5},
}
GRAD_NAMES = ("means", "quats", "scales", "opacities", "colors", "backgrounds")


# --------------------------------------------------------------------------- reference


def reference_project(means, quats, scales, viewmats, Ks, width, height, eps2d=0.3):
    """Textbook EWA projection. Returns means2d [C,N,2], conics [C,N,3], depths [C,N].

    Like gsplat, the Jacobian is evaluated at the view direction clamped to 1.3x
    the field of view (Gaussians far off-screen would otherwise smear across it).
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)
    cov3 = rot @ torch.diag_embed(scales**2) @ rot.transpose(-1, -2)
    r_cw, t_cw = viewmats[:, :3, :3], viewmats[:, :3, 3]
    p_cam = torch.einsum("cij,nj->cni", r_cw, means) + t_cw[:, None]
    cov_cam = r_cw[:, None] @ cov3[None] @ r_cw[:, None].transpose(-1, -2)
    px, py, pz = p_cam.unbind(-1)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    tx = pz * torch.clamp(px / pz, min=-(cx / fx + 0.3 * tan_x), max=(width - cx) / fx + 0.3 * tan_x)
    ty = pz * torch.clamp(py / pz, min=-(cy / fy + 0.3 * tan_y), max=(height - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(pz)
    jac = torch.stack([fx / pz, zero, -fx * tx / pz**2, zero, fy / pz, -fy * ty / pz**2], -1)
    jac = jac.reshape(pz.shape + (2, 3))
    cov2 = jac @ cov_cam @ jac.transpose(-1, -2) + eps2d * torch.eye(2, dtype=means.dtype)
    inv = torch.linalg.inv(cov2)
    conics = torch.stack([inv[..., 0, 0], inv[..., 0, 1], inv[..., 1, 1]], -1)
    means2d = torch.stack([fx * px / pz + cx, fy * py / pz + cy], -1)
    return means2d, conics, pz


def reference_composite(means2d, conics, depths, opacities, feats, width, height, near=0.01):
    """Dense compositing: every pixel x every Gaussian. Returns [C,H,W,D], [C,H,W,1], stop count."""
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype), torch.arange(width, dtype=means2d.dtype), indexing="ij"
    )
    centres = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1) + 0.5  # [P, 2]
    images, alphas, n_stopped = [], [], 0
    for c in range(means2d.shape[0]):
        ok = depths[c] >= near
        key = torch.where(ok, depths[c], torch.full_like(depths[c], float("inf")))
        order = torch.argsort(key.detach(), stable=True)
        delta = means2d[c, order][None] - centres[:, None]  # [P, N, 2]
        con = conics[c, order]
        sigma = (
            0.5 * (con[:, 0] * delta[..., 0] ** 2 + con[:, 2] * delta[..., 1] ** 2)
            + con[:, 1] * delta[..., 0] * delta[..., 1]
        )
        alpha = (opacities[order] * torch.exp(-sigma)).clamp(max=0.999)
        use = (sigma >= 0) & (alpha >= 1.0 / 255.0) & ok[order][None]
        alpha = torch.where(use, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            stopped = torch.cumprod(1 - alpha, dim=1) <= 1e-4
        n_stopped += int(stopped.any(dim=1).sum())
        alpha = torch.where(stopped, torch.zeros_like(alpha), alpha)
        trans_incl = torch.cumprod(1 - alpha, dim=1)
        trans = torch.cat([torch.ones_like(trans_incl[:, :1]), trans_incl[:, :-1]], dim=1)
        feat = feats[c, order] if feats.dim() == 3 else feats[order]
        images.append(((alpha * trans) @ feat).reshape(height, width, -1))
        alphas.append((1 - trans_incl[:, -1:]).reshape(height, width, 1))
    return torch.stack(images), torch.stack(alphas), n_stopped


def reference_render(scene, width, height, sh_degree=None):
    means2d, conics, depths = reference_project(
        scene["means"], scene["quats"], scene["scales"], scene["viewmats"], scene["Ks"], width, height
    )
    feats = scene["colors"]
    if sh_degree is not None:
        cam_pos = -(scene["viewmats"][:, :3, :3].transpose(-1, -2) @ scene["viewmats"][:, :3, 3:])[..., 0]
        dirs = scene["means"][None] - cam_pos[:, None]
        feats = eval_sh_colors(sh_degree, dirs, feats[None].expand(dirs.shape[0], -1, -1, -1))
    img, alpha, n_stopped = reference_composite(means2d, conics, depths, scene["opacities"], feats, width, height)
    if scene.get("backgrounds") is not None:
        img = img + (1 - alpha) * scene["backgrounds"][:, None, None]
    return img, alpha, n_stopped


# --------------------------------------------------------------------------- scenes


def look_at_viewmat(eye, target, dtype):
    """cam_from_world for an OpenCV camera at ``eye`` looking at ``target`` (y down)."""
    eye, target = torch.tensor(eye, dtype=dtype), torch.tensor(target, dtype=dtype)
    fwd = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(fwd, torch.tensor([0.0, -1.0, 0.0], dtype=dtype)), dim=0)
    down = torch.linalg.cross(fwd, right)
    rot_cw = torch.stack([right, down, fwd])
    vm = torch.eye(4, dtype=dtype)
    vm[:3, :3] = rot_cw
    vm[:3, 3] = -rot_cw @ eye
    return vm


def random_scene(n, width, height, dtype, seed, opaque=False, n_cams=2):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.8, 0.8, 0.8])
    scales = torch.exp(torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6 - 3.3)
    if opaque:
        # Stacked, nearly opaque splats: exercises the 0.999 clamp and the T stop.
        opac = 0.85 + 0.15 * torch.rand(n, generator=g, dtype=torch.float64)
        opac[: n // 8] = 1.0
        scales = scales * 2.0
    else:
        opac = 0.02 + 0.96 * torch.rand(n, generator=g, dtype=torch.float64)
    f = 1.3 * width
    Ks = torch.tensor([[f, 0.0, width / 2 + 0.3], [0.0, f * 1.05, height / 2 - 0.2], [0.0, 0.0, 1.0]])
    vms = [
        look_at_viewmat([1.8 * math.sin(0.5 * c), 0.2 * c, -1.8 * math.cos(0.5 * c)], [0, 0, 0], torch.float64)
        for c in range(n_cams)
    ]
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": scales,
        "opacities": opac,
        "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
        "viewmats": torch.stack(vms),
        "Ks": Ks.expand(n_cams, 3, 3).to(torch.float64),
        "backgrounds": torch.rand(n_cams, 3, generator=g, dtype=torch.float64),
    }
    # Round through float32 so both dtypes see identical inputs.
    return {k: v.float().to(dtype) for k, v in scene.items()}


def with_grad(scene):
    return {k: (v.clone().requires_grad_(k in GRAD_NAMES)) for k, v in scene.items()}


def render(scene, width, height, **kwargs):
    kwargs.setdefault("backend", "torch")
    return rasterize(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        scene["colors"],
        scene["viewmats"],
        scene["Ks"],
        width,
        height,
        backgrounds=scene.get("backgrounds"),
        **kwargs,
    )


def loss_weights(shape_c, shape_a, dtype, seed=7):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(shape_c, generator=g, dtype=dtype), torch.randn(shape_a, generator=g, dtype=dtype)


def grads_of(scene, img, alpha, wc, wa):
    params = [scene[k] for k in GRAD_NAMES]
    return torch.autograd.grad((img * wc).sum() + (alpha * wa).sum(), params, allow_unused=True)


# --------------------------------------------------------------------------- equivalence


CASES = {
    # name: (n, width, height, seed, opaque, n_features, rasterize kwargs)
    "translucent": (120, 37, 29, 0, False, 3, {}),
    "opaque": (200, 33, 30, 1, True, 3, {}),
    "chunked": (150, 40, 24, 2, True, 3, {"tile_size": 8, "max_candidates": 512}),  # many tiny batches
    "strip_5ch": (90, 23, 3, 3, False, 5, {}),  # partial tiles, clamped Jacobian, D != 3
}


COMPOSITORS = ["numba", "dense"]  # the compiled per-pixel loops and the batched torch ops


@pytest.mark.parametrize("compositor", COMPOSITORS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("case", list(CASES.values()), ids=list(CASES))
def test_matches_dense_reference(dtype, case, compositor):
    n, width, height, seed, opaque, n_feat, kwargs = case
    kwargs = dict(kwargs, compositor=compositor)
    if compositor == "numba":
        kwargs.pop("max_candidates", None)
    tol = TOLERANCES[dtype]
    scene = random_scene(n, width, height, dtype, seed, opaque)
    g = torch.Generator().manual_seed(seed + 100)
    scene["colors"] = torch.rand(n, n_feat, generator=g).to(dtype)
    scene["backgrounds"] = torch.rand(2, n_feat, generator=g).to(dtype)
    scene = with_grad(scene)
    ref_scene = with_grad({k: v.detach().double() for k, v in scene.items()})

    out = render(scene, width, height, **kwargs)
    ref_img, ref_alpha, n_stopped = reference_render(ref_scene, width, height)
    if opaque:
        assert n_stopped > 20, "scene should exercise the T <= 1e-4 early stop"
    assert out.colors.dtype == dtype and out.colors.shape == (2, height, width, n_feat)
    assert (out.colors.double() - ref_img).abs().max() < tol["fwd_atol"]
    assert (out.alphas.double() - ref_alpha).abs().max() < tol["fwd_atol"]

    wc, wa = loss_weights(out.colors.shape, out.alphas.shape, torch.float64)
    got = grads_of(scene, out.colors, out.alphas, wc.to(dtype), wa.to(dtype))
    want = grads_of(ref_scene, ref_img, ref_alpha, wc, wa)
    for name, g, w in zip(GRAD_NAMES, got, want):
        scale = w.abs().max().item()
        assert scale > 0, name
        err = (g.double() - w).abs().max().item()
        assert err <= tol["grad_rel"] * scale, f"{name}: max err {err:.3g} vs scale {scale:.3g}"


@pytest.mark.parametrize("compositor", COMPOSITORS)
def test_cached_and_recomputed_backward_agree(compositor):
    # dense: the first backward reuses the forward's cached batches (and consumes them);
    # a second one over the retained graph recomputes every batch. numba: a second backward
    # over the retained graph gives the same gradients.
    scene = with_grad(random_scene(150, 33, 30, torch.float64, seed=8, opaque=True))
    out = render(scene, 33, 30, max_candidates=2048, compositor=compositor)
    loss = out.colors.square().sum() + out.alphas.sum()
    params = [scene[k] for k in GRAD_NAMES]
    first = torch.autograd.grad(loss, params, retain_graph=True)
    second = torch.autograd.grad(loss, params)
    for name, a, b in zip(GRAD_NAMES, first, second):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12, msg=name)


def test_sh_colors_match_reference_and_gsplat():
    from gsplat.cuda._torch_impl import _spherical_harmonics

    width, height = 31, 27
    g = torch.Generator().manual_seed(3)
    scene = random_scene(80, width, height, torch.float64, seed=4)
    scene["colors"] = 0.3 * torch.randn(80, 16, 3, generator=g, dtype=torch.float64)
    dirs = torch.randn(50, 3, generator=g, dtype=torch.float64)
    for degree in range(4):
        ours = eval_sh_colors(degree, dirs, scene["colors"][:50])
        theirs = (_spherical_harmonics(degree, dirs, scene["colors"][:50]) + 0.5).clamp_min(0.0)
        torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)

    scene = with_grad(scene)
    out = render(scene, width, height, sh_degree=3)
    ref_img, ref_alpha, _ = reference_render(scene, width, height, sh_degree=3)
    assert (out.colors - ref_img).abs().max() < 1e-10
    g_out = torch.autograd.grad(out.colors.square().sum(), [scene["means"], scene["colors"]])
    g_ref = torch.autograd.grad(ref_img.square().sum(), [scene["means"], scene["colors"]])
    for a, b in zip(g_out, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-8 * b.abs().max().item())


def test_projection_matches_gsplat_torch_impl():
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    scene = random_scene(100, 64, 48, torch.float64, seed=5)
    covars, _ = _quat_scale_to_covar_preci(scene["quats"], scene["scales"], compute_preci=False)
    radii_g, means2d_g, depths_g, conics_g, _ = _fully_fused_projection(
        scene["means"], covars, scene["viewmats"], scene["Ks"], 64, 48
    )
    ours = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["viewmats"], scene["Ks"], 64, 48
    )
    v = ours.valid
    assert v.sum() > 50
    torch.testing.assert_close(ours.means2d[v], means2d_g[v], rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(ours.conics[v], conics_g[v], rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(ours.depths[v], depths_g[v])
    # Opacity-aware radii (gsplat CUDA) are never larger than the fixed 3.33-sigma ones.
    assert (ours.radii[v] <= radii_g[v]).all()
    assert not (v & (radii_g == 0).all(-1)).any()


# --------------------------------------------------------------------------- analytic


def test_single_isotropic_gaussian_peak_and_falloff():
    width, height, z, s, opacity, f = 33, 29, 2.0, 0.01, 0.8, 100.0
    cx, cy = 16.5, 10.5  # on the centre of pixel (row 10, col 16)
    colour = torch.tensor([[0.2, 0.6, 1.0]], dtype=torch.float64)
    bg = torch.tensor([[0.1, 0.1, 0.1]], dtype=torch.float64)
    out = rasterize(
        torch.tensor([[0.0, 0.0, z]], dtype=torch.float64),
        torch.tensor([[2.0, 0.0, 0.0, 0.0]], dtype=torch.float64),  # unnormalised identity
        torch.full((1, 3), s, dtype=torch.float64),
        torch.tensor([opacity], dtype=torch.float64),
        colour,
        torch.eye(4, dtype=torch.float64)[None],
        torch.tensor([[[f, 0, cx], [0, f, cy], [0, 0, 1]]], dtype=torch.float64),
        width,
        height,
        backgrounds=bg,
        backend="torch",
        render_depth=True,
    )
    alpha = out.alphas[0, ..., 0]
    peak = torch.argmax(alpha).item()
    assert divmod(peak, width) == (10, 16)
    assert alpha[10, 16].item() == pytest.approx(opacity, abs=1e-12)
    torch.testing.assert_close(out.colors[0, 10, 16], opacity * colour[0] + (1 - opacity) * bg[0])
    # On the optical axis the 2D covariance is (f s / z)^2 I + 0.3 I exactly.
    var = (f * s / z) ** 2 + 0.3
    for dr, dc in [(0, 1), (1, 0), (2, -1), (-3, 2)]:
        want = opacity * math.exp(-0.5 * (dr * dr + dc * dc) / var)
        want = want if want >= 1 / 255 else 0.0
        assert alpha[10 + dr, 16 + dc].item() == pytest.approx(want, abs=1e-12)
    assert out.depths[0, 10, 16, 0].item() == pytest.approx(z, abs=1e-12)


# --------------------------------------------------------------------------- stability


def _assert_finite_render_and_grads(scene, width, height, **kwargs):
    scene = with_grad(scene)
    out = render(scene, width, height, **kwargs)
    assert torch.isfinite(out.colors).all() and torch.isfinite(out.alphas).all()
    loss = out.colors.square().sum() + out.alphas.sum()
    if loss.requires_grad:
        for name, g in zip(GRAD_NAMES, torch.autograd.grad(loss, [scene[k] for k in GRAD_NAMES], allow_unused=True)):
            assert g is None or torch.isfinite(g).all(), name
    return out


@pytest.mark.parametrize("compositor", COMPOSITORS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", ["needle", "flat", "tiny", "huge", "zero_quat", "behind", "at_camera"])
def test_degenerate_inputs_stay_finite(kind, dtype, compositor):
    width, height = 24, 20
    scene = random_scene(40, width, height, dtype, seed=11)
    n = scene["means"].shape[0]
    if kind == "needle":
        scene["scales"][:, 1:] = 1e-7
    elif kind == "flat":
        scene["scales"][:, 0] = 0.0
    elif kind == "tiny":
        scene["scales"][:] = 1e-6
    elif kind == "huge":
        scene["scales"][: n // 2] = 1e3
    elif kind == "zero_quat":
        scene["quats"][::2] = 0.0
    elif kind == "behind":
        scene["means"][::2] = -scene["means"][::2] * 0.1 + scene["viewmats"][0, 2, :3] * -5.0
    elif kind == "at_camera":
        cam_pos = -(scene["viewmats"][0, :3, :3].T @ scene["viewmats"][0, :3, 3])
        scene["means"][::3] = cam_pos + 1e-4 * torch.randn(3, dtype=dtype)
    out = _assert_finite_render_and_grads(scene, width, height, compositor=compositor)
    assert (out.alphas >= 0).all() and (out.alphas <= 1).all()


@pytest.mark.parametrize("compositor", COMPOSITORS)
def test_empty_and_fully_culled_scenes_render_background(compositor):
    width, height = 16, 12
    scene = random_scene(10, width, height, torch.float32, seed=2)
    empty = {k: (v[:0] if k not in ("viewmats", "Ks", "backgrounds") else v) for k, v in scene.items()}
    for sc in (empty, dict(scene, means=scene["means"] * 0 + scene["viewmats"][0, 2, :3] * -10.0)):
        sc = dict(sc, viewmats=sc["viewmats"][:1], Ks=sc["Ks"][:1], backgrounds=sc["backgrounds"][:1])
        out = _assert_finite_render_and_grads(sc, width, height, compositor=compositor)
        torch.testing.assert_close(out.colors, sc["backgrounds"][:, None, None].expand_as(out.colors))
        assert (out.alphas == 0).all()


# --------------------------------------------------------------------------- API


def test_input_validation_names_argument():
    scene = random_scene(5, 8, 8, torch.float32, seed=0)
    bad = dict(scene, quats=scene["quats"][:, :3])
    with pytest.raises(ValueError, match=r"quats must be \[N=5, 4\].*got \(5, 3\)"):
        render(bad, 8, 8)
    with pytest.raises(ValueError, match="viewmats"):
        render(dict(scene, viewmats=scene["viewmats"][:, :3]), 8, 8)
    with pytest.raises(ValueError, match="backgrounds"):
        render(dict(scene, backgrounds=scene["backgrounds"][:, :2]), 8, 8)
    with pytest.raises(ValueError, match="colors"):
        render(scene, 8, 8, sh_degree=1)
    with pytest.raises(ValueError, match="backend"):
        render(scene, 8, 8, backend="cuda")
    with pytest.raises(ValueError, match="dtype"):
        render(dict(scene, colors=scene["colors"].double()), 8, 8)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA"):
            render(scene, 8, 8, backend="gsplat")


def test_meta_reports_visibility():
    scene = random_scene(50, 30, 20, torch.float32, seed=1)
    out = render(scene, 30, 20)
    meta = out.meta
    assert meta["radii"].shape == (2, 50, 2) and meta["valid"].shape == (2, 50)
    assert meta["means2d"].shape == (int(meta["valid"].sum()), 2)
    assert meta["stats"].n_contributing > 0


# --------------------------------------------------------------------------- CUDA


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_torch_backend_matches_gsplat_cuda():
    width, height = 64, 48
    scene = {k: v.cuda() for k, v in random_scene(300, width, height, torch.float32, seed=9, opaque=True).items()}
    ours = with_grad(scene)
    theirs = with_grad(scene)
    out_t = render(ours, width, height)
    out_g = rasterize(
        theirs["means"],
        theirs["quats"],
        theirs["scales"],
        theirs["opacities"],
        theirs["colors"],
        theirs["viewmats"],
        theirs["Ks"],
        width,
        height,
        backgrounds=theirs["backgrounds"],
        backend="gsplat",
    )
    # gsplat uses __expf and float32 sequential products: compare loosely.
    assert (out_t.colors - out_g.colors).abs().max() < 2e-3
    assert (out_t.alphas - out_g.alphas).abs().max() < 2e-3
    wc, wa = loss_weights(out_t.colors.shape, out_t.alphas.shape, torch.float32)
    wc, wa = wc.cuda(), wa.cuda()
    for name, a, b in zip(
        GRAD_NAMES,
        grads_of(ours, out_t.colors, out_t.alphas, wc, wa),
        grads_of(theirs, out_g.colors, out_g.alphas, wc, wa),
    ):
        assert (a - b).abs().max() <= 2e-2 * b.abs().max() + 1e-6, name
