"""A run's configuration (``RUN/config.json`` ``"train"``): typed dataclasses with one docstring per
field, named presets, and its strict JSON reader.

It lives below :mod:`gsavatar.train` because a run is read by more than the trainer: run loading and
driving (:mod:`gsavatar.runs.load`, :mod:`gsavatar.drive`) rebuild the model from it.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Literal

import numpy as np

from gsavatar.metrics.lpips import LPIPSMode
from gsavatar.models.config import ModelConfig, PresetName, VariantName, model_preset, variant_config
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import config_to_json, dataclass_defaults, is_int, is_number


@dataclass
class LossWeights:
    """Weights of the training loss terms (defaults: the paper's, Sec. 4 "Training Details")."""

    l1: float = 1.0
    """Photometric L1 between the rendered and the ground-truth image."""
    lpips: float = 0.1
    """Perceptual LPIPS distance (metric named by ``LPIPS.lpips_name``)."""
    opac: float = 0.5
    """Opacity regulariser: pushes accumulated alpha to 1 inside the eroded foreground mask."""
    scale: float = 1.0
    """Scale regulariser: penalises Gaussians whose largest axis exceeds a threshold."""
    cpt: float = 0.5
    """Control-point smoothness: displacement difference to the n (paper: 5) nearest control points."""
    kl: float = 1e-6
    """KL divergence of the appearance latent posterior to N(0, I)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not v >= 0:
                raise ValueError(f"LossWeights.{f.name} must be a number >= 0, got {v!r}")

    def as_dict(self) -> dict[str, float]:
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}


@dataclass
class TrainConfig:
    dataset: Path
    """Prepared dataset (``avatar-prep all``)."""
    out: Path
    """Run directory: checkpoints, config.json, metrics, renders."""
    preset: PresetName = "tiny"
    """Model and schedule size: tiny (tests, <2 min CPU), small (demo, minutes on CPU), paper (GPU)."""
    variant: VariantName = "ours"
    """Model variant: ``ours`` or one of the paper's ablations and baselines, a name of the table
    :data:`gsavatar.models.config.VARIANTS` (the choices ``--help`` lists)."""
    steps: int = 0
    """Optimisation steps (0 = preset)."""
    batch_size: int = 0
    """Views (frame, camera pairs) per step over all ranks (0 = preset)."""
    image_scale: float = 0.0
    """Image downscale factor for training and evaluation (0 = preset)."""
    sh_increase_fraction: float = 0.6
    """SH degree goes 0 -> max after this fraction of the steps (paper: 60k of 100k)."""
    correctives_step: int = -1
    """Step from which the MLP correctives are applied (-1 = preset; paper 500)."""
    basis_lr_scale: float = 0.0
    """Multiplier of the corrective bases' learning rates (0 = preset: 30 on CPU presets, 1 = the paper's).
    The bases start at zero and Adam moves them by ~lr per step: at the paper's 1e-4 an SH0 basis needs
    ~2k steps to express a 0.1 colour change, 20x the CPU budget's corrective steps."""
    vae_noise_step: int = -2
    """Step from which latents are sampled with the VAE noise and the KL applies (-2 = preset; -1 = never:
    deterministic latents ``mu``). Paper preset: with the correctives; CPU presets: never (docs/train.md)."""
    texture_source: Literal["projected", "gt"] = "projected"
    """Encoder input: the prepared projected texture, or (synthetic captures) the ground-truth albedo in
    ``capture/gt/textures``: the oracle run, which bounds what the latent path can do."""
    cache_views: bool = True
    """Keep decoded training views and textures in memory (float16) when they fit in ``cache_max_gb``."""
    cache_max_gb: float = 4.0
    """Memory budget of the view cache; views past it are decoded every time."""
    losses: LossWeights = field(default_factory=LossWeights)
    """Loss weights (defaults: the paper's)."""
    lpips: LPIPSMode = "auto"
    """Perceptual loss: ``auto`` = on when training on CUDA, off on CPU (ST-LPIPS AlexNet costs ~2 s per
    256^2 view forward+backward on 2 cores, more than the rest of a step). ``off`` also drops the metric."""
    lpips_weights: Path | None = None
    """Standard LPIPS weights, when you have them (see gsavatar.metrics.lpips)."""
    background: Literal["random", "black", "white"] = "random"
    """Background composited behind the ground truth and the render during training."""
    checkpoint_every: int = 0
    """Steps between checkpoints (0 = preset)."""
    log_every: int = 10
    """Steps between log lines."""
    eval_frames: int = 8
    """Training frames used to evaluate held-out cameras (evenly spaced)."""
    seed: int = 0
    """Seed of sampling, backgrounds, VAE noise and initialisation."""
    num_workers: int = 0
    """DataLoader worker processes (0 = load in the main process)."""
    device: str = "auto"
    """``auto`` (CUDA if available), ``cpu`` or ``cuda[:i]``."""
    backend: Literal["auto", "torch", "gsplat"] = "auto"
    """Rasterizer: gsplat on CUDA, our PyTorch compositor on CPU."""
    deterministic: bool = False
    """Single-threaded CPU kernels and deterministic algorithms, so a resumed run is bit-identical to an
    uninterrupted one (multi-threaded CPU reductions differ in the last bits, which AdamW's eps=1e-15
    amplifies for parameters with near-zero gradients)."""
    max_steps_this_run: int = 0
    """Stop after this many steps in this invocation (0 = run to the end); for tests of resuming."""


