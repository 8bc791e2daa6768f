"""FrameBatch, the model's one input, and AvatarNet's forward on it (against the pre-refactor composition)."""

from __future__ import annotations

import pytest
import torch

from avatar_variants import build_parts, make_inputs, make_variant
from gsavatar.models import AppearanceEncoder, AvatarNet, FrameBatch
from gsavatar.models.encoder import sample_at_uv


@pytest.fixture(scope="module")
def parts():
    return build_parts()


def _net(parts) -> AvatarNet:
    torch.manual_seed(0)
    av = make_variant(parts, "ours")
    return AvatarNet(av, AppearanceEncoder(latent_dim=16), torch.from_numpy(parts[1].anchors.uv).float())


def test_from_dict_of_dataset_items():
    B, P = 2, 5
    items = {
        "pose": torch.zeros(B, P),
        "root_rotation": torch.zeros(B, 3),
        "root_translation": torch.ones(B, 3),
        "face": torch.zeros(B, 0),
        "frame": torch.tensor([3, 4]),
        "image": torch.zeros(B, 3, 4, 4),
    }
    b = FrameBatch.from_dict(items)
    assert b.face is None and b.texture is None and b.latents is None and b.batch_size == B  # [B, 0] face: none
    items |= {"face": torch.ones(B, 3), "texture": torch.zeros(B, 3, 64, 64)}
    lat = torch.zeros(B, 7, 16)
    b = FrameBatch.from_dict(items, lat)
    assert b.face is items["face"] and b.texture is items["texture"] and b.latents is lat
    moved = b.to("cpu")
    assert isinstance(moved, FrameBatch) and torch.equal(moved.root_translation, items["root_translation"])
    assert FrameBatch(*b)._replace(pose=b.pose + 1).pose.sum() == B * P


def test_avatar_net_forward_is_the_pre_refactor_composition(parts):
    # Before: net(pose, rr, rt, face, texture, eps, sh, correctives, latents=None) with the trainer's own sample
    # ``mu + exp(logvar / 2) * eps``; now net(FrameBatch, sh_degree=, correctives=, eps=) samples in the encoder.
    net = _net(parts).train()
    pose, rr, rt, face, _ = make_inputs(parts)
    tex = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(1))
    eps = torch.randn(2, 16, 2, 2, generator=torch.Generator().manual_seed(2))
    stats = {k: v.clone() for k, v in net.latent_norm.state_dict().items()}
    got = net(FrameBatch(pose, rr, rt, face, tex), sh_degree=1, correctives=True, eps=eps)
    net.latent_norm.load_state_dict(stats)  # the running statistics updated once: replay from the same state
    enc = net.encoder(tex)
    lat = net.latent_norm(sample_at_uv(enc.mu + torch.exp(0.5 * enc.logvar) * eps, net.anchor_uv))
    want = net.avatar(pose, rr, rt, face, lat, sh_degree=1, correctives=True)
    for a, b in zip(got.avatar, want):
        assert torch.equal(a, b)
    assert torch.equal(got.mu, enc.mu) and torch.equal(got.logvar, enc.logvar)


def test_given_latents_skip_the_encoder_and_a_missing_texture_is_named(parts):
    net = _net(parts).eval()
    pose, rr, rt, face, lat = make_inputs(parts)
    out = net(FrameBatch(pose, rr, rt, face, latents=lat))
    assert out.mu is None and out.logvar is None
    want = net.avatar(pose, rr, rt, face, lat)
    assert all(torch.equal(a, b) for a, b in zip(out.avatar, want))
    with pytest.raises(ValueError, match="texture"):
        net(FrameBatch(pose, rr, rt, face))


def test_every_parameter_gets_a_gradient_through_one_forward(parts):
    # AvatarNet exists so DDP sees the avatar and the encoder behind one forward.
    net = _net(parts).train()
    pose, rr, rt, face, _ = make_inputs(parts)
    tex = torch.rand(2, 3, 64, 64)
    out = net(FrameBatch(pose, rr, rt, face, tex), eps=torch.randn(2, 16, 2, 2))
    (sum(t.square().mean() for t in out.avatar) + out.mu.square().mean() + out.logvar.mean()).backward()
    # (reached by autograd; the MLPs' last bias gets an exact 0: center_correctives subtracts it back out)
    assert not [n for n, p in net.named_parameters() if p.numel() and p.grad is None]
