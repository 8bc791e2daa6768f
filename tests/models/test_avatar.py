from __future__ import annotations

import numpy as np
import pytest
import torch

from gsavatar.geometry.rotations import axis_angle_to_matrix, orthonormalize, quat_to_matrix
from gsavatar.models import GaussianAvatar, LearningRates, ModelConfig, model_preset, variant_config
from gsavatar.models import gaussians as gm
from gsavatar.models.pose_heads import UVDecoderHead
from prep_fixtures import arm_avatar_inputs, randomize_bases


@pytest.fixture(scope="module")
def prep():
    return arm_avatar_inputs()


def make(prep, cfg: ModelConfig | None = None, randomize: bool = False, face_dim: int | None = None) -> GaussianAvatar:
    rig, h, masks, pl, pg = prep
    av = GaussianAvatar(h, masks, rig, pl, pg, cfg or model_preset("tiny"), face_dim=face_dim)
    if randomize:  # non-zero correctives so that outputs depend on the MLP inputs
        randomize_bases(av)
    return av


def zeros(B, P):
    return torch.zeros(B, P), torch.zeros(B, 3), torch.zeros(B, 3)


def test_rest_pose_without_correctives_is_the_hierarchy(prep):
    rig, h, *_ = prep
    av = make(prep)
    out = av(*zeros(2, rig.pose_dim), correctives=False)
    G, C = h.num_gaussians, h.num_control
    assert out.means.shape == (2, G, 3) and out.quats.shape == (2, G, 4) and out.scales.shape == (2, G, 3)
    assert out.opacities.shape == (2, G) and out.sh.shape == (2, G, 4, 3) and out.ctrl_disp.shape == (2, C, 3)
    rest = torch.as_tensor(h.gaussians.position)
    assert torch.equal(out.canonical_means[0], rest)
    torch.testing.assert_close(out.means[1], rest, rtol=0, atol=1e-6)
    torch.testing.assert_close(out.opacities, torch.full_like(out.opacities, 0.9))
    assert (out.sh == 0).all()  # grey: colour 0.5
    assert (out.scales <= av.config.scale_max).all() and (out.scales > 0).all()
    # flat Gaussians: the smallest axis is the surface normal
    R = quat_to_matrix(out.quats[0])
    n = torch.as_tensor(h.gaussians.normal)
    torch.testing.assert_close((R[:, :, 2] * n).sum(-1).abs(), torch.ones(G), rtol=0, atol=1e-5)
    assert (out.scales[0, :, 2] < out.scales[0, :, 0]).all()
    # correctives on but all bases zero (init): same canonical Gaussians
    on = av(*zeros(2, rig.pose_dim), latents=torch.randn(2, h.num_anchors, 16))
    torch.testing.assert_close(on.canonical_means, out.canonical_means, rtol=0, atol=0)
    torch.testing.assert_close(on.scales, out.scales, rtol=0, atol=0)


def test_root_motion_is_rigid(prep):
    rig, h, *_ = prep
    av = make(prep, randomize=True)
    P = rig.pose_dim
    pose = torch.randn(1, P) * 0.3
    aa, tr = torch.tensor([[0.3, -1.1, 0.7]]), torch.tensor([[0.5, -0.2, 1.0]])
    base = av(pose, torch.zeros(1, 3), torch.zeros(1, 3))
    moved = av(pose, aa, tr)
    R = axis_angle_to_matrix(aa)[0]
    head = torch.as_tensor(rig.heads()[0])
    want = (base.means[0] - head) @ R.T + head + tr[0]
    torch.testing.assert_close(moved.means[0], want, rtol=0, atol=1e-5)
    torch.testing.assert_close(moved.canonical_means, base.canonical_means, rtol=0, atol=0)
    Rq = quat_to_matrix(moved.quats[0])
    torch.testing.assert_close(Rq, R @ quat_to_matrix(base.quats[0]), rtol=0, atol=1e-5)
    torch.testing.assert_close(moved.quats.norm(dim=-1), torch.ones(1, h.num_gaussians), rtol=0, atol=1e-6)
    torch.testing.assert_close(torch.det(Rq), torch.ones(h.num_gaussians), rtol=0, atol=1e-5)