@dataclass(frozen=True)
class Schedule:
    steps: int
    batch_size: int
    image_scale: float
    correctives_step: int
    checkpoint_every: int
    basis_lr_scale: float = 1.0
    vae_noise_step: int | None = None  # None: the correctives step; -1: never


PRESET_SCHEDULES: dict[str, Schedule] = {
    "tiny": Schedule(
        steps=150,
        batch_size=2,
        image_scale=1.0,
        correctives_step=30,
        checkpoint_every=50,
        basis_lr_scale=30.0,
        vae_noise_step=-1,
    ),
    "small": Schedule(
        steps=1200,
        batch_size=2,
        image_scale=1.0,
        correctives_step=200,
        checkpoint_every=200,
        basis_lr_scale=30.0,
        vae_noise_step=-1,
    ),
    "paper": Schedule(steps=100_000, batch_size=64, image_scale=1.0, correctives_step=500, checkpoint_every=2000),
}
"""Schedules per preset; the paper trains 100k steps at batch 64 on 8 GPUs."""


def resolve(cfg: TrainConfig) -> TrainConfig:
    """Fill the preset's values into fields left at 0/-1."""
    s = PRESET_SCHEDULES[cfg.preset]
    correctives_step = s.correctives_step if cfg.correctives_step < 0 else cfg.correctives_step
    if cfg.vae_noise_step != -2:  # given
        vae_noise_step = cfg.vae_noise_step
    else:  # the preset's; None = with the correctives
        vae_noise_step = correctives_step if s.vae_noise_step is None else s.vae_noise_step
    return dataclasses.replace(
        cfg,
        steps=cfg.steps or s.steps,
        batch_size=cfg.batch_size or s.batch_size,
        image_scale=cfg.image_scale or s.image_scale,
        correctives_step=correctives_step,
        checkpoint_every=cfg.checkpoint_every or s.checkpoint_every,
        basis_lr_scale=cfg.basis_lr_scale or s.basis_lr_scale,
        vae_noise_step=vae_noise_step,
    )


def model_config(cfg: TrainConfig) -> ModelConfig:
    """The model configuration of a run: its preset with its variant applied."""
    return variant_config(model_preset(cfg.preset), cfg.variant)


def model_config_from_json(d: dict, file: str | Path) -> ModelConfig:
    """The model configuration a run was trained with, from its ``config.json`` ``model`` object: fields
    added since then take their defaults (which keep the old behaviour), so a run keeps loading after a
    preset changes (e.g. the CPU recipe). Raises SchemaError(file, ``model...``) on unknown or bad fields."""
    if not isinstance(d, dict):
        raise SchemaError(file, "model", f"expected an object, got {type(d).__name__}")
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise SchemaError(file, f"model.{unknown[0]}", "unknown field (a newer gsavatar wrote this run?)")
    hints = typing.get_type_hints(ModelConfig)  # typed like the train fields: "true" is no int, null no float
    typed = {k: _typed(v, hints[k], file, f"model.{k}") for k, v in d.items()}
    try:
        return ModelConfig(**{**dataclass_defaults(ModelConfig), **typed})
    except (TypeError, ValueError) as e:
        raise SchemaError(file, "model", str(e)) from None


