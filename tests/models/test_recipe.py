"""The CPU training recipe and the faster step: each fast op against its naive reference, and the
properties the recipe promises (correctives vanish at the mean input, standardised latents)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.geometry.rotations import axis_angle_to_matrix, orthonormalize
from gsavatar.metrics.temporal import frame_dependence
from gsavatar.models import GaussianAvatar, ModelConfig, model_preset
from gsavatar.models import gaussians as gm
from gsavatar.models.encoder import LatentNorm
from gsavatar.prep.localize import build_localization
from gsavatar.prep.pca import fit_pose_pca
from gsavatar.prep.sample_points import build_hierarchy
from prep_fixtures import arm_rig, arm_template, randomize_bases


@pytest.fixture(scope="module")
def prep():
    rig, t = arm_rig(), arm_template()
    h = build_hierarchy(t, n_anchors=24, n_control=120, n_gaussians=800, seed=0, min_candidates=2000)
    poses = np.random.default_rng(0).normal(size=(60, rig.pose_dim)) * 0.3
    return rig, h, build_localization(h, rig, t.face_uv_mask), fit_pose_pca(poses, rig, 2, "local")


def make(prep, cfg: ModelConfig, randomize: bool = False) -> GaussianAvatar:
    rig, h, masks, pca = prep
    av = GaussianAvatar(h, masks, rig, pca, None, cfg)
    if randomize:  # non-zero correctives so that outputs depend on the MLP inputs
        randomize_bases(av)
    return av


# tolerance per dtype for the Newton polar factor vs the SVD (round-off of ~6 iterations)
POLAR_TOL = {torch.float64: (1e-12, 1e-9), torch.float32: (5e-6, 5e-3)}  # (values, gradients)


def _blends(n: int, spread: float, dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    R = axis_angle_to_matrix(torch.randn(3, n, 3, generator=g, dtype=torch.float64) * spread)
    w = torch.rand(n, 3, generator=g, dtype=torch.float64)
    w = w / w.sum(1, keepdim=True)
    return torch.einsum("nk,knij->nij", w, R).to(dtype)  # LBS-like blends of three rotations


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("spread", [0.2, 1.0, 2.5])
def test_polar_rotation_matches_svd_values_and_gradients(dtype, spread, compiled):
    M = _blends(400, spread, dtype)
    ok = torch.det(M.double()) > 1e-2  # SVD's own gradient is ill-conditioned near singular blends
    tv, tg = POLAR_TOL[dtype]
    Q = gm.polar_rotation(M, compiled=compiled)
    torch.testing.assert_close(Q, orthonormalize(M.double()).to(dtype), rtol=0, atol=tv)
    torch.testing.assert_close(torch.det(Q.double()), torch.ones(len(M), dtype=torch.float64), rtol=0, atol=10 * tv)
    G = torch.randn(M.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    a = M.double().clone().requires_grad_()
    (gm.polar_rotation(a, compiled=compiled) * G).sum().backward()
    b = M.double().clone().requires_grad_()
    (orthonormalize(b) * G).sum().backward()
    scale = b.grad[ok].abs().max()
    torch.testing.assert_close(a.grad[ok] / scale, b.grad[ok] / scale, rtol=0, atol=tg)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch"])
def test_polar_rotation_hard_cases(compiled):
    I = torch.eye(3, dtype=torch.float64)
    R = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, np.pi * 0.999]], dtype=torch.float64))[0]
    cases = torch.stack(
        [
            I,  # exact rotation: SVD's backward is NaN here, ours is finite
            0.5 * (I + R),  # near-opposite blend: nearly singular -> SVD fallback
            torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)),  # reflection -> SVD path, det +1
            torch.zeros(3, 3, dtype=torch.float64),  # degenerate
            1e-20 * I,  # tiny scale: scaling keeps Newton exact
        ]
    ).requires_grad_()
    Q = gm.polar_rotation(cases, compiled=compiled)
    assert torch.isfinite(Q).all()
    torch.testing.assert_close(torch.det(Q.detach()), torch.ones(5, dtype=torch.float64), rtol=0, atol=1e-9)
    torch.testing.assert_close(Q[0].detach(), I, rtol=0, atol=1e-12)
    torch.testing.assert_close(Q[4].detach(), I, rtol=0, atol=1e-12)
    Q.sum().backward()
    assert torch.isfinite(cases.grad).all()
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 3\]"):
        gm.polar_rotation(torch.zeros(4, 3))


def test_sparse_interpolate_matches_gather_values_and_gradients():
    g = torch.Generator().manual_seed(0)
    N, M, k, B, D = 500, 40, 3, 2, 7
    idx = torch.randint(0, M, (N, k), generator=g)
    idx[0] = 3  # a repeated source must add up, as in the gather
    w = torch.rand(N, k, generator=g, dtype=torch.float64)
    v1 = torch.randn(B, M, D, generator=g, dtype=torch.float64, requires_grad=True)
    v2 = v1.detach().clone().requires_grad_()
    ref = gm.interpolate(v1, idx, w)
    out = gm.sparse_interpolate(v2, gm.interpolation_matrix(idx, w, M))
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    G = torch.randn(ref.shape, generator=g, dtype=torch.float64)
    (ref * G).sum().backward()
    (out * G).sum().backward()
    torch.testing.assert_close(v2.grad, v1.grad, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="sources"):
        gm.sparse_interpolate(v2[:, :10], gm.interpolation_matrix(idx, w, M))


def test_blend_affine_sparse_matches_gather():
    g = torch.Generator().manual_seed(0)
    B, J, N, K = 2, 9, 300, 4
    T = torch.randn(B, J, 4, 4, generator=g, dtype=torch.float64)
    idx = torch.randint(0, J, (N, K), generator=g)
    w = torch.rand(N, K, generator=g, dtype=torch.float64)
    ref = gm.blend_affine(T, idx, w)
    out = gm.blend_affine(T, idx, w, gm.interpolation_matrix(idx, w, J))
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)


def test_frame_dependence_known_answers():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(30, 200, 3, generator=g, dtype=torch.float64)
    # a static prediction has ratio 0; one that moves half as much (plus any constant) has ratio 0.5
    assert frame_dependence(gt.mean(0, keepdim=True).expand_as(gt), gt)["ratio"] == pytest.approx(0.0, abs=1e-12)
    r = frame_dependence(0.5 * gt + 0.2, gt)
    assert r["ratio"] == pytest.approx(0.5, rel=1e-12)
    assert r["std_gt"] == pytest.approx(float(gt.std(0, correction=0).mean()), rel=1e-12)
    # weights leave points out: a point that moves wildly but has weight 0 does not count
    pred = gt.clone()
    pred[:, 0] = torch.randn(30, 3, generator=g, dtype=torch.float64) * 100
    w = torch.ones(200, dtype=torch.float64)
    w[0] = 0
    assert frame_dependence(pred, gt, w)["ratio"] == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(ValueError, match=r"\[F, N, C\]"):
        frame_dependence(gt[0], gt[0])
    with pytest.raises(ValueError, match="2 frames"):
        frame_dependence(gt[:1], gt[:1])


def test_latent_norm_learns_per_anchor_statistics_and_freezes_in_eval():
    g = torch.Generator().manual_seed(0)
    A, L = 5, 3
    mean = torch.randn(A, L, generator=g) * 3
    std = torch.rand(A, L, generator=g) * 0.01 + 0.001  # tiny frame-to-frame change, as the encoder's
    norm = LatentNorm(A, L, momentum=0.01).train()
    for _ in range(3000):
        norm(mean + std * torch.randn(2, A, L, generator=g))
    torch.testing.assert_close(norm.mean, mean, rtol=0, atol=3e-3 * 1)
    torch.testing.assert_close(norm.var.sqrt() / std, torch.ones(A, L), rtol=0, atol=0.3)
    norm.eval()
    x = mean + std * torch.randn(4000, A, L, generator=g)
    before = norm.mean.clone()
    z = norm(x)
    assert torch.equal(norm.mean, before)  # eval: frozen
    torch.testing.assert_close(z.std(0), torch.ones(A, L), rtol=0, atol=0.35)
    with pytest.raises(ValueError, match="momentum"):
        LatentNorm(A, L, momentum=0.0)


def test_centred_correctives_vanish_at_the_mean_input(prep):
    rig, *_ = prep
    cfg = model_preset("tiny")
    assert cfg.input_norm and cfg.center_correctives and cfg.latent_norm  # the CPU recipe
    assert not model_preset("paper").center_correctives  # the paper preset keeps the paper's model
    av = make(prep, cfg, randomize=True)
    poses = torch.randn(50, rig.pose_dim, generator=torch.Generator().manual_seed(2)) * 0.3
    av.set_input_stats(poses)
    av.train()
    x = av.conditioning_pose(poses)
    torch.testing.assert_close(av.pose_in_mean, x.mean(0))
    # an input whose conditioning pose is the mean: coefficients exactly 0 (latents 0 = the mean latent)
    lat = torch.zeros(1, av.num_anchors, av.latent_in)
    mean_pose = av.pose_in_mean[None]
    w = av.pose_head.coefficients(av.anchor_inputs(mean_pose, None, lat))
    torch.testing.assert_close(w, torch.zeros_like(w), rtol=0, atol=1e-6)
    # elsewhere they are not, and the posed output differs from the bias-only avatar
    w2 = av.pose_head.coefficients(av.anchor_inputs(poses[:2], None, torch.randn(2, av.num_anchors, av.latent_in)))
    assert w2.abs().max() > 1e-3
    # without centring, the mean input gives the MLP's static output
    plain = make(prep, cfg.replace(center_correctives=False), randomize=True)
    plain.set_input_stats(poses)
    plain.train()
    assert plain.pose_head.coefficients(plain.anchor_inputs(mean_pose, None, lat)).abs().max() > 1e-3
    with pytest.raises(ValueError, match="input_norm"):
        make(prep, cfg.replace(input_norm=False)).set_input_stats(poses)


def test_anchor_sh0_basis_against_a_dense_oracle(prep):
    """``anchor_sh0``: zero anchor basis = the plain avatar; a non-zero one adds, per Gaussian, the anchor
    deltas ``<w_a, ΔΛ^a>`` blended with the Gaussian's anchor weights (dense oracle), and gets gradients."""
    rig, *_ = prep
    cfg = model_preset("tiny").replace(latent_sh0=False)  # the latent colour map has its own test (test_pose_heads)
    pose = torch.randn(2, rig.pose_dim, generator=torch.Generator().manual_seed(3)) * 0.3
    torch.manual_seed(0)
    plain = make(prep, cfg, randomize=True)
    torch.manual_seed(0)
    av = make(prep, cfg.replace(anchor_sh0=True), randomize=True)
    av.load_state_dict(plain.state_dict(), strict=False)
    with torch.no_grad():
        av.sh0_anchor_basis.zero_()  # randomize_bases filled it too
    assert set(av.state_dict()) - set(plain.state_dict()) == {"sh0_anchor_basis"}
    rr, rt = torch.zeros(2, 3), torch.zeros(2, 3)
    lat = torch.randn(2, av.num_anchors, av.latent_in, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(av(pose, rr, rt, None, lat).sh, plain(pose, rr, rt, None, lat).sh, rtol=0, atol=0)
    with torch.no_grad():
        av.sh0_anchor_basis.normal_(0, 0.3, generator=torch.Generator().manual_seed(5))
    out = av(pose, rr, rt, None, lat)
    coeffs = av.pose_head.coefficients(av.anchor_inputs(pose, None, lat))[..., : cfg.n_basis]  # [B, A, Bg]
    d_a = (coeffs[..., None] * av.sh0_anchor_basis[None]).sum(2)  # [B, A, 3]
    dense = av.sparse_weights("gauss_anchor", d_a.device, d_a.dtype).to_dense()  # [G, A]
    w_g = torch.einsum("ga,bak->bgk", dense, coeffs)
    pre = av.sh0_bias[None] + (w_g[..., None] * av.sh0_basis[None]).sum(2) + torch.einsum("ga,bad->bgd", dense, d_a)
    torch.testing.assert_close(out.sh[:, :, 0], gm.activate_sh0(pre), rtol=1e-5, atol=1e-6)
    out.sh.sum().backward()
    assert av.sh0_anchor_basis.grad is not None and av.sh0_anchor_basis.grad.abs().max() > 0
    groups = {g["name"]: g for g in av.param_groups()}
    assert groups["sh0_anchor_basis"]["lr"] == groups["sh0_basis"]["lr"]
    assert "sh0_anchor_basis" not in {g["name"] for g in plain.param_groups()}