def _region(prep, av, slots):
    """Gaussians whose anchors, control points' anchors and skinning joints never see ``slots``."""
    rig, h, *_ = prep
    off = (av.pose_mask[:, slots] == 0).all(1).numpy()  # [A]
    ok = off[h.gauss_anchor_idx].all(1) & off[h.ctrl_anchor_idx[h.gauss_ctrl_idx]].all((1, 2))
    moved = [rig.joint_index(j) for j in ("LeftForeArm", "LeftHand", "LeftFinger")]
    ok &= ~(np.isin(h.gaussians.skin_indices, moved) & (h.gaussians.skin_weights > 0)).any(1)
    assert ok.sum() > 10 and (~ok).sum() > 10
    return torch.as_tensor(ok)


def _outputs_equal(a, b, sel):
    return all(torch.equal(x[:, sel], y[:, sel]) for x, y in zip(a[:5], b[:5])) and torch.equal(
        a.canonical_means[:, sel], b.canonical_means[:, sel]
    )


def _slots(prep, name):
    rig, _, masks, *_ = prep
    s = masks.slot_of(rig, name)
    size = [p.size for p in rig.params if p.name == name][0]
    return list(range(s, s + size))


@pytest.mark.parametrize(
    "variant,pca,param,identical",
    [
        ("ours", "local", "LeftFinger.rx", True),  # hand group: local PCA keeps it within the hand
        ("ours", "none", "LeftForeArm.r", True),
        ("mmlps", "none", "LeftForeArm.r", False),  # MMLPs: full pose everywhere...
        ("mmlps", "none", "LeftFinger.rx", True),  # ...except the localized hand/finger params
    ],
)
def test_local_masking(prep, variant, pca, param, identical):
    rig = prep[0]
    av = make(prep, model_preset("tiny", variant=variant, pca=pca), randomize=True)
    slots = _slots(prep, param)
    sel = _region(prep, make(prep, model_preset("tiny", pca="none")), slots)  # region of the ours-mask
    pose = torch.randn(2, rig.pose_dim) * 0.3
    pose2 = pose.clone()
    pose2[:, slots] += 0.4
    rr, tt = torch.randn(2, 3), torch.randn(2, 3)
    a, b = av(pose, rr, tt), av(pose2, rr, tt)
    assert _outputs_equal(a, b, sel) == identical
    assert not torch.equal(a.means[:, ~sel], b.means[:, ~sel])  # the rest does change


def test_without_local_pose_every_anchor_sees_everything(prep):
    rig = prep[0]
    av = make(prep, model_preset("tiny", local_pose=False, pca="none"), randomize=True)
    assert (av.pose_mask == 1).all()
    slots = _slots(prep, "LeftFinger.rx")
    sel = _region(prep, make(prep, model_preset("tiny", pca="none")), slots)
    pose = torch.randn(1, rig.pose_dim) * 0.3
    pose2 = pose.clone()
    pose2[:, slots] += 0.4
    root = (torch.zeros(1, 3), torch.zeros(1, 3))
    assert not _outputs_equal(av(pose, *root), av(pose2, *root), sel)


def test_face_embedding_is_masked(prep):
    rig, h, masks, *_ = prep
    assert masks.face.any() and not masks.face.all()
    av = make(prep, face_dim=3)
    x = av.anchor_inputs(torch.randn(2, rig.pose_dim), torch.randn(2, 3), torch.randn(2, h.num_anchors, 16))
    assert x.shape == (2, h.num_anchors, rig.pose_dim + 3 + 16)
    face_part = x[..., rig.pose_dim : rig.pose_dim + 3]
    assert (face_part[:, ~torch.as_tensor(masks.face)] == 0).all()
    assert (face_part[:, torch.as_tensor(masks.face)] != 0).all()
    av(torch.zeros(2, rig.pose_dim), torch.zeros(2, 3), torch.zeros(2, 3), face=torch.randn(2, 3))
    with pytest.raises(ValueError, match=r"face must be \[2, 3\]"):
        av(torch.zeros(2, rig.pose_dim), torch.zeros(2, 3), torch.zeros(2, 3), face=torch.randn(2, 4))


