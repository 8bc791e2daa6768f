"""LPIPS (Zhang et al. 2018) and ST-LPIPS (Ghildyal & Liu 2022), no torchvision.

The perceptual distance between images ``x0`` and ``x1`` is

    d(x0, x1) = sum_l  mean_{h,w}  w_l . (n(F_l(s(x0))) - n(F_l(s(x1))))^2

with ``s`` LPIPS' ScalingLayer (an ImageNet-like shift/scale of [-1, 1] inputs),
``F_l`` the l-th ReLU feature map of a frozen AlexNet / VGG16 trunk, ``n`` the
unit normalisation over channels and ``w_l`` the non-negative 1x1 "lin" weights.

Two trunk variants are implemented as plain ``nn.Sequential`` modules:

* ``"vanilla"``: torchvision's ``alexnet().features`` / ``vgg16().features``,
  layer for layer (same indices), i.e. the trunk of the official ``lpips``
  package (``lpips.LPIPS(net='alex'|'vgg', version='0.1')``).
* ``"shift_tolerant"``: ST-LPIPS' anti-aliased trunks (``stlpips-pytorch``,
  ``variant='shift_tolerant'``): strided convs / max-pools replaced by stride-1
  ops followed by :class:`BlurPool2d` (3x3 binomial [1,2,1]^2/16 filter,
  reflection pad 2, stride 2). AlexNet's first conv runs at stride 1, so the
  ST AlexNet is ~16x more expensive than vanilla AlexNet at the first layer.

State-dict layout (same as the ``lpips`` / ``stlpips`` packages' ``LPIPS``
module, so their files load with ``strict=True``)::

    scaling_layer.shift               [1, 3, 1, 1]  (-.030, -.088, -.188)
    scaling_layer.scale               [1, 3, 1, 1]  (.458, .448, .450)
    net.slice{k}.{i}.weight / .bias   conv of torchvision ``features[i]`` (vanilla)
                                      or of ST-LPIPS' feature list (shift_tolerant)
    net.slice{k}.{i}.filt             [C, 1, 3, 3] blur filter (shift_tolerant only)
    lin{l}.model.1.weight             [1, C_l, 1, 1]   (l = 0..4)

Vanilla slice boundaries (torchvision feature indices):
    alex: [0,2) [2,5) [5,8) [8,10) [10,12)     vgg: [0,4) [4,9) [9,16) [16,23) [23,30)

Weights are never downloaded here. Sources, in order:

1. ``LPIPS(net, weights=path)``: a state dict in the layout above, e.g. a file
   written by :func:`convert_official_lpips` from the official LPIPS lin file
   (``lpips/weights/v0.1/{alex,vgg}.pth``, keys ``lin{l}.model.1.weight``) and a
   torchvision trunk (``alexnet-owt-7be5be79.pth`` / ``vgg16-397923af.pth``,
   keys ``features.{i}.weight``), or an ST-LPIPS ``*_shift_tolerant.pth``.
2. ``LPIPS.from_official(net, trunk=..., lin=...)``: the same, without writing a file.
3. ``LPIPS(net)``: ST-LPIPS weights shipped in the ``stlpips-pytorch`` wheel
   (``pip install --no-deps stlpips-pytorch==0.0.2``; only its ``.pth`` files are
   read, its python modules are never imported because they need torchvision).

Every instance exposes ``lpips_name`` for reports: ST-LPIPS and LPIPS values are
*not* interchangeable (different trunks and lin weights), so always report which.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Literal, NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

NetName = Literal["alex", "vgg"]
Variant = Literal["vanilla", "shift_tolerant"]

# LPIPS ScalingLayer constants (applied to inputs in [-1, 1]).
LPIPS_SHIFT = (-0.030, -0.088, -0.188)
LPIPS_SCALE = (0.458, 0.448, 0.450)
# lpips.normalize_tensor's epsilon (added to the channel norm).
NORM_EPS = 1e-10

STLPIPS_PACKAGE = "stlpips_pytorch"
STLPIPS_DIST = "stlpips-pytorch"
STLPIPS_PIP = "pip install --no-deps stlpips-pytorch==0.0.2"

CHANNELS: dict[str, tuple[int, ...]] = {
    "alex": (64, 192, 384, 256, 256),
    "vgg": (64, 128, 256, 512, 512),
}

# Smallest H, W accepted (smaller inputs make a reflection pad or pooling fail).
MIN_SIZE: dict[tuple[str, str], int] = {
    ("alex", "vanilla"): 31,
    ("alex", "shift_tolerant"): 21,
    ("vgg", "vanilla"): 16,
    ("vgg", "shift_tolerant"): 18,
}

VANILLA_SLICES: dict[str, tuple[tuple[int, int], ...]] = {
    "alex": ((0, 2), (2, 5), (5, 8), (8, 10), (10, 12)),
    "vgg": ((0, 4), (4, 9), (9, 16), (16, 23), (23, 30)),
}


class LPIPSWeightsError(RuntimeError):
    """No usable LPIPS weights (missing package/file or incompatible state dict)."""


# --------------------------------------------------------------------------- math


def scale_inputs(x01: Tensor, shift: Tensor, scale: Tensor) -> Tensor:
    """[0, 1] image -> LPIPS trunk input: ``((2 x - 1) - shift) / scale``.

    Args:
        x01: Tensor  # [B, 3, H, W] in [0, 1]
        shift: Tensor  # [1, 3, 1, 1]
        scale: Tensor  # [1, 3, 1, 1]

    Returns:
        Tensor  # [B, 3, H, W]
    """
    return (2.0 * x01 - 1.0 - shift) / scale


def unit_normalize(feat: Tensor, eps: float = NORM_EPS) -> Tensor:
    """Divide each pixel's feature vector by its L2 norm (``lpips.normalize_tensor``).

    Uses ``torch.linalg.vector_norm`` whose gradient at an all-zero vector is 0
    (``sqrt(sum x^2)`` would give NaN there), so gradients stay finite even where
    a ReLU map is zero in every channel; the forward value is identical.

    Args:
        feat: Tensor  # [B, C, H, W]

    Returns:
        Tensor  # [B, C, H, W], unit norm over C (or 0 where feat is 0)
    """
    return feat / (torch.linalg.vector_norm(feat, dim=1, keepdim=True) + eps)


def layer_distance(f0: Tensor, f1: Tensor, lin_weight: Tensor) -> Tensor:
    """One LPIPS layer term: spatial mean of ``w . (n(f0) - n(f1))^2``.

    Args:
        f0: Tensor  # [B, C, h, w] trunk features of image 0
        f1: Tensor  # [B, C, h, w] trunk features of image 1
        lin_weight: Tensor  # [1, C, 1, 1] lin (1x1 conv) weights

    Returns:
        Tensor  # [B]
    """
    diff = (unit_normalize(f0) - unit_normalize(f1)).square()  # [B, C, h, w]
    return (diff * lin_weight).sum(1).mean((1, 2))


# --------------------------------------------------------------------- modules


def binomial_filter(channels: int) -> Tensor:
    """3x3 binomial blur ``[1,2,1]^T [1,2,1] / 16`` repeated per channel.

    Returns:
        Tensor  # [channels, 1, 3, 3]
    """
    a = torch.tensor([1.0, 2.0, 1.0])
    f = a[:, None] * a[None, :]
    return (f / f.sum())[None, None].repeat(channels, 1, 1, 1)


class BlurPool2d(nn.Module):
    """Anti-aliased stride-2 downsampling (Zhang 2019), as ST-LPIPS uses it.

    Reflection-pads by ``pad`` on each side, then a depthwise 3x3 binomial blur with
    stride 2. ST-LPIPS uses ``pad_more=True`` -> pad 2 (= filt_size - 1); the
    anti-aliased-CNN default is pad 1. The filter is a persistent buffer named
    ``filt`` so ST-LPIPS state dicts load strictly.
    """

    def __init__(self, channels: int, pad: int = 2) -> None:
        super().__init__()
        self.pad = pad
        self.register_buffer("filt", binomial_filter(channels))

    def forward(self, x: Tensor) -> Tensor:  # [B, C, H, W] -> [B, C, ~(H + 2 pad - 1) / 2, ...]
        x = F.pad(x, (self.pad,) * 4, mode="reflect")
        return F.conv2d(x, self.filt, stride=2, groups=x.shape[1])

    def extra_repr(self) -> str:
        return f"channels={self.filt.shape[0]}, pad={self.pad}, stride=2"


def _relu() -> nn.ReLU:
    # inplace like torchvision: every ReLU output is a slice output or feeds a
    # conv/pool, never a tensor autograd still needs.
    return nn.ReLU(inplace=True)


def _alex_layers(variant: Variant) -> tuple[list[nn.Module], tuple[tuple[int, int], ...]]:
    if variant == "vanilla":  # torchvision alexnet().features
        layers: list[nn.Module] = [
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2),
            _relu(),  # 0, 1
            nn.MaxPool2d(kernel_size=3, stride=2),  # 2
            nn.Conv2d(64, 192, kernel_size=5, padding=2),
            _relu(),  # 3, 4
            nn.MaxPool2d(kernel_size=3, stride=2),  # 5
            nn.Conv2d(192, 384, kernel_size=3, padding=1),
            _relu(),  # 6, 7
            nn.Conv2d(384, 256, kernel_size=3, padding=1),
            _relu(),  # 8, 9
            nn.Conv2d(256, 256, kernel_size=3, padding=1),
            _relu(),  # 10, 11
        ]  # (12: final MaxPool, unused by LPIPS)
        return layers, VANILLA_SLICES["alex"]
    # ST-LPIPS invariant_networks.alexnet(variant='shift_tolerant', filter_size=3)
    layers = [
        nn.Conv2d(3, 64, kernel_size=11, stride=1, padding=2),  # 0
        BlurPool2d(64),
        _relu(),  # 1, 2
        nn.MaxPool2d(kernel_size=3, stride=1),
        BlurPool2d(64),  # 3, 4
        nn.Conv2d(64, 192, kernel_size=5, padding=2),
        _relu(),  # 5, 6
        nn.MaxPool2d(kernel_size=3, stride=1),
        BlurPool2d(192),  # 7, 8
        nn.Conv2d(192, 384, kernel_size=3, padding=1),
        _relu(),  # 9, 10
        nn.Conv2d(384, 256, kernel_size=3, padding=1),
        _relu(),  # 11, 12
        nn.Conv2d(256, 256, kernel_size=3, padding=1),
        _relu(),  # 13, 14
    ]  # (15, 16: final MaxPool + BlurPool, unused)
    return layers, ((0, 3), (3, 7), (7, 11), (11, 13), (13, 15))


def _vgg_layers(variant: Variant) -> tuple[list[nn.Module], tuple[tuple[int, int], ...]]:
    # VGG16 configuration "D" up to relu5_3; 'M' = pooling stage.
    cfg: list[int | str] = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    layers: list[nn.Module] = []
    c_in = 3
    for v in cfg:
        if v == "M":
            if variant == "vanilla":
                layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
            else:  # ST-LPIPS models_lpf.vgg16(filter_size=3, pad_more=True)
                layers += [nn.MaxPool2d(kernel_size=2, stride=1), BlurPool2d(c_in)]
        else:
            assert isinstance(v, int)
            layers += [nn.Conv2d(c_in, v, kernel_size=3, padding=1), _relu()]
            c_in = v
    if variant == "vanilla":
        return layers, VANILLA_SLICES["vgg"]
    return layers, ((0, 4), (4, 10), (10, 18), (18, 26), (26, 34))


class FeatureTrunk(nn.Module):
    """AlexNet / VGG16 feature extractor returning the 5 LPIPS feature maps.

    Children ``slice1..slice5`` are ``nn.Sequential`` whose sub-module names are
    the *global* feature indices (``slice2.3`` = ``features[3]``), as in lpips.
    """

    def __init__(self, net: NetName, variant: Variant) -> None:
        super().__init__()
        layers, bounds = _alex_layers(variant) if net == "alex" else _vgg_layers(variant)
        for k, (a, b) in enumerate(bounds, start=1):
            seq = nn.Sequential()
            for i in range(a, b):
                seq.add_module(str(i), layers[i])
            self.add_module(f"slice{k}", seq)
        self.n_slices = len(bounds)

    def forward(self, x: Tensor) -> list[Tensor]:
        """x: [B, 3, H, W] scaled input -> 5 maps [B, C_l, h_l, w_l] (post-ReLU)."""
        feats = []
        for k in range(1, self.n_slices + 1):
            x = getattr(self, f"slice{k}")(x)
            feats.append(x)
        return feats


class ScalingLayer(nn.Module):
    """LPIPS input normalisation; buffers ``shift``/``scale`` [1, 3, 1, 1]."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("shift", torch.tensor(LPIPS_SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(LPIPS_SCALE)[None, :, None, None])

    def forward(self, x01: Tensor) -> Tensor:  # [B, 3, H, W] in [0, 1]
        return scale_inputs(x01, self.shift, self.scale)


