"""Inference-only compiled paths (no autograd) against the training path they replace: the fused corrective
deltas (separate and packed bases), the fused LBS + posing pass, the posed quaternion without saved state,
packing the bases, and the whole avatar forward under ``torch.no_grad`` vs with gradients enabled."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.models.properties import GAUSSIAN_PROPERTIES, packed_layout
from gsavatar.models import GaussianAvatar, ModelConfig, model_preset
from gsavatar.models import gaussians as gm
from gsavatar.models import kernels
from prep_fixtures import arm_avatar_inputs, randomize_bases


@pytest.fixture(scope="module")
def prep():
    return arm_avatar_inputs()


def make(prep, cfg: ModelConfig | None = None, randomize: bool = False) -> GaussianAvatar:
    rig, h, masks, pl, pg = prep
    av = GaussianAvatar(h, masks, rig, pl, pg, cfg or model_preset("tiny"))
    if randomize:  # non-zero correctives so that outputs depend on the MLP inputs
        randomize_bases(av)
    return av


LAYOUT = packed_layout(GAUSSIAN_PROPERTIES, ModelConfig(sh_degree=1))  # position, scale, rotation, sh0, 3 SH bands


DIMS = {"position": (3,), "scale": (3,), "rotation": (4,), "sh0": (3,), "shn": (3, 3)}  # the table's at SH degree 1


def _interp_case(dtype, B=2, G=300, A=12, K=16, seed=0):
    """Random coefficients, interpolation weights, one basis per row of LAYOUT (in its order) and anchor SH0."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randint(0, A, (G, 3), generator=g)
    w = torch.rand(G, 3, generator=g, dtype=dtype)
    W = gm.interpolation_matrix(idx, w / w.sum(1, keepdim=True), A)
    bases = [torch.randn(G, K, *DIMS[n], generator=g, dtype=dtype) for n in LAYOUT.names]
    coeffs = torch.randn(B, A, K, generator=g, dtype=dtype)
    extra = torch.randn(B, A, 3, generator=g, dtype=dtype)
    return coeffs, W, bases, extra


def _interp_reference(coeffs, W, bases, n_rest, extra):
    """Interpolate ``w``, then one einsum per basis; the anchor row adds the interpolated ``extra``."""
    w = torch.sparse.mm(W, coeffs.transpose(0, 1).reshape(W.shape[1], -1)).reshape(W.shape[0], coeffs.shape[0], -1)
    w = w.transpose(0, 1)  # [B, G, K]
    out = {}
    for name, b, offset in zip(LAYOUT.names, bases, LAYOUT.offsets):
        b = b[:, :, :n_rest] if name == "shn" else b
        out[name] = torch.einsum("bnk,nk...->bn...", w, b)
        if extra is not None and offset == LAYOUT.anchor_at:
            out[name] = out[name] + gm.sparse_interpolate(extra, W, compiled=False)
    return out