def test_pca_modes(prep):
    rig, _, _, pl, pg = prep
    pose = torch.randn(3, rig.pose_dim, dtype=torch.float64) * 2.0  # far outside the fit: clamping kicks in
    loc = torch.as_tensor(pl.project(pose.numpy())).float()
    glob = torch.as_tensor(pg.project(pose.numpy())).float()
    p = pose.float()
    for mode, train_want, eval_want in (
        ("local", loc, loc),
        ("global", glob, glob),
        ("global_test_only", p, glob),
        ("none", p, p),
    ):
        av = make(prep, model_preset("tiny", pca=mode))
        torch.testing.assert_close(av.train().conditioning_pose(p), train_want, rtol=0, atol=1e-5)
        torch.testing.assert_close(av.eval().conditioning_pose(p), eval_want, rtol=0, atol=1e-5)
    assert not torch.allclose(loc, glob, atol=1e-3)
    with pytest.raises(ValueError, match="pca_local"):
        GaussianAvatar(prep[1], prep[2], rig, None, pg, model_preset("tiny"))


def test_variant_configs_and_presets():
    base = model_preset("paper")
    assert base.hidden == (512, 256, 256, 256) and model_preset("tiny").hidden == (64, 64)
    d = variant_config(base, "mmlps_dagger")
    assert (d.variant, d.pca, d.use_latent, d.local_pose) == ("mmlps", "global_test_only", False, True)
    assert variant_config(base, "wo_local_pca").pca == "global"
    assert variant_config(base, "wo_local_pose").local_pose is False
    with pytest.raises(ValueError):
        ModelConfig(variant="x")
    with pytest.raises(ValueError):
        model_preset("huge")


def test_mmlps_dagger_without_latents(prep):
    rig, h, *_ = prep
    av = make(prep, variant_config(model_preset("tiny"), "mmlps_dagger"))
    assert av.pose_head.mlp.in_dim == rig.pose_dim
    out = av(*zeros(1, rig.pose_dim), latents=torch.randn(1, h.num_anchors, 16))  # ignored
    assert out.means.shape == (1, h.num_gaussians, 3)


def test_sh_degree_and_shape_errors(prep):
    rig, h, *_ = prep
    av = make(prep)
    assert av(*zeros(1, rig.pose_dim), sh_degree=0).sh.shape == (1, h.num_gaussians, 1, 3)
    with pytest.raises(ValueError, match="sh_degree"):
        av(*zeros(1, rig.pose_dim), sh_degree=2)
    with pytest.raises(ValueError, match=rf"pose must be \[B, {rig.pose_dim}\], got \[1, 3\]"):
        av(torch.zeros(1, 3), torch.zeros(1, 3), torch.zeros(1, 3))
    with pytest.raises(ValueError, match=r"root_translation must be \[2, 3\]"):
        av(torch.zeros(2, rig.pose_dim), torch.zeros(2, 3), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="latents must be"):
        av(*zeros(1, rig.pose_dim), latents=torch.zeros(1, 3, 16))


def test_param_groups_and_training_step(prep):
    rig, h, *_ = prep
    av = make(prep)
    groups = av.param_groups(LearningRates())
    by = {g["name"]: g for g in groups}
    assert by["mlp"]["lr"] == 5e-4 and by["mlp"]["weight_decay"] == 1e-3
    assert by["sh0_bias"]["lr"] == 2.5e-3 and by["shn_basis"]["lr"] == 2.5e-6 and by["ctrl_bias"]["lr"] == 1.6e-4
    assert by["gauss_pos_basis"]["lr"] == 1e-4 and "opacity_basis" not in by
    assert all(g["weight_decay"] == 0 for g in groups if g["name"] != "mlp")
    n = sum(p.numel() for g in groups for p in g["params"])
    assert n == sum(p.numel() for p in av.parameters()) == av.parameter_counts()["total"]
    opt = torch.optim.AdamW(groups, eps=1e-15, betas=(0.9, 0.999))
    pose = (torch.randn(2, rig.pose_dim) * 0.3).requires_grad_()  # grads through the polar path too
    out = av(pose, torch.randn(2, 3), torch.randn(2, 3), latents=torch.randn(2, h.num_anchors, 16))
    loss = (
        out.means.square().mean()
        + out.scales.mean()
        + out.sh.square().mean()
        + out.quats[..., 1].mean()
        + out.ctrl_disp.square().mean()
    )
    loss.backward()
    assert torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0
    for name, p in av.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    assert av.scale_basis.grad.abs().sum() > 0  # correctives receive gradient at zero init
    before = av.scale_basis.detach().clone()
    opt.step()
    assert not torch.equal(before, av.scale_basis)


