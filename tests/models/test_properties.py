"""The property table (models/properties.py): a toy property added as one row in a test-only subclass gets its
parameters, optimiser groups, packed columns, pose-head deltas and activation, and trains through both the
compiled and the torch path to the same numbers."""

from __future__ import annotations

import pytest
import torch
from avatar_variants import FACE_DIM, build_parts, make_inputs

from gsavatar.models import GaussianAvatar, model_preset, variant_config
from gsavatar.models import kernels
from gsavatar.models.config import LearningRates
from gsavatar.runs.checkpoint import load_optimizer_by_group_name
from gsavatar.utils.errors import SchemaError
from gsavatar.models.properties import (
    GAUSSIAN_PROPERTIES,
    GaussianProperty,
    activate_sigmoid,
    check_table,
    packed_layout,
)

ROUGHNESS = GaussianProperty(
    "roughness", (2,), activate_sigmoid, "roughness_bias", "roughness_basis", "opacity_bias", "scale_basis"
)
"""The toy: two values in (0, 1) per Gaussian, with a bias and a corrective basis (the docstring's example)."""


class ToyAvatar(GaussianAvatar):
    PROPERTIES = (*GAUSSIAN_PROPERTIES, ROUGHNESS)


@pytest.fixture(scope="module")
def parts():
    return build_parts()


def make(parts, variant: str = "ours", seed: int = 1) -> ToyAvatar:
    rig, h, masks, pl, pg = parts
    cfg = variant_config(model_preset("tiny", uv_decoder_size=32, uv_decoder_channels=32), variant)
    torch.manual_seed(3)  # the UV decoder's init draws from the global generator
    av = ToyAvatar(h, masks, rig, pl, pg, cfg, face_dim=FACE_DIM, seed=seed)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():  # non-zero bases, so the outputs depend on the coefficients
        for n, p in av.named_parameters():
            if n.endswith("_basis"):
                p.copy_(torch.randn(p.shape, generator=g) * 0.05)
    return av


def test_one_row_builds_the_parameters_groups_and_layout(parts):
    av = make(parts)
    G, Bg = av.num_gaussians, av.pose_head.n_basis
    assert av.roughness_bias.shape == (G, 2) and av.roughness_basis.shape == (G, Bg, 2)
    groups = {g["name"]: g for g in av.param_groups(LearningRates())}
    assert groups["roughness_bias"]["lr"] == LearningRates().opacity_bias
    assert groups["roughness_basis"]["params"] == [av.roughness_basis]
    assert av.parameter_counts()["roughness_basis"] == G * Bg * 2
    layout = packed_layout(av.PROPERTIES, av.config)
    assert layout.names[-1] == "roughness" and layout.widths[-1] == 2
    assert layout.size == 3 + 3 + 4 + 3 + 3 * (av.config.num_sh - 1) + 2
    rig, h, masks, pl, pg = parts
    plain = GaussianAvatar(h, masks, rig, pl, pg, av.config, face_dim=FACE_DIM, seed=1)
    assert {n for n, _ in av.named_parameters()} - {n for n, _ in plain.named_parameters()} == {
        "roughness_bias",
        "roughness_basis",
    }


def _train_two_steps(parts, compiled: bool, monkeypatch) -> dict[str, torch.Tensor]:
    with monkeypatch.context() as m:
        if not compiled:
            m.setattr(kernels, "numba", None)  # every fast kernel declines: the torch twins
        kernels.reset_paths()
        av = make(parts).train()
        # SGD: its step is linear in the gradient, so the two paths' rounding stays rounding (AdamW's eps=1e-15
        # turns a near-zero gradient's sign into a full step)
        opt = torch.optim.SGD([{**g, "lr": 10 * g["lr"]} for g in av.param_groups()])
        pose, rr, rt, face, lat = make_inputs(parts)
        for _ in range(2):
            out, extras = av.evaluate(pose, rr, rt, face, lat)
            assert set(extras) == {"roughness"} and extras["roughness"].shape == (2, av.num_gaussians, 2)
            loss = (extras["roughness"] - 0.8).square().mean() + out.sh.square().mean() + out.means.square().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        report = kernels.path_report()
    if compiled:  # the compiled kernels ran (the inference-only ones decline while gradients are on)
        assert report["sparse_interpolate_fast"]["compiled"] > 0 and report["sparse_interpolate_fast"]["torch"] == 0
    else:
        assert all(p["compiled"] == 0 for p in report.values()), report
    return {n: p.detach().clone() for n, p in av.named_parameters()}