def check_train_config(cfg: TrainConfig) -> None:
    """Refuse counts and scales the trainer cannot use (0 = the preset's value where allowed),
    before anything is loaded or written. Raises ValueError naming the field."""
    minimum = {
        "steps": 0,
        "batch_size": 0,
        "checkpoint_every": 0,
        "max_steps_this_run": 0,
        "num_workers": 0,
        "log_every": 1,
        "eval_frames": 1,
        "correctives_step": -1,
    }
    for name, lo in minimum.items():
        v = getattr(cfg, name)
        if not isinstance(v, int) or v < lo:
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    if not (np.isfinite(cfg.image_scale) and cfg.image_scale >= 0):
        raise ValueError(f"image_scale must be > 0 (or 0 = preset), got {cfg.image_scale!r}")
    if not (np.isfinite(cfg.basis_lr_scale) and cfg.basis_lr_scale >= 0):
        raise ValueError(f"basis_lr_scale must be > 0 (or 0 = preset), got {cfg.basis_lr_scale!r}")
    if not isinstance(cfg.vae_noise_step, int) or cfg.vae_noise_step < -2:
        raise ValueError(
            f"vae_noise_step must be an integer >= -2 (-2 = preset, -1 = never), got {cfg.vae_noise_step!r}"
        )
    if not (np.isfinite(cfg.cache_max_gb) and cfg.cache_max_gb >= 0):
        raise ValueError(f"cache_max_gb must be >= 0, got {cfg.cache_max_gb!r}")
    if not 0 <= cfg.sh_increase_fraction <= 1:
        raise ValueError(f"sh_increase_fraction must be in [0, 1], got {cfg.sh_increase_fraction!r}")


def to_json(cfg: TrainConfig) -> dict:
    """Plain-JSON form (``config.json`` of a run; :func:`from_json` reads it back)."""
    return config_to_json(cfg)


def from_json(d: dict, file: str | Path, prefix: str = "train") -> TrainConfig:
    """Inverse of :func:`to_json` for a config read back from a run's ``config.json``: every field of
    TrainConfig it holds is type-checked against the field's annotation (``true`` is not an int, a
    Literal must be one of its choices); unknown keys are ignored and ``losses`` keeps its default.
    Raises SchemaError(file, ``prefix.field``)."""
    if not isinstance(d, dict):
        raise SchemaError(file, prefix, f"expected an object, got {type(d).__name__}")
    hints = typing.get_type_hints(TrainConfig)
    kwargs: dict = {}
    for f in dataclasses.fields(TrainConfig):
        if f.name == "losses" or f.name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise SchemaError(file, f"{prefix}.{f.name}", "missing")
            continue
        kwargs[f.name] = _typed(d[f.name], hints[f.name], file, f"{prefix}.{f.name}")
    return TrainConfig(**kwargs)


def _typed(v, hint, file: str | Path, field: str):
    """``v`` converted to ``hint`` (Path, Path | None, int, float, bool, str, Literal, ``tuple[X, ...]`` from a
    JSON list); SchemaError otherwise."""
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        if not isinstance(v, list):
            raise SchemaError(file, field, f"expected a list, got {v!r}"[:200])
        return tuple(_typed(x, args[0], file, f"{field}[{i}]") for i, x in enumerate(v))
    if typing.get_origin(hint) is Literal:
        if v not in args or isinstance(v, bool):
            raise SchemaError(file, field, f"expected one of {list(args)}, got {v!r}")
        return v
    if type(None) in args:  # Optional[...]
        return None if v is None else _typed(v, next(a for a in args if a is not type(None)), file, field)
    ok = {
        Path: lambda x: isinstance(x, str) and x != "",
        int: is_int,
        float: is_number,
        bool: lambda x: isinstance(x, bool),
        str: lambda x: isinstance(x, str),
    }.get(hint)
    if ok is None:
        raise TypeError(f"{field}: no JSON reader for {hint}")
    if not ok(v):
        raise SchemaError(file, field, f"expected {getattr(hint, '__name__', hint)}, got {v!r}")
    return Path(v) if hint is Path else (float(v) if hint is float else v)