def test_polar_rotation_matches_svd_and_has_finite_grads():
    torch.manual_seed(0)
    R1, R2 = axis_angle_to_matrix(torch.randn(2, 50, 3, dtype=torch.float64))
    w = torch.rand(50, 1, 1, dtype=torch.float64)
    M = (w * R1 + (1 - w) * R2).requires_grad_()
    Q = gm.polar_rotation(M)
    torch.testing.assert_close(Q, orthonormalize(M.detach()), rtol=0, atol=1e-10)
    Q.sum().backward()
    assert torch.isfinite(M.grad).all()
    I = torch.eye(3, dtype=torch.float64).expand(4, 3, 3).clone().requires_grad_()
    gm.polar_rotation(I).sum().backward()
    assert torch.isfinite(I.grad).all()


def test_device_dtype_agnostic_float64(prep):
    rig, h, *_ = prep
    av = make(prep, randomize=True).double()
    out = av(
        torch.zeros(1, rig.pose_dim, dtype=torch.float64),
        torch.zeros(1, 3, dtype=torch.float64),
        torch.zeros(1, 3, dtype=torch.float64),
    )
    assert out.means.dtype == torch.float64
    assert all(b.dtype in (torch.float64, torch.long) for b in av.buffers())


def test_nrfgca_dagger_conv_uv_decoder(prep):
    rig, h, masks, *_ = prep
    cfg = variant_config(model_preset("tiny", uv_decoder_size=32, uv_decoder_channels=32), "nrfgca_dagger")
    assert (cfg.variant, cfg.pca, cfg.use_latent, cfg.local_pose) == ("conv_uv", "none", False, False)
    av = make(prep, cfg)
    assert isinstance(av.pose_head, UVDecoderHead) and av.scale_basis.numel() == 0
    pose = torch.randn(2, rig.pose_dim) * 0.3
    args = (pose, torch.zeros(2, 3), torch.zeros(2, 3))
    # the decoder's last conv starts at zero: the model starts as the bias-only avatar
    a, b = av(*args), av(*args, correctives=False)
    assert torch.equal(a.means, b.means) and torch.equal(a.sh, b.sh)
    groups = av.param_groups()
    assert sum(p.numel() for g in groups for p in g["params"]) == sum(p.numel() for p in av.parameters())
    with torch.no_grad():
        av.pose_head.uv_decoder.head.weight.normal_(0, 0.05)
    out = av(*args)
    (out.means.square().mean() + out.sh.square().mean() + out.scales.mean()).backward()
    for name, p in av.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    assert av.pose_head.uv_decoder.fc.weight.grad.abs().sum() > 0
    # no localization: one distant pose parameter moves Gaussians everywhere, unlike 'ours'
    slot = 0
    region = torch.from_numpy(masks.pose[:, slot])[torch.from_numpy(h.gauss_anchor_idx)].any(1)
    assert (~region).any()
    p2 = pose.clone()
    p2[:, slot] += 0.5
    with torch.no_grad():
        d = (av(p2, *args[1:]).canonical_means - av(*args).canonical_means).norm(dim=-1)[0]
    assert d[~region].mean() > 1e-6
    with pytest.raises(ValueError, match="size must be"):
        make(prep, model_preset("tiny", uv_decoder_size=48, variant="conv_uv", use_latent=False))