def test_a_toy_property_trains_through_both_paths(parts, monkeypatch):
    if kernels.numba is None:
        pytest.skip("numba missing: only the torch path exists")
    before = {n: p.detach().clone() for n, p in make(parts).named_parameters()}
    fast = _train_two_steps(parts, True, monkeypatch)
    slow = _train_two_steps(parts, False, monkeypatch)
    for n in ("roughness_bias", "roughness_basis"):
        assert not torch.equal(fast[n], before[n]), n  # it trained
    for n in fast:
        torch.testing.assert_close(fast[n], slow[n], rtol=1e-4, atol=1e-6, msg=n)


@pytest.mark.parametrize("variant", ["ours", "nrfgca_dagger"])
def test_the_compiled_inference_pass_gives_the_toy_property_too(parts, monkeypatch, variant):
    """Inference on CPU packs the bases (the toy's columns after the SH) and takes one compiled pass; the same
    numbers as the torch path. The UV decoder head grows two output channels for it."""
    av = make(parts, variant).eval()
    pose, rr, rt, face, lat = make_inputs(parts)
    with torch.no_grad():
        with monkeypatch.context() as m:
            m.setattr(kernels, "numba", None)
            want_out, want = av.evaluate(pose, rr, rt, face, lat)
        kernels.reset_paths()
        assert av.pack_bases_() == (variant == "ours")  # the UV decoder has no bases to pack
        got_out, got = av.evaluate(pose, rr, rt, face, lat)
    if variant == "ours":
        assert kernels.path_report()["interpolated_deltas_fast"]["compiled"] == 1
    else:
        assert av.pose_head.split_sizes[-1] == 2  # position, scale, rotation, sh0, sh bands, roughness
    torch.testing.assert_close(got["roughness"], want["roughness"], rtol=1e-5, atol=1e-6)
    for a, b in zip(got_out, want_out):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=2e-6)


def test_bad_tables_are_refused():
    with pytest.raises(ValueError, match="unique"):
        check_table((*GAUSSIAN_PROPERTIES, GAUSSIAN_PROPERTIES[1]))
    with pytest.raises(ValueError, match="neither a bias nor a basis"):
        check_table((GaussianProperty("x", (1,), None, None, None, None, None),))
    with pytest.raises(ValueError, match="learning-rate"):
        check_table((GaussianProperty("x", (1,), None, "x_bias", None, None, None),))


def test_optimiser_state_resumes_by_group_name():
    """A checkpoint's AdamW state lands on the parameters of the same group names, whatever their order now,
    and a group added since starts without state (runs/checkpoint.py)."""
    a, b, c = (torch.nn.Parameter(torch.randn(n)) for n in (2, 3, 4))
    old = torch.optim.AdamW([{"name": "a", "params": [a]}, {"name": "b", "params": [b]}], lr=0.1)
    (a.square().sum() + 2 * b.sum()).backward()
    old.step()
    saved = old.state_dict()
    new = torch.optim.AdamW(
        [{"name": "c", "params": [c]}, {"name": "b", "params": [b]}, {"name": "a", "params": [a]}], lr=0.1
    )
    load_optimizer_by_group_name(new, saved, "latest.pt")
    assert torch.equal(new.state[a]["exp_avg"], old.state[a]["exp_avg"])
    assert torch.equal(new.state[b]["exp_avg"], old.state[b]["exp_avg"])
    assert c not in new.state or not new.state[c]
    wrong = torch.optim.AdamW([{"name": "a", "params": [a, c]}, {"name": "b", "params": [b]}], lr=0.1)
    with pytest.raises(SchemaError, match=r"optimizer\.a"):
        load_optimizer_by_group_name(wrong, saved, "latest.pt")