class LinLayer(nn.Module):
    """1x1 conv C -> 1, no bias. ``model.0`` is a placeholder for lpips' Dropout
    (inactive at eval) so the weight key stays ``model.1.weight``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Identity(), nn.Conv2d(channels, 1, 1, bias=False))

    @property
    def weight(self) -> Tensor:  # [1, C, 1, 1]
        return self.model[1].weight


# ---------------------------------------------------------------- weight files


def stlpips_weights_path(net: NetName) -> Path:
    """Path of ``{net}_shift_tolerant.pth`` inside the installed ``stlpips-pytorch``.

    Raises:
        LPIPSWeightsError: package not installed or file missing.
    """
    spec = importlib.util.find_spec(STLPIPS_PACKAGE)  # locates, does not import
    if spec is None or not spec.submodule_search_locations:
        raise LPIPSWeightsError(
            "No LPIPS weights available: pass weights=<file> (see "
            "gsavatar.metrics.lpips.convert_official_lpips for the official LPIPS "
            "v0.1 lin file + torchvision trunk), or install the ST-LPIPS weights "
            f"with `{STLPIPS_PIP}` (--no-deps: its torchvision dependency would "
            "pull a CUDA torch; only its .pth files are used)."
        )
    for loc in spec.submodule_search_locations:
        p = Path(loc) / "weights" / "vST0.0" / f"{net}_shift_tolerant.pth"
        if p.is_file():
            return p
    raise LPIPSWeightsError(
        f"{STLPIPS_DIST} is installed but has no weights/vST0.0/{net}_shift_tolerant.pth "
        f"under {list(spec.submodule_search_locations)}; reinstall with `{STLPIPS_PIP}`."
    )


def _stlpips_version() -> str:
    try:
        return importlib.metadata.version(STLPIPS_DIST)
    except importlib.metadata.PackageNotFoundError:
        return "unknown version"


def _load_file(path: Path) -> dict[str, Tensor]:
    if not path.is_file():
        raise LPIPSWeightsError(f"LPIPS weights file not found: {path}")
    sd = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(sd, Mapping) and "state_dict" in sd and isinstance(sd["state_dict"], Mapping):
        sd = sd["state_dict"]
    if not isinstance(sd, Mapping) or not all(isinstance(v, Tensor) for v in sd.values()):
        raise LPIPSWeightsError(f"{path} is not a state dict of tensors")
    return dict(sd)


def infer_variant(state_dict: Mapping[str, Tensor]) -> Variant:
    """``"shift_tolerant"`` when the state dict holds BlurPool ``.filt`` buffers."""
    return "shift_tolerant" if any(k.endswith(".filt") for k in state_dict) else "vanilla"


_TRUNK_KEY = re.compile(r"^(?:module\.)?(?:features|(?:net\.)?slice\d+)\.(\d+)\.(weight|bias)$")
_LIN_KEY = re.compile(r"^(?:module\.)?(?:lin|lins\.)(\d+)\.model\.1\.weight$")


def official_lpips_state_dict(
    net: NetName, trunk: Mapping[str, Tensor], lin: Mapping[str, Tensor]
) -> dict[str, Tensor]:
    """Assemble a vanilla-LPIPS state dict (layout in the module docstring).

    Args:
        net: "alex" or "vgg"
        trunk: torchvision ``alexnet``/``vgg16`` state dict (keys ``features.{i}.weight|bias``;
            ``classifier.*`` is ignored) or an lpips trunk (``[net.]slice{k}.{i}.*``).
        lin: official LPIPS lin file (``weights/v0.1/{net}.pth``: keys
            ``lin{l}.model.1.weight`` [1, C_l, 1, 1]; ``lins.{l}.model.1.weight`` also accepted).

    Returns:
        dict[str, Tensor] loadable by ``LPIPS(net, weights=..., variant="vanilla")``.
    """
    if net not in CHANNELS:
        raise ValueError(f"net must be one of {sorted(CHANNELS)}, got {net!r}")
    bounds = VANILLA_SLICES[net]
    out: dict[str, Tensor] = {
        "scaling_layer.shift": torch.tensor(LPIPS_SHIFT)[None, :, None, None],
        "scaling_layer.scale": torch.tensor(LPIPS_SCALE)[None, :, None, None],
    }
    for key, val in trunk.items():
        m = _TRUNK_KEY.match(key)
        if m is None:
            continue  # classifier.*, num_batches_tracked, ...
        idx, kind = int(m.group(1)), m.group(2)
        k = next((s for s, (a, b) in enumerate(bounds, start=1) if a <= idx < b), None)
        if k is None:
            continue  # feature layers past relu5 (none have weights in alex/vgg16)
        out[f"net.slice{k}.{idx}.{kind}"] = val
    n_lin = 0
    for key, val in lin.items():
        m = _LIN_KEY.match(key)
        if m is not None:
            out[f"lin{int(m.group(1))}.model.1.weight"] = val
            n_lin += 1
    if n_lin != len(CHANNELS[net]):
        raise LPIPSWeightsError(
            f"lin state dict: expected {len(CHANNELS[net])} keys 'lin{{l}}.model.1.weight', "
            f"found {n_lin} among {sorted(lin)[:8]}"
        )
    return out


def convert_official_lpips(net: NetName, trunk_path: str | Path, lin_path: str | Path, out_path: str | Path) -> Path:
    """Write one combined LPIPS weights file from the official pieces.

    Example::

        # lin: https://github.com/richzhang/PerceptualSimilarity/blob/master/lpips/weights/v0.1/alex.pth
        # trunk: https://download.pytorch.org/models/alexnet-owt-7be5be79.pth
        convert_official_lpips("alex", "alexnet-owt-7be5be79.pth", "alex.pth", "lpips_alex_v0.1.pth")
        LPIPS("alex", weights="lpips_alex_v0.1.pth")

    The result is checked by a strict load into :class:`LPIPS` before saving.
    """
    sd = official_lpips_state_dict(net, _load_file(Path(trunk_path)), _load_file(Path(lin_path)))
    LPIPS(net, weights=sd, variant="vanilla")  # strict-load check
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(sd, out)
    return out


# ----------------------------------------------------------------------- LPIPS


class LPIPS(nn.Module):
    """Frozen LPIPS / ST-LPIPS distance; ``forward(pred, gt) -> [B]``.

    Inputs are images in [0, 1] (mapped to [-1, 1] inside). Parameters never
    require grad and the module stays in eval mode (``.train()`` is a no-op), but
    the output is differentiable w.r.t. the inputs, so it can serve as a loss.

    Args:
        net: trunk, "alex" or "vgg".
        weights: ``None`` -> ST-LPIPS weights from the ``stlpips-pytorch`` wheel;
            a path to a state-dict file, or a state-dict mapping, in the layout of
            the module docstring (see :func:`convert_official_lpips`).
        variant: trunk architecture; ``None`` infers it (``shift_tolerant`` if the
            state dict has BlurPool ``.filt`` buffers, else ``vanilla``). Giving a
            variant that the weights do not fit raises.
        name: overrides the auto-generated :attr:`lpips_name`.

    Attributes:
        lpips_name: human-readable description of metric + weights for reports,
            e.g. ``"ST-LPIPS alex (stlpips-pytorch 0.0.2 weights)"``.
        net_name, variant, weights_source.
    """

    def __init__(
        self,
        net: NetName = "alex",
        weights: str | Path | Mapping[str, Tensor] | None = None,
        variant: Variant | None = None,
        name: str | None = None,
    ) -> None:
        super().__init__()
        if net not in CHANNELS:
            raise ValueError(f"net must be one of {sorted(CHANNELS)}, got {net!r}")
        if variant not in (None, "vanilla", "shift_tolerant"):
            raise ValueError(f"variant must be None, 'vanilla' or 'shift_tolerant', got {variant!r}")

        if weights is None:
            if variant == "vanilla":
                raise ValueError(
                    "variant='vanilla' needs weights=<file> (official LPIPS lin + torchvision "
                    "trunk, see convert_official_lpips); the bundled fallback is ST-LPIPS only"
                )
            path = stlpips_weights_path(net)
            sd = _load_file(path)
            source = str(path)
            auto_name = f"ST-LPIPS {net} ({STLPIPS_DIST} {_stlpips_version()} weights)"
        elif isinstance(weights, Mapping):
            sd = dict(weights)
            source = "<state dict>"
            auto_name = None
        else:
            path = Path(weights)
            sd = _load_file(path)
            source = str(path)
            auto_name = None

        found = infer_variant(sd)
        if variant is not None and variant != found:
            raise ValueError(f"variant={variant!r} but the weights from {source} are for a {found!r} trunk")
        self.net_name: NetName = net
        self.variant: Variant = found
        self.weights_source = source
        if auto_name is None:
            kind = "ST-LPIPS" if found == "shift_tolerant" else "LPIPS v0.1"
            auto_name = f"{kind} {net} (weights: {Path(source).name})"
        self.lpips_name = name or auto_name

        self.scaling_layer = ScalingLayer()
        self.net = FeatureTrunk(net, found)
        for i, c in enumerate(CHANNELS[net]):
            self.add_module(f"lin{i}", LinLayer(c))

        own = self.state_dict()
        missing = sorted(set(own) - set(sd))
        unexpected = sorted(set(sd) - set(own))
        wrong = sorted(k for k in set(own) & set(sd) if own[k].shape != sd[k].shape)
        if missing or unexpected or wrong:

            def _few(keys: list[str]) -> str:
                return f"{keys[:5]}{' ...' if len(keys) > 5 else ''}"

            raise LPIPSWeightsError(
                f"LPIPS {net}/{found} weights from {source} do not fit: missing {_few(missing)}, "
                f"unexpected {_few(unexpected)}, wrong shape {_few(wrong)}. Official LPIPS pieces "
                "(torchvision trunk + lin file) must be combined with convert_official_lpips()."
            )
        self.load_state_dict(sd, strict=True)
        for p in self.parameters():
            p.requires_grad_(False)
        super().train(False)

    @classmethod
    def from_official(cls, net: NetName, trunk: str | Path, lin: str | Path, name: str | None = None) -> LPIPS:
        """Vanilla LPIPS from a torchvision trunk file + official LPIPS v0.1 lin file."""
        sd = official_lpips_state_dict(net, _load_file(Path(trunk)), _load_file(Path(lin)))
        auto = f"LPIPS v0.1 {net} (lin: {Path(lin).name}, trunk: {Path(trunk).name})"
        return cls(net, weights=sd, variant="vanilla", name=name or auto)

    def train(self, mode: bool = True) -> LPIPS:
        """No-op: the metric always stays in eval mode."""
        return super().train(False)

    @property
    def min_size(self) -> int:
        """Smallest accepted image height/width."""
        return MIN_SIZE[(self.net_name, self.variant)]

    @property
    def lin_weights(self) -> list[Tensor]:
        """5 tensors [1, C_l, 1, 1]."""
        return [getattr(self, f"lin{i}").weight for i in range(len(CHANNELS[self.net_name]))]

    def _check(self, pred: Tensor, gt: Tensor) -> None:
        if pred.ndim != 4 or pred.shape[1] != 3:
            raise ValueError(f"pred must be [B, 3, H, W], got {tuple(pred.shape)}")
        if gt.shape != pred.shape:
            raise ValueError(f"gt must match pred's shape {tuple(pred.shape)}, got {tuple(gt.shape)}")
        h, w = pred.shape[-2:]
        if min(h, w) < self.min_size:
            raise ValueError(f"{self.lpips_name} needs H, W >= {self.min_size}, got H={h}, W={w}")

    def layer_distances(self, pred: Tensor, gt: Tensor) -> Tensor:
        """Per-layer LPIPS terms.

        Args:
            pred: Tensor  # [B, 3, H, W] in [0, 1]
            gt: Tensor  # [B, 3, H, W] in [0, 1]

        Returns:
            Tensor  # [B, 5] in the module's dtype (float32 unless converted);
            # the sum over the last dim is the LPIPS distance
        """
        self._check(pred, gt)
        B = pred.shape[0]
        dtype = self.scaling_layer.shift.dtype  # inputs follow the module's dtype (differentiable cast)
        # one trunk pass over both images (batched)
        x = self.scaling_layer(torch.cat([pred, gt], 0).to(dtype))  # [2B, 3, H, W]
        feats = self.net(x)
        return torch.stack([layer_distance(f[:B], f[B:], w) for f, w in zip(feats, self.lin_weights)], dim=1)

    def forward(self, pred: Tensor, gt: Tensor) -> Tensor:
        """LPIPS distance per image.

        Args:
            pred: Tensor  # [B, 3, H, W] in [0, 1]
            gt: Tensor  # [B, 3, H, W] in [0, 1]

        Returns:
            Tensor  # [B], >= 0 (0 for identical inputs); use ``.mean()`` as a loss
        """
        return self.layer_distances(pred, gt).sum(1)

    def extra_repr(self) -> str:
        return f"lpips_name={self.lpips_name!r}"


# ----------------------------------------------------------------------- a command's --lpips

LPIPSMode = Literal["auto", "on", "off"]
"""A command's ``--lpips``: ``on`` requires the network, ``off`` skips it, ``auto`` is up to the command
(:func:`load_lpips`)."""


class LoadedLPIPS(NamedTuple):
    net: LPIPS | None
    """The network on the requested device; None when off or unavailable."""
    name: str
    """What to report next to the scores: ``net.lpips_name``, ``off`` or ``off (unavailable: <error type>)``."""


def load_lpips(
    mode: LPIPSMode,
    device: torch.device | str,
    weights: str | Path | None = None,
    *,
    auto_on: bool = True,
    fallback: bool = False,
) -> LoadedLPIPS:
    """The LPIPS network a command's ``--lpips mode`` asks for: the one place the commands build it.

    ``off``: none. ``on``: ``LPIPS(weights=weights)`` on ``device``; ValueError naming the option when it
    cannot be loaded (no ``stlpips-pytorch`` wheel, a missing or unfitting ``weights`` file). ``auto``: as
    ``on`` if ``auto_on`` (the command's condition), else none; with ``fallback`` a network that cannot be
    loaded is skipped (named ``off (unavailable: ...)``) instead of refused. The commands: the training loss
    passes ``auto_on`` = training on CUDA (on CPU it costs more than the rest of a step); a run's
    evaluation uses it unless ``off``; ``avatar-drive`` passes ``fallback=True`` (its metric is optional).
    """
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"lpips must be 'auto', 'on' or 'off', got {mode!r}")
    if mode == "off" or (mode == "auto" and not auto_on):
        return LoadedLPIPS(None, "off")
    try:
        net = LPIPS(weights=weights).to(device)
    except Exception as e:  # noqa: BLE001 - missing weights wheel, unreadable or unfitting file
        if mode == "auto" and fallback:
            return LoadedLPIPS(None, f"off (unavailable: {type(e).__name__})")
        raise ValueError(f"lpips={mode} but the LPIPS network cannot be loaded: {e}") from None
    return LoadedLPIPS(net, net.lpips_name)


__all__ = [
    "LPIPS",
    "BlurPool2d",
    "FeatureTrunk",
    "LPIPSMode",
    "LPIPSWeightsError",
    "LoadedLPIPS",
    "convert_official_lpips",
    "infer_variant",
    "load_lpips",
    "layer_distance",
    "official_lpips_state_dict",
    "scale_inputs",
    "stlpips_weights_path",
    "unit_normalize",
]