def _packed(bases):
    """The bases side by side in one tensor in LAYOUT's columns, as GaussianAvatar.pack_bases_ lays them out."""
    G, K = bases[0].shape[:2]
    flat = torch.cat([b.reshape(G, K, -1) for b in bases], 2)
    return [flat[:, :, o : o + w].unflatten(2, b.shape[2:]) for b, o, w in zip(bases, LAYOUT.offsets, LAYOUT.widths)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("packed", [False, True])
@pytest.mark.parametrize("n_rest", [0, 2, 3])
@pytest.mark.parametrize("with_extra", [False, True])
def test_interpolated_deltas_match_interpolation_then_products(dtype, packed, n_rest, with_extra):
    coeffs, W, bases, extra = _interp_case(dtype)
    extra = extra if with_extra else None
    if packed:
        bases = _packed(bases)
    assert (kernels.packed_bases(bases, LAYOUT) is not None) == packed
    with torch.no_grad():
        got = kernels.interpolated_deltas_fast(coeffs, W, bases, LAYOUT, n_rest, extra)
    if not packed:  # separate bases: the caller takes the per-basis products (the oracle below)
        assert got is None
        return
    want = _interp_reference(coeffs, W, bases, n_rest, extra)
    tol = {"rtol": 1e-5, "atol": 1e-5} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    assert got is not None and set(got) == set(want) - ({"shn"} if not n_rest else set())  # no bands asked: none
    for name, b in got.items():
        assert b.shape == want[name].shape
        torch.testing.assert_close(b, want[name], **tol)


def test_interpolated_deltas_decline_with_gradients_or_mixed_dtypes():
    coeffs, W, bases, extra = _interp_case(torch.float32)
    bases = _packed(bases)
    fast = kernels.interpolated_deltas_fast
    with torch.no_grad():
        assert fast(coeffs, W, bases, LAYOUT, 3, extra) is not None
    assert fast(coeffs, W, bases, LAYOUT, 3, extra) is None  # grad mode on
    with torch.no_grad():
        assert fast(coeffs.double(), W, bases, LAYOUT, 3, extra) is None
        assert fast(coeffs, W, bases, LAYOUT, 4, extra) is None  # more bands than bases
        assert fast(coeffs[..., :0], W, [b[:, :0] for b in bases], LAYOUT, 3) is None


def test_packed_views_must_line_up():
    coeffs, W, bases, _ = _interp_case(torch.float32)
    views = _packed(bases)
    assert kernels.packed_bases(views, LAYOUT) is not None
    swapped = [views[1], views[0], *views[2:]]  # wrong order: not the packed layout
    assert kernels.packed_bases(swapped, LAYOUT) is None


def _posing_case(dtype, B=2, G=400, J=6, seed=0, spread=0.6):
    g = torch.Generator().manual_seed(seed)
    from gsavatar.geometry.rotations import axis_angle_to_matrix

    T = torch.eye(4, dtype=dtype).repeat(B, J, 1, 1)
    T[:, :, :3, :3] = axis_angle_to_matrix(torch.randn(B, J, 3, generator=g, dtype=dtype) * spread)
    T[:, :, :3, 3] = torch.randn(B, J, 3, generator=g, dtype=dtype)
    idx = torch.stack([torch.randperm(J, generator=g)[:3] for _ in range(G)])
    w = torch.rand(G, 3, generator=g, dtype=dtype) + 0.05
    w = w / w.sum(1, keepdim=True)
    X = torch.randn(B, G, 3, generator=g, dtype=dtype)
    q = torch.randn(B, G, 4, generator=g, dtype=dtype)
    return T, idx, w, gm.interpolation_matrix(idx, w, J), X, q


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_lbs_posing_matches_blend_then_pose(dtype):
    T, idx, w, S, X, q = _posing_case(dtype)
    q_unit = q / q.norm(dim=-1, keepdim=True)
    with torch.no_grad():
        got = kernels.pose_lbs_fast(T, S, X, q, 10 * torch.finfo(dtype).eps, gm.POLAR_MIN_DET)
        means, quats = gm.pose_gaussians(X, q_unit, gm.blend_affine(T, idx, w), compiled=False)
    assert got is not None
    tol = {"rtol": 1e-5, "atol": 2e-5} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-10}
    torch.testing.assert_close(got[0], means, **tol)
    torch.testing.assert_close(got[1], quats, **tol)
    assert (got[1][..., 0] >= 0).all()


def test_fused_lbs_posing_declines_singular_blends_and_gradients():
    T, idx, w, S, X, q = _posing_case(torch.float64)
    T[0, :, :3, :3] = 0.0  # every blend of frame 0 singular: the SVD path must take them
    with torch.no_grad():
        assert kernels.pose_lbs_fast(T, S, X, q, 1e-12, gm.POLAR_MIN_DET) is None
        # gm.pose_lbs falls back and still returns the reference numbers
        means, quats = gm.pose_lbs(X, q / q.norm(dim=-1, keepdim=True), T, idx, w, S)
        m_ref, q_ref = gm.pose_gaussians(
            X, q / q.norm(dim=-1, keepdim=True), gm.blend_affine(T, idx, w), compiled=False
        )
    torch.testing.assert_close(means, m_ref)
    torch.testing.assert_close(quats, q_ref)
    T2, _, _, S2, X2, q2 = _posing_case(torch.float64, seed=1)
    assert kernels.pose_lbs_fast(T2, S2, X2.requires_grad_(), q2, 1e-12, gm.POLAR_MIN_DET) is None


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_posed_quaternion_without_autograd_equals_the_autograd_path(dtype):
    T, idx, w, S, X, q = _posing_case(dtype, B=1, G=300)
    M = gm.blend_affine(T, idx, w)[..., :3]
    tol = 10 * torch.finfo(dtype).eps
    with_grad = kernels.posed_quaternion_fast(M.clone().requires_grad_(), q, tol)
    with torch.no_grad():
        plain = kernels.posed_quaternion_fast(M, q, tol)
    assert with_grad.requires_grad and not plain.requires_grad and plain.dtype == dtype
    # float32 inputs are read as float32 there and converted to float64 first here: one output ulp apart
    torch.testing.assert_close(plain, with_grad.detach(), rtol=0, atol=0 if dtype == torch.float64 else 2.5e-7)


