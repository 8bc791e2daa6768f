"""A run's configuration (``RUN/config.json`` ``"train"``): typed dataclasses with one docstring per
field, named presets, and its strict JSON reader.

It lives below :mod:`gsavatar.train` because a run is read by more than the trainer: run loading and
driving (:mod:`gsavatar.runs.load`, :mod:`gsavatar.drive`) rebuild the model from it.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import tyro

from gsavatar.metrics.lpips import LPIPSMode
from gsavatar.models.config import ModelConfig, PresetName, VariantName, model_preset, variant_config
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import config_to_json, is_int, is_number


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


VaeNoise = Literal["never", "correctives"]
"""``Schedule.vae_noise_step`` values that are not a step: ``never`` (deterministic latents ``mu``) and
``correctives`` (from the step the correctives start, the paper's)."""


@dataclass(frozen=True)
class Schedule:
    """When things happen during training. ``None`` = the preset's value (:data:`PRESET_SCHEDULES`); a run's
    ``config.json`` holds the resolved schedule (:func:`resolve`)."""

    steps: Annotated[int | None, tyro.conf.arg(aliases=("--steps",))] = None
    """Optimisation steps."""
    batch_size: Annotated[int | None, tyro.conf.arg(aliases=("--batch-size",))] = None
    """Views (frame, camera pairs) per step over all ranks."""
    image_scale: Annotated[float | None, tyro.conf.arg(aliases=("--image-scale",))] = None
    """Image downscale factor for training and evaluation (1 = full size)."""
    correctives_step: Annotated[int | None, tyro.conf.arg(aliases=("--correctives-step",))] = None
    """Step from which the MLP correctives are applied (paper 500)."""
    checkpoint_every: Annotated[int | None, tyro.conf.arg(aliases=("--checkpoint-every",))] = None
    """Steps between checkpoints."""
    basis_lr_scale: Annotated[float | None, tyro.conf.arg(aliases=("--basis-lr-scale",))] = None
    """Multiplier of the corrective bases' learning rates (30 on CPU presets, 1 = the paper's). The bases start
    at zero and Adam moves them by ~lr per step: at the paper's 1e-4 an SH0 basis needs ~2k steps to express a
    0.1 colour change, 20x the CPU budget's corrective steps."""
    vae_noise_step: Annotated[int | VaeNoise | None, tyro.conf.arg(aliases=("--vae-noise-step",))] = None
    """Step from which latents are sampled with the VAE noise and the KL applies; ``never``: deterministic
    latents ``mu``; ``correctives``: with the correctives. Paper preset: ``correctives``; CPU presets: ``never``
    (docs/train.md)."""
    sh_increase_fraction: float = 0.6
    """SH degree goes 0 -> max after this fraction of the steps (paper: 60k of 100k)."""

    def resolved(self) -> bool:
        """True when no field is left to the preset."""
        return all(getattr(self, f.name) is not None for f in fields(self))


@dataclass
class TrainConfig:
    """One training run: data, model, schedule, losses and the machinery, a tree of typed configs (every field
    settable from ``avatar-train avatar``: ``--model.latent-sh0``, ``--schedule.correctives-step``, ...)."""

    dataset: Path
    """Prepared dataset (``avatar-prep all``)."""
    out: Path
    """Run directory: checkpoints, config.json, metrics, renders."""
    preset: PresetName = "tiny"
    """Model and schedule size: tiny (tests, <2 min CPU), small (demo, minutes on CPU), paper (GPU). The named
    default instance the ``model`` and ``schedule`` fields start from."""
    variant: VariantName = "ours"
    """Model variant: ``ours`` or one of the paper's ablations and baselines, a name of the table
    :data:`gsavatar.models.config.VARIANTS` (the choices ``--help`` lists)."""
    model: Annotated[ModelConfig | None, tyro.conf.AvoidSubcommands] = None
    """The avatar's hyper-parameters; ``None`` = the preset's model with the variant applied (:func:`model_config`;
    on the command line the flags start from that instance)."""
    schedule: Schedule = field(default_factory=Schedule)
    """Steps, batch, image scale and when correctives, VAE noise and SH bands start."""
    losses: LossWeights = field(default_factory=LossWeights)
    """Loss weights (defaults: the paper's)."""
    texture_source: Literal["projected", "gt"] = "projected"
    """Encoder input: the prepared projected texture, or (synthetic captures) the ground-truth albedo in
    ``capture/gt/textures``: the oracle run, which bounds what the latent path can do."""
    cache_views: bool = True
    """Keep decoded training views and textures in memory (float16) when they fit in ``cache_max_gb``."""
    cache_max_gb: float = 4.0
    """Memory budget of the view cache; views past it are decoded every time."""
    lpips: LPIPSMode = "auto"
    """Perceptual loss: ``auto`` = on when training on CUDA, off on CPU (ST-LPIPS AlexNet costs ~2 s per
    256^2 view forward+backward on 2 cores, more than the rest of a step). ``off`` also drops the metric."""
    lpips_weights: Path | None = None
    """Standard LPIPS weights, when you have them (see gsavatar.metrics.lpips)."""
    background: Literal["random", "black", "white"] = "random"
    """Background composited behind the ground truth and the render during training."""
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
    max_steps_this_run: int | None = None
    """Stop after this many steps in this invocation (``None`` = run to the end); for tests of resuming."""


PRESET_SCHEDULES: dict[str, Schedule] = {
    "tiny": Schedule(
        steps=150,
        batch_size=2,
        image_scale=1.0,
        correctives_step=30,
        checkpoint_every=50,
        basis_lr_scale=30.0,
        vae_noise_step="never",
    ),
    "small": Schedule(
        steps=1200,
        batch_size=2,
        image_scale=1.0,
        correctives_step=200,
        checkpoint_every=200,
        basis_lr_scale=30.0,
        vae_noise_step="never",
    ),
    "paper": Schedule(
        steps=100_000,
        batch_size=64,
        image_scale=1.0,
        correctives_step=500,
        checkpoint_every=2000,
        basis_lr_scale=1.0,
        vae_noise_step="correctives",
    ),
}
"""The named schedules (presets' default instances); the paper trains 100k steps at batch 64 on 8 GPUs."""


def preset_config(dataset: Path, out: Path, preset: PresetName = "tiny", variant: VariantName = "ours", **kw):
    """The preset's default instance with every model and schedule field spelt out (what ``avatar-train
    avatar --preset P --variant V`` starts from, so ``--help`` shows the values that apply)."""
    base = TrainConfig(dataset=dataset, out=out, preset=preset, variant=variant, **kw)
    return dataclasses.replace(base, model=model_config(base), schedule=PRESET_SCHEDULES[preset])


def resolve(cfg: TrainConfig) -> TrainConfig:
    """Fill what is left to the preset: ``model`` (the preset's with the variant) and every ``None`` of the
    schedule; ``vae_noise_step="correctives"`` becomes the correctives step."""
    p = PRESET_SCHEDULES[cfg.preset]
    s = cfg.schedule
    vals = {f.name: getattr(p, f.name) if getattr(s, f.name) is None else getattr(s, f.name) for f in fields(s)}
    if vals["vae_noise_step"] == "correctives":
        vals["vae_noise_step"] = vals["correctives_step"]
    return dataclasses.replace(cfg, model=model_config(cfg), schedule=Schedule(**vals))


def model_config(cfg: TrainConfig) -> ModelConfig:
    """The model configuration of a run: its own (``cfg.model``) or its preset with its variant applied."""
    return cfg.model if cfg.model is not None else variant_config(model_preset(cfg.preset), cfg.variant)


def model_config_from_json(d: dict, file: str | Path) -> ModelConfig:
    """The model configuration a run was trained with, from its ``config.json`` ``model`` object: fields
    added since then take their defaults (which keep the old behaviour), so a run keeps loading after a
    preset changes (e.g. the CPU recipe). Raises SchemaError(file, ``model...``) on unknown or bad fields."""
    return read_config(ModelConfig, d, file, "model", unknown="error")


def check_train_config(cfg: TrainConfig) -> None:
    """Refuse counts and scales the trainer cannot use, before anything is loaded or written (``None`` = the
    preset's value). Raises ValueError naming the field."""
    s = cfg.schedule
    minimum = {
        "schedule.steps": (s.steps, 1),
        "schedule.batch_size": (s.batch_size, 1),
        "schedule.checkpoint_every": (s.checkpoint_every, 1),
        "schedule.correctives_step": (s.correctives_step, 0),
        "max_steps_this_run": (cfg.max_steps_this_run, 1),
        "num_workers": (cfg.num_workers, 0),
        "log_every": (cfg.log_every, 1),
        "eval_frames": (cfg.eval_frames, 1),
    }
    for name, (v, lo) in minimum.items():
        if v is not None and (not is_int(v) or v < lo):
            raise ValueError(f"{name} must be an integer >= {lo}, got {v!r}")
    for name, v in (("schedule.image_scale", s.image_scale), ("schedule.basis_lr_scale", s.basis_lr_scale)):
        if v is not None and not (is_number(v) and np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be > 0, got {v!r}")
    v = s.vae_noise_step
    if v is not None and v not in typing.get_args(VaeNoise) and (not is_int(v) or v < 0):
        raise ValueError(f"schedule.vae_noise_step must be a step >= 0, 'never' or 'correctives', got {v!r}")
    if not (np.isfinite(cfg.cache_max_gb) and cfg.cache_max_gb >= 0):
        raise ValueError(f"cache_max_gb must be >= 0, got {cfg.cache_max_gb!r}")
    if not 0 <= s.sh_increase_fraction <= 1:
        raise ValueError(f"schedule.sh_increase_fraction must be in [0, 1], got {s.sh_increase_fraction!r}")


def to_json(cfg: TrainConfig) -> dict:
    """Plain-JSON form (``config.json`` ``"train"`` of a run; :func:`from_json` reads it back). The model is
    written beside it, as the file's ``"model"`` (what resuming checks against the checkpoint)."""
    return config_to_json(cfg, exclude=("model",))


OLD_SCHEDULE_FIELDS = {
    # flat field of config.json "train" before the schedule was a subtree -> its "preset" and "never" sentinels
    "steps": (0, None),
    "batch_size": (0, None),
    "image_scale": (0, None),
    "correctives_step": (-1, None),
    "checkpoint_every": (0, None),
    "basis_lr_scale": (0, None),
    "vae_noise_step": (-2, -1),
    "sh_increase_fraction": (None, None),
}


def upgrade_train_json(d: dict) -> dict:
    """``config.json`` ``"train"`` of any earlier version in today's layout: the flat schedule fields (with 0 /
    -1 / -2 for "the preset's" and -1 for "never") become the ``schedule`` subtree with ``None`` / ``"never"``,
    ``max_steps_this_run`` 0 becomes ``None``. Today's layout is returned unchanged."""
    if not isinstance(d, dict) or not any(k in d for k in OLD_SCHEDULE_FIELDS):
        return d
    d = dict(d)
    sched = dict(d.get("schedule") or {}) if isinstance(d.get("schedule"), dict) else {}
    for k, (preset, never) in OLD_SCHEDULE_FIELDS.items():
        if k not in d:
            continue
        v = d.pop(k)
        if preset is not None and v == preset and not isinstance(v, bool):
            v = None
        elif never is not None and v == never and not isinstance(v, bool):
            v = "never"
        sched[k] = v
    d["schedule"] = sched
    if d.get("max_steps_this_run") == 0 and not isinstance(d.get("max_steps_this_run"), bool):
        d["max_steps_this_run"] = None
    return d


def upgrade_run_json(saved: dict) -> dict:
    """A whole ``config.json`` (or a checkpoint's copy of it) with its ``"train"`` in today's layout
    (:func:`upgrade_train_json`), so resuming compares like with like."""
    if isinstance(saved, dict) and isinstance(saved.get("train"), dict):
        return {**saved, "train": upgrade_train_json(saved["train"])}
    return saved


def from_json(d: dict, file: str | Path, prefix: str = "train", model: dict | None = None) -> TrainConfig:
    """Inverse of :func:`to_json` for a config read back from a run's ``config.json`` of this or an earlier
    version (:func:`upgrade_train_json`): every field is type-checked against its annotation by the one generic
    reader (:func:`read_config`); ``model`` is the file's ``"model"`` object (None: the preset's). Raises
    SchemaError(file, ``prefix.field``)."""
    cfg = read_config(TrainConfig, upgrade_train_json(d), file, prefix)
    return cfg if model is None else dataclasses.replace(cfg, model=model_config_from_json(model, file))


def read_config(cls, d, file: str | Path, prefix: str, unknown: Literal["ignore", "error"] = "ignore"):
    """A config dataclass from its JSON form (:func:`gsavatar.utils.jsonio.config_to_json`), recursively: each
    field converted and checked against its annotation (nested dataclasses, ``X | None``, Literal, tuples,
    paths, numbers that are not bools); a field the JSON lacks takes its default (so fields added since keep
    older files loading), a required one is an error; unknown keys are ignored (fields an older version had)
    or, with ``unknown="error"``, refused (a newer writer). The class's own checks run (``__post_init__``).
    Raises SchemaError(file, ``prefix.field``)."""
    if not isinstance(d, dict):
        raise SchemaError(file, prefix, f"expected an object, got {type(d).__name__}")
    names = {f.name for f in fields(cls)}
    extra = sorted(set(d) - names)
    if extra and unknown == "error":
        raise SchemaError(file, f"{prefix}.{extra[0]}", "unknown field (a newer gsavatar wrote this file?)")
    hints = typing.get_type_hints(cls)
    kwargs: dict = {}
    for f in fields(cls):
        if f.name not in d:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise SchemaError(file, f"{prefix}.{f.name}", "missing")
            continue
        kwargs[f.name] = _typed(d[f.name], hints[f.name], file, f"{prefix}.{f.name}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise SchemaError(file, prefix, str(e)) from None


def _typed(v, hint, file: str | Path, field: str):
    """``v`` converted to ``hint`` (Path, Path | None, int, float, bool, str, Literal, ``tuple[X, ...]`` from a
    JSON list); SchemaError otherwise."""
    args = typing.get_args(hint)
    if dataclasses.is_dataclass(hint):
        return read_config(hint, v, file, field)
    if typing.get_origin(hint) is tuple:
        if not isinstance(v, list):
            raise SchemaError(file, field, f"expected a list, got {v!r}"[:200])
        return tuple(_typed(x, args[0], file, f"{field}[{i}]") for i, x in enumerate(v))
    if typing.get_origin(hint) is Literal:
        if v not in args or isinstance(v, bool):
            raise SchemaError(file, field, f"expected one of {list(args)}, got {v!r}")
        return v
    if type(None) in args:  # Optional[...]
        if v is None:
            return None
        rest = tuple(a for a in args if a is not type(None))
        return _typed(v, rest[0] if len(rest) == 1 else typing.Union[rest], file, field)  # noqa: UP007
    if typing.get_origin(hint) in (typing.Union, types.UnionType):  # e.g. int | Literal["never"]: the first fit
        for a in args:
            try:
                return _typed(v, a, file, field)
            except SchemaError:
                continue
        raise SchemaError(file, field, f"expected {hint}, got {v!r}"[:200])
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
