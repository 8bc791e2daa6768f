"""LPIPS / ST-LPIPS: weight loading, metric properties, gradients, converter."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from gsavatar.metrics import lpips as lp
from gsavatar.metrics.lpips import (
    LPIPS,
    CHANNELS,
    FeatureTrunk,
    LPIPSWeightsError,
    convert_official_lpips,
    stlpips_weights_path,
)


def _have_stlpips() -> bool:
    try:
        stlpips_weights_path("alex")
        stlpips_weights_path("vgg")
    except LPIPSWeightsError:
        return False
    return True


needs_st = pytest.mark.skipif(
    not _have_stlpips(), reason="ST-LPIPS weights missing: pip install --no-deps stlpips-pytorch==0.0.2"
)


def _smooth_image(H=64, W=64) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
    img = torch.stack([xx, yy, 0.5 + 0.5 * torch.sin(10 * xx * yy) * torch.cos(7 * yy)])
    return img[None]  # [1, 3, H, W] in [0, 1]


@pytest.fixture(scope="module")
def alex() -> LPIPS:
    if not _have_stlpips():
        pytest.skip("ST-LPIPS weights missing")
    return LPIPS("alex")


@pytest.fixture(scope="module")
def vgg() -> LPIPS:
    if not _have_stlpips():
        pytest.skip("ST-LPIPS weights missing")
    return LPIPS("vgg")


# ------------------------------------------------------------------ loading


@needs_st
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_stlpips_weights_load_strict(net):
    sd = torch.load(stlpips_weights_path(net), map_location="cpu", weights_only=True)
    m = LPIPS(net)
    assert m.variant == "shift_tolerant"
    assert set(m.state_dict()) == set(sd)
    res = m.load_state_dict(sd, strict=True)
    assert not res.missing_keys and not res.unexpected_keys
    for k, v in sd.items():
        assert torch.equal(m.state_dict()[k], v), k
    assert m.lpips_name.startswith(f"ST-LPIPS {net} (stlpips-pytorch")
    assert "0.0.2" in m.lpips_name or "unknown" in m.lpips_name


@needs_st
def test_module_is_frozen_and_stays_eval(alex):
    assert all(not p.requires_grad for p in alex.parameters())
    alex.train()
    assert not alex.training and all(not mod.training for mod in alex.modules())


# ---------------------------------------------------------------- properties


@needs_st
@pytest.mark.parametrize("which", ["alex", "vgg"])
def test_identity_is_zero_and_noise_is_monotonic(which, request):
    m = request.getfixturevalue(which)
    x = _smooth_image()
    g = torch.Generator().manual_seed(0)
    noise = torch.randn(x.shape, generator=g)
    with torch.no_grad():
        d0 = m(x, x)
        assert d0.shape == (1,)
        assert d0.abs().item() < 1e-6
        ds = [m((x + s * noise).clamp(0, 1), x).item() for s in (0.01, 0.03, 0.1, 0.3)]
    assert all(a < b for a, b in zip(ds, ds[1:])), ds
    assert 0 < ds[0] and ds[-1] < 2


@needs_st
def test_batch_elements_are_independent(alex):
    x = _smooth_image()
    g = torch.Generator().manual_seed(1)
    y = (x + 0.1 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    with torch.no_grad():
        both = alex(torch.cat([x, y]), torch.cat([y, y]))
        single = alex(x, y)
    assert both.shape == (2,)
    assert both[0].item() == pytest.approx(single.item(), rel=1e-5)
    assert abs(both[1].item()) < 1e-6


@needs_st
@pytest.mark.parametrize("which", ["alex", "vgg"])
def test_shift_tolerance(which, request):
    """ST-LPIPS is (by design) far less sensitive to a 1-px shift than to mild noise."""
    m = request.getfixturevalue(which)
    x = _smooth_image(64, 65)
    a, b = x[..., 1:], x[..., :-1]
    g = torch.Generator().manual_seed(2)
    with torch.no_grad():
        d_shift = m(a, b).item()
        d_noise = m((a + 0.03 * torch.randn(a.shape, generator=g)).clamp(0, 1), a).item()
    assert d_shift < d_noise / 5, (d_shift, d_noise)


@needs_st
def test_gradients_finite_including_dead_relu_regions(alex):
    x = _smooth_image().repeat(2, 1, 1, 1)
    x[1] = 0.0  # black image: whole ReLU maps are zero -> norm has a kink at 0
    g = torch.Generator().manual_seed(3)
    y = (x + 0.05 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    for pred, gt in ((y, x), (x, y), (x, x)):
        p = pred.clone().requires_grad_(True)
        alex(p, gt).sum().backward()
        assert torch.isfinite(p.grad).all()
    p = y.clone().requires_grad_(True)
    alex(p, x).mean().backward()
    assert p.grad.abs().sum() > 0
    assert all(q.grad is None for q in alex.parameters())


@needs_st
def test_matches_functional_reference_forward(alex):
    """Independent functional re-statement of ST-LPIPS alex (per image, unbatched,
    lpips' normalize_tensor and a 1x1 conv for the lin layer) from the raw weights."""
    sd = torch.load(stlpips_weights_path("alex"), map_location="cpu", weights_only=True)

    def blur(h, f):
        return F.conv2d(F.pad(h, (2, 2, 2, 2), mode="reflect"), f, stride=2, groups=h.shape[1])

    def feats(x01):
        x = (2 * x01 - 1 - sd["scaling_layer.shift"]) / sd["scaling_layer.scale"]
        h = F.conv2d(x, sd["net.slice1.0.weight"], sd["net.slice1.0.bias"], stride=1, padding=2)
        r1 = F.relu(blur(h, sd["net.slice1.1.filt"]))
        h = blur(F.max_pool2d(r1, 3, 1), sd["net.slice2.4.filt"])
        r2 = F.relu(F.conv2d(h, sd["net.slice2.5.weight"], sd["net.slice2.5.bias"], padding=2))
        h = blur(F.max_pool2d(r2, 3, 1), sd["net.slice3.8.filt"])
        r3 = F.relu(F.conv2d(h, sd["net.slice3.9.weight"], sd["net.slice3.9.bias"], padding=1))
        r4 = F.relu(F.conv2d(r3, sd["net.slice4.11.weight"], sd["net.slice4.11.bias"], padding=1))
        r5 = F.relu(F.conv2d(r4, sd["net.slice5.13.weight"], sd["net.slice5.13.bias"], padding=1))
        return [r1, r2, r3, r4, r5]

    def ref(a, b):
        out = 0.0
        for i, (fa, fb) in enumerate(zip(feats(a), feats(b))):
            na = fa / (torch.sqrt((fa**2).sum(1, keepdim=True)) + 1e-10)
            nb = fb / (torch.sqrt((fb**2).sum(1, keepdim=True)) + 1e-10)
            out = out + F.conv2d((na - nb) ** 2, sd[f"lin{i}.model.1.weight"]).mean((2, 3))
        return out.flatten()

    x = _smooth_image(45, 52)
    g = torch.Generator().manual_seed(4)
    y = (x + 0.1 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    with torch.no_grad():
        assert alex(y, x).item() == pytest.approx(ref(y, x).item(), rel=1e-4)


@needs_st
def test_rejects_bad_inputs(alex):
    x = _smooth_image()
    with pytest.raises(ValueError, match="pred"):
        alex(x[:, :2], x[:, :2])
    with pytest.raises(ValueError, match="gt"):
        alex(x, x[..., :-1])
    small = _smooth_image(alex.min_size - 1, 40)
    with pytest.raises(ValueError, match="H, W >="):
        alex(small, small)
    ok = _smooth_image(alex.min_size, alex.min_size)
    with torch.no_grad():
        assert torch.isfinite(alex(ok, ok)).all()


@pytest.mark.parametrize("net", ["alex", "vgg"])
@pytest.mark.parametrize("variant", ["vanilla", "shift_tolerant"])
def test_trunks_accept_min_size(net, variant):
    t = FeatureTrunk(net, variant)
    s = lp.MIN_SIZE[(net, variant)]
    with torch.no_grad():
        outs = t(torch.rand(1, 3, s, s + 3))
    assert [o.shape[1] for o in outs] == list(CHANNELS[net])


# ------------------------------------------------------- official LPIPS files


def _fake_official_files(tmp_path: Path, net: str) -> tuple[Path, Path]:
    """A torchvision-layout trunk (features.{i}.*, plus classifier.*) and an lpips lin file."""
    g = torch.Generator().manual_seed(0)
    trunk = FeatureTrunk(net, "vanilla")
    tv = {}
    for k, v in trunk.state_dict().items():
        _, idx, kind = k.split(".")  # slice{k}.{i}.{weight|bias}
        tv[f"features.{idx}.{kind}"] = 0.05 * torch.randn(v.shape, generator=g)
    tv["classifier.1.weight"] = torch.randn(10, 4, generator=g)
    lin = {f"lin{i}.model.1.weight": torch.rand(1, c, 1, 1, generator=g) for i, c in enumerate(CHANNELS[net])}
    torch.save(tv, tmp_path / f"{net}_trunk.pth")
    torch.save(lin, tmp_path / f"{net}_lin.pth")
    return tmp_path / f"{net}_trunk.pth", tmp_path / f"{net}_lin.pth"


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_convert_official_lpips_roundtrip(tmp_path, net):
    trunk_p, lin_p = _fake_official_files(tmp_path, net)
    out = convert_official_lpips(net, trunk_p, lin_p, tmp_path / "combined.pth")
    m = LPIPS(net, weights=out)
    assert m.variant == "vanilla"
    assert m.lpips_name == f"LPIPS v0.1 {net} (weights: combined.pth)"
    tv = torch.load(trunk_p, weights_only=True)
    sd = m.state_dict()
    first_conv = "net.slice1.0.weight"
    assert torch.equal(sd[first_conv], tv["features.0.weight"])
    last = max(int(k.split(".")[1]) for k in tv if k.startswith("features."))
    assert torch.equal(sd[f"net.slice5.{last}.weight"], tv[f"features.{last}.weight"])
    m2 = LPIPS.from_official(net, trunk=trunk_p, lin=lin_p)
    assert "LPIPS v0.1" in m2.lpips_name and "lin: " in m2.lpips_name
    x = _smooth_image(40, 40)
    y = (x + 0.1).clamp(0, 1)
    with torch.no_grad():
        assert m(x, x).abs().item() < 1e-6
        assert m(x, y).item() == pytest.approx(m2(x, y).item(), rel=1e-6)


def test_variant_mismatch_and_bad_files(tmp_path):
    trunk_p, lin_p = _fake_official_files(tmp_path, "alex")
    out = convert_official_lpips("alex", trunk_p, lin_p, tmp_path / "a.pth")
    with pytest.raises(ValueError, match="variant"):
        LPIPS("alex", weights=out, variant="shift_tolerant")
    with pytest.raises(LPIPSWeightsError, match="do not fit"):
        LPIPS("vgg", weights=out)  # alex weights into a vgg trunk
    with pytest.raises(LPIPSWeightsError, match="do not fit"):
        LPIPS("alex", weights=trunk_p)  # un-converted torchvision file
    with pytest.raises(LPIPSWeightsError, match="not found"):
        LPIPS("alex", weights=tmp_path / "missing.pth")
    with pytest.raises(ValueError, match="net"):
        LPIPS("squeeze")  # type: ignore[arg-type]


def test_clear_error_without_any_weights(monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        lp.importlib.util, "find_spec", lambda name, *a: None if name == lp.STLPIPS_PACKAGE else real(name, *a)
    )
    with pytest.raises(LPIPSWeightsError, match="pip install --no-deps stlpips-pytorch"):
        LPIPS("alex")
    with pytest.raises(ValueError, match="vanilla"):
        LPIPS("alex", variant="vanilla")


# ------------------------------------------------------------------ a command's --lpips


def test_load_lpips_modes(tmp_path):
    """The one helper behind ``--lpips auto|on|off`` (training loss, run evaluation, avatar-drive)."""
    missing = tmp_path / "missing.pth"
    assert lp.load_lpips("off", "cpu", missing) == (None, "off")  # nothing is loaded
    assert lp.load_lpips("auto", "cpu", missing, auto_on=False) == (None, "off")  # training on CPU
    assert lp.load_lpips("auto", "cpu", missing, fallback=True) == (None, "off (unavailable: LPIPSWeightsError)")
    for mode in ("on", "auto"):  # refused, naming the option and why (exit 2 in a CLI)
        with pytest.raises(ValueError, match=f"lpips={mode} but the LPIPS network cannot be loaded: .*not found"):
            lp.load_lpips(mode, "cpu", missing, fallback=mode == "on")  # fallback is for auto only
    with pytest.raises(ValueError, match="'auto', 'on' or 'off'"):
        lp.load_lpips("yes", "cpu")  # type: ignore[arg-type]


@needs_st
def test_load_lpips_builds_the_network():
    got = lp.load_lpips("on", "cpu")
    assert isinstance(got.net, LPIPS) and got.name == got.net.lpips_name == LPIPS().lpips_name
    assert lp.load_lpips("auto", "cpu", auto_on=True).name == got.name