@pytest.mark.parametrize("det_scale", [1e-4, 0.3, 0.9, 1.0, 1.9, 50.0])
def test_newton_polar_scaling_is_exact_inside_and_outside_the_polynomial_range(det_scale):
    # |det| in (0.5, 2) takes the polynomial cube root, outside it pow(): both must give the SVD's factor
    g = torch.Generator().manual_seed(3)
    M = torch.randn(500, 3, 3, generator=g, dtype=torch.float64)
    M = M[torch.linalg.det(M) > 1e-3]
    M = M / torch.linalg.det(M).abs()[:, None, None] ** (1 / 3) * det_scale ** (1 / 3)
    U, _, Vh = torch.linalg.svd(M)
    R = kernels.polar_rotation_fast(M, 1e-14)
    torch.testing.assert_close(R, U @ Vh, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("variant", ["ours", "mmlps"])
def test_avatar_forward_no_grad_matches_the_training_path(prep, variant):
    cfg = ModelConfig(**{**model_preset("tiny").__dict__, "variant": variant, "sh_degree": 2})
    av = make(prep, cfg, randomize=True).eval()
    rig = prep[0]
    g = torch.Generator().manual_seed(7)
    pose = torch.randn(2, rig.pose_dim, generator=g) * 0.4
    rr, tt = torch.randn(2, 3, generator=g) * 0.3, torch.randn(2, 3, generator=g)
    lat = torch.randn(2, av.num_anchors, av.latent_in, generator=g) if av.latent_in else None
    ref = av(pose, rr, tt, latents=lat)  # gradients enabled: the autograd path
    assert ref.means.requires_grad
    with torch.no_grad():
        fast = av(pose, rr, tt, latents=lat)
        assert av.pack_bases_()
        packed = av(pose, rr, tt, latents=lat)
    for out in (fast, packed):
        for name in ("means", "quats", "scales", "opacities", "sh"):
            torch.testing.assert_close(getattr(out, name), getattr(ref, name).detach(), rtol=1e-5, atol=2e-6)


def test_packing_keeps_values_parameters_and_training(prep):
    av = make(prep, randomize=True)
    before = {n: p.detach().clone() for n, p in av.named_parameters()}
    ids = {n: id(p) for n, p in av.named_parameters()}
    assert av.pack_bases_()
    assert {n: id(p) for n, p in av.named_parameters()} == ids
    for n, p in av.named_parameters():
        torch.testing.assert_close(p.detach(), before[n], rtol=0, atol=0)
    assert kernels.packed_bases([getattr(av, n) for n in av.packed_bases], av.packed_layout()) is not None
    # an optimiser step on the views writes through to the packed storage, and the state dict round-trips
    rig = prep[0]
    opt = torch.optim.AdamW(av.param_groups(), eps=1e-15)
    out = av(torch.randn(1, rig.pose_dim) * 0.3, torch.zeros(1, 3), torch.zeros(1, 3))
    (out.means.square().sum() + out.sh.square().sum() + out.scales.sum() + out.quats[..., 1:].sum()).backward()
    opt.step()
    for name in av.packed_bases:
        assert not torch.equal(getattr(av, name).detach(), before[name]), name
    assert kernels.packed_bases([getattr(av, n) for n in av.packed_bases], av.packed_layout()) is not None
    other = make(prep)
    other.load_state_dict(av.state_dict())
    for n, p in other.named_parameters():
        torch.testing.assert_close(p.detach(), dict(av.named_parameters())[n].detach(), rtol=0, atol=0)


def test_activations_match_tanh_and_the_guarded_quaternion():
    x = torch.linspace(-30, 30, 20001, dtype=torch.float32)
    from gsavatar.models.config import SH_C0

    torch.testing.assert_close(gm.activate_sh0(x), torch.tanh(x) * (0.5 / SH_C0), rtol=0, atol=4e-7)
    torch.testing.assert_close(gm.activate_shn(x, 0.7), 0.7 * torch.tanh(x), rtol=0, atol=2e-7)
    q = torch.tensor([[1e20, 2e20, 0.0, 0.0], [3e-13, 0.0, 0.0, 0.0], [0.3, -2.0, 0.5, 1.0]])
    got = gm.activate_quat(q)
    assert torch.isfinite(got).all()
    torch.testing.assert_close(got[0], torch.tensor([1.0, 2.0, 0.0, 0.0]) / np.sqrt(5.0))
    torch.testing.assert_close(got[2], q[2] / q[2].norm())
