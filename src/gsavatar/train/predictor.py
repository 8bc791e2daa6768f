"""Training the appearance predictor on an avatar run's encoder latents (paper section 3.4).

Targets: the run's encoder mean ``mu`` sampled at the anchor UVs, for every frame with
a projected texture (train and test), cached in ``RUN/predictor/targets.npz``.

One training sample is a window of ``T`` consecutive TRAIN frames ``s..s+T-1`` inside
one contiguous segment (``s`` >= segment start + 1, so frame ``s-1`` has a target). The
pose history of every frame is its ``N_b`` most recent frames, clamped at the segment
start (= repeating the first frame, like :meth:`AppearancePredictor.init_state`). The
predictor is unrolled over the window, feeding back its own (clamped) predictions;
the first step gets the target latents of ``s-1`` (GT-context pass) or the "zero" latents
(zero-context pass; :meth:`AppearancePredictor.zero_latents`: the training mean by default). Both passes run
as one doubled batch; their losses are summed:
per pass L1 on the latents + L1 on the velocity, acceleration and jerk (1st..3rd finite
differences over the unrolled window) against those of the targets, all weight 1.
The optional InitialLatentNet is trained alongside on random train frames (L1).
AdamW (lr 1e-3). Batches depend only on (seed, step), so a resumed run is identical.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from gsavatar.data_schema.prepared import ProjectedTextures
from gsavatar.geometry.lbs import KinematicChain
from gsavatar.models.predictor import (
    LEGACY_CONFIG,
    SELECTION_LR_SCALE,
    AppearancePredictor,
    PredictorConfig,
    PredictorEnsemble,
)
from gsavatar.runs.checkpoint import load_checkpoint, resume_hint, save_checkpoint
from gsavatar.runs.load import LoadedRun, load_run
from gsavatar.train.sampler import step_generator
from gsavatar.utils.cli import set_resume_hint
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_save_npz, atomic_write_json, read_npz
from gsavatar.utils.jsonio import config_to_json, dataclass_defaults, parse_json_text
from gsavatar.utils.outdir import claim_output_dir
from gsavatar.utils.provenance import code_version

TARGETS_FORMAT = "gsavatar-predictor-targets"


MEMBER_SEED_STRIDE = 1000
"""Member k of an ensemble trains from seed ``seed + MEMBER_SEED_STRIDE * k`` (k = 0: the predictor's own seed, so
a one-member ensemble is the single predictor; seeds 0, 1, 2 of a study share no member)."""


@dataclass
class PredictorTrainConfig:
    """Optimisation of the appearance predictor (model hyper-parameters in ``model``)."""

    steps: int = 2000
    """Optimisation steps."""
    batch_size: int = 8
    """Windows per step (each forwarded twice: GT and zero context)."""
    window: int = 16
    """Frames unrolled per window (shortened to the longest train segment - 1)."""
    lr: float = 1e-3
    """AdamW learning rate (paper: 1e-3)."""
    weight_decay: float = 1e-2
    """AdamW weight decay."""
    initial_weight: float = 1.0
    """Weight of the InitialLatentNet L1 loss (its parameters are disjoint from the predictor's)."""
    detach_feedback: bool = False
    """Stop gradients through the fed-back predictions (default: backprop through the unroll)."""
    feature_noise: float = 0.0
    """Std of Gaussian noise added, while training only, to the standardised pose-token features (values,
    velocities, accelerations of every slot; unit variance over the training windows), redrawn at every unroll
    step; 0 = none (the paper's). A predictor fit to a few hundred frames can tell every training frame apart by
    its exact pose window and memorise its latents; jittered inputs make nearby windows share one answer. Measured
    in docs/train.md."""
    context_noise: float = 0.0
    """Std of Gaussian noise added, while training only, to every previous-latents input of the unroll (the
    given context and each fed-back prediction), in units of the per-(anchor, dim) latent scale; 0 = none (the
    paper's). Trains the predictor to correct its own drift instead of trusting the latents fed back; measured in
    docs/train.md."""
    burn_in: int = 0
    """Frames the zero-context pass runs free, without gradients, before each window (beyond the paper; 0 = none,
    the paper's): it starts from the "zero" latents at frame ``s - burn_in`` (clamped at the segment start, where
    the pose window repeats the first frame as in driving) and feeds back its own predictions up to ``s - 1``, so the
    supervised window sees the latents a long free-running rollout produces instead of those of a fresh start
    (driving runs hundreds of frames, training windows a few). Measured in docs/train.md."""
    ema: float = 0.0
    """Decay of an exponential moving average of the weights, updated after every step (0 = none, the paper's). The
    average is what is evaluated, saved as the checkpoint's ``predictor`` and driven (the training weights are kept
    as ``predictor_train`` for resuming). The average starts at the initial weights (no warm-up correction): keep
    ``1 / (1 - ema)`` well below ``steps``. Measured worse than no average on `small` (docs/train.md); kept as an
    opt-in for longer trainings."""
    selection_lr_scale: float = SELECTION_LR_SCALE
    """Learning-rate multiplier of the signal readout's selection logits (``readout`` ``signals`` / ``both``; no
    weight decay on them): softmax logits that start uniform over ~120 tokens must move by several units to select
    a few; too fast and a selection saturates on the first correlated token it meets. Measured in docs/train.md."""
    signal_warmup_steps: int = 0
    """With ``model.readout = "both"``: the first this many steps train the signal readout alone (the transformer is
    skipped, the signals update the previous latents as ``readout = "signals"`` does), then both train together
    (``steps`` counts both phases; ``feature_noise`` perturbs the transformer's tokens, so it acts only after).
    Jointly from the start, the transformer fits the training sequence (it can tell
    every training window apart) before the selections have found the joints that drive the appearance, and the
    signals' gradient fades; a warm-up lets the selections settle first. 0 = joint from the start. Measured in
    docs/train.md."""
    seed: int = 0
    """Seed of initialisation and window sampling."""
    ensemble: int = 1
    """K: predictors trained side by side, member k from seed ``seed + 1000 k`` (its own initialisation and
    windows), averaged at every driving step (:class:`~gsavatar.models.predictor.PredictorEnsemble`); 1 = one
    predictor (the paper's). K times the training and predictor time; measured in docs/train.md."""
    parallel_members: bool = True
    """With ``ensemble`` > 1 and no more torch threads than members (the 2-core box): train the members side by side,
    one forked process of one thread each, between checkpoints, instead of one after the other in this process. The
    same optimisation (the members share nothing: their losses are summed and AdamW updates every parameter from its
    own gradient), so the same predictor up to float rounding, with the same checkpoints, logs and resuming; measured
    in docs/performance.md. Off (in this process) with ``ema`` > 0, dropout, or more threads than members."""
    checkpoint_every: int = 250
    """Steps between checkpoints (and at the end)."""
    log_every: int = 50
    """Steps between log lines."""
    max_steps_this_run: int | None = None
    """Stop after this many steps in this invocation (``None`` = run to the end); for tests of resuming."""
    model: PredictorConfig = field(default_factory=PredictorConfig)
    """Predictor hyper-parameters (``latent_dim`` is taken from the avatar run)."""


class TargetLatents(NamedTuple):
    latents: np.ndarray
    """Encoder mu sampled at the anchor UVs.  # [F, A, L] float32"""
    frames: np.ndarray
    """Capture frame of every row, ascending.  # [F] int64"""


class SequenceData(NamedTuple):
    """Per-frame driving inputs and targets, rows aligned and sorted by frame."""

    frames: Tensor  # [F] int64 capture frame index
    pose: Tensor  # [F, P]
    root_rotation: Tensor  # [F, 3]
    root_translation: Tensor  # [F, 3]
    latents: Tensor  # [F, A, L]


class DualLoss(NamedTuple):
    total: Tensor
    """gt + zero (scalar)."""
    gt: Tensor
    """Loss of the GT-context pass (scalar)."""
    zero: Tensor
    """Loss of the zero-context pass (scalar)."""
    logs: dict[str, float]


# ----------------------------------------------------------------------------- targets
def predictor_dir(run: Path, out: Path | None = None) -> Path:
    return Path(out) if out is not None else Path(run) / "predictor"


@torch.no_grad()
def extract_targets(
    run: Path, out: Path | None = None, device: str = "auto", batch_size: int = 8, loaded: LoadedRun | None = None
) -> TargetLatents:
    """Encoder latents of every textured frame, cached (keyed on the run's checkpoint step).

    ``loaded``: ``load_run(run)``'s result, to avoid reloading. -> TargetLatents
    """
    net, scene, _, step = loaded if loaded is not None else load_run(run, device)
    if net.encoder is None:
        raise ValueError(f"run {run} has no appearance encoder (variant without latents): nothing to predict")
    path = predictor_dir(run, out) / "targets.npz"
    textures = ProjectedTextures(scene.dataset)
    frames = np.asarray(textures.frames, dtype=np.int64)
    if path.exists():
        try:
            z = read_npz(path, keys=("header", "latents", "frames"))
            hdr = parse_json_text(str(z["header"]), path)
        except (SchemaError, KeyError):
            z, hdr = {}, None  # unreadable cache: extract again and overwrite it
        if (
            isinstance(hdr, dict)
            and hdr.get("format") == TARGETS_FORMAT
            and hdr.get("step") == step
            and "latents" in z
            and "frames" in z
            and np.array_equal(z["frames"], frames)
        ):
            return TargetLatents(z["latents"], z["frames"])
    dev = next(net.parameters()).device
    out_lat = []
    for i in range(0, len(frames), batch_size):
        tex = np.stack([textures.get(int(f)) for f in frames[i : i + batch_size]])
        tex = torch.from_numpy(tex).permute(0, 3, 1, 2).contiguous().to(dev)  # [b, 3, S, S]
        out_lat.append(net.latents(tex, None)[0].float().cpu().numpy())  # [b, A, L]
    lat = np.concatenate(out_lat).astype(np.float32)
    hdr = {"format": TARGETS_FORMAT, "step": step, "run": str(run)}
    atomic_save_npz(path, header=np.array(json.dumps(hdr)), latents=lat, frames=frames)
    return TargetLatents(lat, frames)


def sequence_data(motion, targets: TargetLatents, device: torch.device | str = "cpu") -> SequenceData:
    """Rows of ``targets`` with the capture's motion (``capture.motion``)."""
    f = torch.as_tensor(targets.frames, dtype=torch.long)
    t = lambda a: torch.as_tensor(np.asarray(a)[targets.frames], dtype=torch.float32, device=device)  # noqa: E731
    return SequenceData(
        f.to(device),
        t(motion.pose),
        t(motion.root_rotation),
        t(motion.root_translation),
        torch.as_tensor(targets.latents, dtype=torch.float32, device=device),
    )


def split_segments(frames: Tensor | np.ndarray, split_frames) -> list[tuple[int, int]]:
    """Maximal runs of rows whose frames are in ``split_frames`` and consecutive. -> [(start, end_excl)]"""
    frames = np.asarray(torch.as_tensor(frames).cpu())
    keep = np.isin(frames, np.asarray(list(split_frames)))
    segs, start = [], None
    for i in range(len(frames) + 1):
        cont = i < len(frames) and keep[i] and start is not None and frames[i] == frames[i - 1] + 1
        if start is not None and not cont:
            segs.append((start, i))
            start = None
        if start is None and i < len(frames) and keep[i]:
            start = i
    return segs


def history_index(rows: Tensor, seg_start: Tensor, history: int) -> Tensor:
    """Rows of the N_b-frame pose window ending at each row, clamped at its segment start.

    rows [...], seg_start [...] (broadcastable) -> [..., N_b]
    """
    off = torch.arange(history - 1, -1, -1, device=rows.device)
    return torch.maximum(rows[..., None] - off, seg_start[..., None])


class WindowSampler:
    """Uniform over all windows of ``T`` frames ``s..s+T-1`` inside a segment with ``s > start``."""

    def __init__(self, segments: list[tuple[int, int]], window: int) -> None:
        longest = max((e - s for s, e in segments), default=0)
        if longest < 2:
            raise ValueError(f"segments must contain a run of >= 2 consecutive frames, longest is {longest}")
        self.T = min(window, longest - 1)
        starts, seg = [], []
        for s, e in segments:
            for k in range(s + 1, e - self.T + 1):
                starts.append(k)
                seg.append(s)
        self.starts, self.seg = torch.tensor(starts), torch.tensor(seg)

    def sample(self, batch: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
        """-> rows [B, T], seg_start [B]"""
        i = torch.randint(len(self.starts), (batch,), generator=gen)
        return self.starts[i, None] + torch.arange(self.T), self.seg[i]


# ----------------------------------------------------------------------------- losses
def unroll(
    model: AppearancePredictor,
    data: SequenceData,
    rows: Tensor,
    seg_start: Tensor,
    ctx0: Tensor,
    detach_feedback: bool = False,
    context_noise: float = 0.0,
    gen: torch.Generator | None = None,
    feature_noise: float = 0.0,
) -> Tensor:
    """Autoregressive unroll over windows, feeding back the predictions.

    rows [B, T], seg_start [B], ctx0 [B, A, L] (previous latents of the first frame) -> [B, T, A, L].
    ``context_noise`` > 0: every previous-latents input gets ``context_noise * latent_scale * N(0, 1)``
    (drawn from ``gen``); the outputs themselves are not perturbed. ``feature_noise`` > 0: every step's
    standardised pose-token features get ``feature_noise * N(0, 1)`` (from ``gen``).
    """
    dev = data.pose.device
    hist = history_index(rows.to(dev), seg_start.to(dev)[:, None], model.config.window_frames)  # [B, T, W]
    pose, rr, rt = data.pose[hist], data.root_rotation[hist], data.root_translation[hist]
    prev, out = ctx0, []
    for k in range(rows.shape[1]):
        ctx = prev.detach() if detach_feedback and k else prev
        if context_noise > 0:
            eps = torch.randn(ctx.shape, generator=gen, device=gen.device if gen is not None else None)
            ctx = ctx + context_noise * model.latent_scale * eps.to(ctx)
        noise = None
        if feature_noise > 0:
            shape = (rows.shape[0], model.num_slots, model.feature_dim)
            eps = torch.randn(shape, generator=gen, device=gen.device if gen is not None else None)
            noise = feature_noise * eps.to(ctx)
        prev = model(pose[:, k], rr[:, k], rt[:, k], ctx, noise)
        out.append(prev)
    return torch.stack(out, 1)


def temporal_l1_terms(pred: Tensor, target: Tensor) -> dict[str, Tensor]:
    """L1 on values and on the 1st/2nd/3rd finite differences over time (where T allows).

    pred, target [B, T, A, L] -> {"l1", "vel", "acc", "jerk"} scalars
    """
    terms, p, t = {"l1": (pred - target).abs().mean()}, pred, target
    for name in ("vel", "acc", "jerk"):
        p, t = p[:, 1:] - p[:, :-1], t[:, 1:] - t[:, :-1]
        if p.shape[1] == 0:
            break
        terms[name] = (p - t).abs().mean()
    return terms


def dual_context_loss(
    model: AppearancePredictor,
    data: SequenceData,
    rows: Tensor,
    seg_start: Tensor,
    detach_feedback: bool = False,
    context_noise: float = 0.0,
    gen: torch.Generator | None = None,
    feature_noise: float = 0.0,
    burn_in: int = 0,
) -> DualLoss:
    """Unrolled losses of the GT-context and zero-context passes (one doubled batch), summed
    (``context_noise``, ``gen``, ``feature_noise``: see :func:`unroll`; ``burn_in``: the zero-context pass starts
    that many frames earlier, :func:`burn_in_context`)."""
    B = rows.shape[0]
    dev = data.latents.device
    rows = rows.to(dev)
    gt_prev = data.latents[rows[:, 0] - 1]  # [B, A, L]
    zero = model.zero_latents().to(gt_prev).expand_as(gt_prev)
    if burn_in > 0:
        zero = burn_in_context(model, data, rows[:, 0], seg_start, burn_in, zero)
    pred = unroll(
        model,
        data,
        rows.repeat(2, 1),
        seg_start.repeat(2),
        torch.cat([gt_prev, zero]),
        detach_feedback,
        context_noise,
        gen,
        feature_noise,
    )  # [2B, T, A, L]
    target = data.latents[rows]  # [B, T, A, L]
    tg, tz = temporal_l1_terms(pred[:B], target), temporal_l1_terms(pred[B:], target)
    gt, zero = sum(tg.values()), sum(tz.values())
    logs = {
        **{f"gt_{k}": float(v.detach()) for k, v in tg.items()},
        **{f"zero_{k}": float(v.detach()) for k, v in tz.items()},
    }
    return DualLoss(gt + zero, gt, zero, logs)


@torch.no_grad()
def burn_in_context(
    model: AppearancePredictor, data: SequenceData, first: Tensor, seg_start: Tensor, burn_in: int, ctx0: Tensor
) -> Tensor:
    """Previous latents of frame ``first`` after a free-running rollout from ``ctx0`` at ``first - burn_in``.

    The rollout's frames are clamped at the segment start (a window that starts there repeats the start frame,
    poses and all, like :meth:`AppearancePredictor.init_state`). No gradients flow through it.
    first [B], seg_start [B], ctx0 [B, A, L] -> [B, A, L]
    """
    dev = data.pose.device
    first, seg_start = first.to(dev), seg_start.to(dev)
    prefix = history_index(first - 1, seg_start, burn_in)  # frames first - burn_in .. first - 1, clamped
    return unroll(model, data, prefix, seg_start, ctx0)[:, -1]


def initial_loss(model: AppearancePredictor, data: SequenceData, rows: Tensor) -> Tensor:
    """L1 of the InitialLatentNet on frames ``rows`` [M] (0 without the net)."""
    if model.initial is None:
        return data.latents.new_zeros(())
    rows = rows.to(data.pose.device)
    return (model.initial_latents(data.pose[rows], trained_only=False) - data.latents[rows]).abs().mean()


# ----------------------------------------------------------------------------- model setup
def build_predictor(
    scene, config: PredictorConfig, latent_dim: int, avatar_pca: str = "local", seed: int = 0
) -> AppearancePredictor:
    """Predictor for a prepared scene: tokens for the slots active at >= 1 anchor, the avatar's pose PCA."""
    slots = np.flatnonzero(np.asarray(scene.masks.pose, bool).any(0))
    pca = {"local": scene.pca_local, "global": scene.pca_global, "global_test_only": scene.pca_global}.get(avatar_pca)
    pose_pca = None if pca is None else (pca.mean, pca.basis, pca.clamp_sigma * pca.sigma)
    cfg = dataclasses.replace(
        config,
        latent_dim=int(latent_dim),
        latent_pca_components=config.latent_pca_components
        if config.latent_pca == "global"
        else min(config.latent_pca_components, int(latent_dim)),
    )
    kin = KinematicChain.from_rig(scene.capture.rig) if cfg.needs_kinematics else None
    return AppearancePredictor(
        cfg, scene.hierarchy.num_anchors, slots, scene.capture.rig.pose_dim, pose_pca, seed, kinematics=kin
    )


@torch.no_grad()
def prepare_model(
    model: AppearancePredictor, data: SequenceData, segments: list[tuple[int, int]], chunk: int = 512
) -> dict:
    """Fit the input normalisation (all train frames' windows) and the latent PCA (train targets)."""
    rows = torch.cat([torch.arange(s, e) for s, e in segments]).to(data.pose.device)
    starts = torch.cat([torch.full((e - s,), s) for s, e in segments]).to(data.pose.device)
    hist = history_index(rows, starts, model.config.window_frames)  # [n, W]
    parts = [
        model.input_features(data.pose[h], data.root_rotation[h], data.root_translation[h]) for h in hist.split(chunk)
    ]
    joints = torch.cat([p[1] for p in parts]) if model.chain is not None else None
    model.fit_input_normalization(torch.cat([p[0] for p in parts]), joints)
    model.fit_latent_statistics(data.latents[rows])
    lat = data.latents[rows].double()
    total = float(((lat - lat.mean(0)) ** 2).sum())
    lost = float(((model.clamp_latents(data.latents[rows]).double() - lat) ** 2).sum())  # what the clamp removes
    return {"train_frames": int(len(rows)), "latent_pca_explained_variance": 1.0 - lost / total if total > 0 else 1.0}


# ----------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate_predictor(model: AppearancePredictor, data: SequenceData, segments: list[tuple[int, int]]) -> dict:
    """L1 to the encoder latents on frames 1.. of every segment (frame-weighted means).

    ``teacher_first``: frame 0 from the encoder, then free-running; ``zero_init`` /
    ``initial_net_init``: free-running from zeros / the InitialLatentNet; ``one_step``:
    GT previous latents at every frame. Baselines: zero latents, the per-anchor train
    mean, the clamp's floor |clamp(gt) - gt|, and the encoder itself (0).
    """
    was = model.training
    model.eval()
    acc: dict[str, float] = {}
    n = 0
    use_init = model.initial is not None and bool(model.initial_ready)
    for s, e in segments:
        if e - s < 2:
            continue
        P, R, Tr, gt = (x[s:e] for x in (data.pose, data.root_rotation, data.root_translation, data.latents))
        zeros = model.zero_latents().to(gt)
        runs = {
            "teacher_first": model.rollout(P, R, Tr, gt[0], first_is_given=True),
            "zero_init": model.rollout(P, R, Tr, zeros),
        }
        if use_init:
            runs["initial_net_init"] = model.rollout(P, R, Tr, None)
        rows = torch.arange(s + 1, e, device=gt.device)[:, None]
        one = unroll(model, data, rows, torch.full((e - s - 1,), s), data.latents[rows[:, 0] - 1])[:, 0]
        runs["one_step"] = torch.cat([gt[:1], one])
        runs["zero_latent_baseline"] = torch.zeros_like(gt)
        if bool(model.latent_pca_ready):
            runs["train_mean_baseline"] = model.latent_mean.expand_as(gt)
            runs["clamp_floor"] = model.clamp_latents(gt)
        for k, v in runs.items():
            acc[k] = acc.get(k, 0.0) + float((v[1:] - gt[1:]).abs().mean()) * (e - s - 1)
        n += e - s - 1
    out = {f"{k}_l1": v / max(n, 1) for k, v in acc.items()}
    out["encoder_l1"] = 0.0
    out["frames"] = n
    model.train(was)
    return out


# ----------------------------------------------------------------------------- trainer
def optimizer_groups(model: torch.nn.Module, lr: float, selection_lr_scale: float = SELECTION_LR_SCALE) -> list[dict]:
    """AdamW parameter groups: everything at ``lr``; the signal readout's selection logits (if any) at
    ``lr * selection_lr_scale`` without weight decay (one group, as before, for a model without them)."""
    named = list(model.named_parameters())
    sel = [p for n, p in named if n.split(".")[-1] == "selection_logits"]
    rest = [p for n, p in named if n.split(".")[-1] != "selection_logits"]
    if not sel:
        return [{"params": rest}]
    return [{"params": rest}, {"params": sel, "lr": lr * selection_lr_scale, "weight_decay": 0.0}]


class PredictorTrainer:
    """Loop, AdamW, logging and atomic resumable checkpoints in ``out`` (latest.pt, metrics.jsonl).

    Resuming checks the model config, seed, batch size, window and the avatar checkpoint step
    the targets came from (``extra_config["targets_step"]``): after the avatar trained further,
    delete ``latest.pt`` to retrain on the new latents.
    """

    def __init__(
        self,
        model: AppearancePredictor,
        data: SequenceData,
        train_segments: list[tuple[int, int]],
        cfg: PredictorTrainConfig,
        out: Path,
        extra_config: dict | None = None,
    ) -> None:
        if not (cfg.context_noise >= 0 and math.isfinite(cfg.context_noise)):
            raise ValueError(f"context_noise must be a finite number >= 0, got {cfg.context_noise}")
        if not (cfg.feature_noise >= 0 and math.isfinite(cfg.feature_noise)):
            raise ValueError(f"feature_noise must be a finite number >= 0, got {cfg.feature_noise}")
        if cfg.burn_in < 0:
            raise ValueError(f"burn_in must be >= 0, got {cfg.burn_in}")
        if not 0.0 <= cfg.ema < 1.0:
            raise ValueError(f"ema must be in [0, 1), got {cfg.ema}")
        self.members = list(model.members) if isinstance(model, PredictorEnsemble) else [model]
        if len(self.members) != cfg.ensemble:
            raise ValueError(f"ensemble = {cfg.ensemble} but the model has {len(self.members)} member(s)")
        self.model, self.data, self.cfg, self.out = model, data, cfg, Path(out)
        self.sampler = WindowSampler(train_segments, cfg.window)
        self.train_rows = torch.cat([torch.arange(s, e) for s, e in train_segments])
        if cfg.feature_noise > 0 and model.config.readout == "signals":
            raise ValueError("feature_noise perturbs the pose-token features, which readout='signals' does not have")
        if cfg.signal_warmup_steps < 0:
            raise ValueError(f"signal_warmup_steps must be >= 0, got {cfg.signal_warmup_steps}")
        if cfg.signal_warmup_steps > 0 and model.config.readout != "both":
            raise ValueError(
                f"signal_warmup_steps = {cfg.signal_warmup_steps} needs model.readout = 'both' (got "
                f"{model.config.readout!r}): it trains the signal readout alone before the transformer joins"
            )
        if not (cfg.selection_lr_scale > 0 and math.isfinite(cfg.selection_lr_scale)):
            raise ValueError(f"selection_lr_scale must be a finite number > 0, got {cfg.selection_lr_scale}")
        groups = optimizer_groups(model, cfg.lr, cfg.selection_lr_scale)
        self.optim = torch.optim.AdamW(groups, lr=cfg.lr, weight_decay=cfg.weight_decay)
        train = config_to_json(cfg, exclude=("model",))
        self.config = {
            "train": train,
            "model": model.config.to_json(),
            "pose_dim": model.pose_dim,
            "num_anchors": model.num_anchors,
            **({"ensemble": cfg.ensemble} if cfg.ensemble > 1 else {}),  # absent = one predictor (older checkpoints)
            **({"ema": cfg.ema} if cfg.ema > 0 else {}),  # absent = no weight average (older checkpoints)
            **(extra_config or {}),
        }
        self.ckpt = self.out / "latest.pt"
        self.step = 0
        # the weight average (cfg.ema > 0): a copy of the model whose parameters follow the training weights
        self.average = copy.deepcopy(model) if cfg.ema > 0 else None
        if self.ckpt.exists():
            state = load_checkpoint(
                self.ckpt,
                self.config,
                strict_config_keys=(
                    "model",
                    "ensemble",
                    "ema",
                    "num_anchors",
                    "pose_dim",
                    "targets_step",
                    "train.seed",
                    "train.batch_size",
                    "train.window",
                ),
                defaults={"model": {**dataclass_defaults(PredictorConfig), **LEGACY_CONFIG}},
            )
            if self.average is not None:
                self.average.load_state_dict(state["modules"]["predictor"])
                model.load_state_dict(state["modules"]["predictor_train"])
            else:
                model.load_state_dict(state["modules"]["predictor"])
            self.optim.load_state_dict(state["optimizer"])
            for g, want in zip(self.optim.param_groups, groups):  # this run's learning rates, not the saved ones
                g["lr"] = want.get("lr", cfg.lr)
            self.step = int(state["step"])

    @property
    def result(self) -> AppearancePredictor | PredictorEnsemble:
        """The predictor this training yields: the weight average with ``ema`` > 0, else the trained model."""
        return self.average if self.average is not None else self.model

    @torch.no_grad()
    def _update_average(self) -> None:
        """``avg <- ema avg + (1 - ema) w`` for every parameter (buffers are fitted once and shared)."""
        d = self.cfg.ema
        for a, w in zip(self.average.parameters(), self.model.parameters()):
            a.lerp_(w, 1.0 - d)
        for name, buf in self.model.named_buffers():  # initial_ready flips during training
            self.average.get_buffer(name).copy_(buf)

    def save(self) -> None:
        modules = {"predictor": self.result}
        if self.average is not None:
            modules["predictor_train"] = self.model
        save_checkpoint(self.ckpt, step=self.step, config=self.config, modules=modules, optimizer=self.optim)

    def loss(self, step: int, members: list[int] | None = None) -> tuple[Tensor, dict[str, float]]:
        """Summed dual-context (+ InitialLatentNet) losses of every member (or of the members with these indices),
        each on its own windows; logs are the members' means."""
        cfg = self.cfg
        ks = list(range(len(self.members))) if members is None else members
        K = len(ks)
        total, logs = None, {}
        for k in ks:
            m = self.members[k]
            g = step_generator(cfg.seed + MEMBER_SEED_STRIDE * k, step)
            rows, seg = self.sampler.sample(cfg.batch_size, g)
            d = dual_context_loss(
                m, self.data, rows, seg, cfg.detach_feedback, cfg.context_noise, g, cfg.feature_noise, cfg.burn_in
            )
            part, mlogs = d.total, {**d.logs, "gt": float(d.gt.detach()), "zero": float(d.zero.detach())}
            if m.initial is not None and cfg.initial_weight > 0:
                irows = self.train_rows[
                    torch.randint(len(self.train_rows), (cfg.batch_size * self.sampler.T,), generator=g)
                ]
                il = initial_loss(m, self.data, irows)
                part = part + cfg.initial_weight * il
                mlogs["initial_l1"] = float(il.detach())
            total = part if total is None else total + part
            for key, v in mlogs.items():
                logs[key] = logs.get(key, 0.0) + v / K
        logs["total"] = float(total.detach())
        return total, logs

    def _optimise(self, step: int, members: list[int] | None = None) -> dict[str, float]:
        """One AdamW step at ``step`` of every member (or of the members with these indices; the others get no
        gradient, so AdamW leaves them and their state alone). -> the step's logs"""
        ks = range(len(self.members)) if members is None else members
        for k in ks:  # from the step, so a resumed run is in the right phase
            self.members[k].signals_only = step < self.cfg.signal_warmup_steps
        loss, logs = self.loss(step, members)
        self.optim.zero_grad(set_to_none=True)
        loss.backward()
        self.optim.step()
        for k in ks:
            m = self.members[k]
            if m.initial is not None and self.cfg.initial_weight > 0:
                m.initial_ready.fill_(True)
        return logs

    def parallel(self) -> bool:
        """Whether :meth:`train` runs the members in forked processes (``parallel_members``)."""
        return (
            self.cfg.parallel_members
            and len(self.members) > 1
            and self.average is None
            and all(m.config.dropout == 0 for m in self.members)
            and torch.get_num_threads() <= len(self.members)
            and hasattr(os, "fork")
            and all(p.device.type == "cpu" for p in self.model.parameters())
        )

    def _log(self, step: int, logs: dict[str, float], rate: float) -> None:
        with open(self.out / "metrics.jsonl", "a") as f:
            f.write(json.dumps({"step": step, **{k: round(v, 6) for k, v in logs.items()}}) + "\n")
        print(
            f"[predictor] step {step}/{self.cfg.steps} loss {logs['total']:.4f} gt_l1 {logs['gt_l1']:.4f} "
            f"zero_l1 {logs['zero_l1']:.4f} ({rate:.2f} steps/s)",
            flush=True,
        )

    def _member_steps(self, k: int, end: int, stop: int, path: Path) -> None:
        """In a forked child: member ``k``'s steps ``self.step..end-1`` (:meth:`_optimise`); writes the member's
        weights, its parameters' optimiser state and its logs at the log steps to ``path``."""
        torch.set_num_threads(1)
        cfg, m = self.cfg, self.members[k]
        logs_at = {}
        for step in range(self.step, end):
            logs = self._optimise(step, [k])
            if (step + 1) % cfg.log_every == 0 or step + 1 == stop:
                logs_at[step + 1] = {**logs, "_time": time.perf_counter()}  # monotonic, shared by the processes
                if k == 0:  # live progress (the members' merged lines follow at the checkpoint)
                    print(f"[predictor] member 0: step {step + 1}/{cfg.steps} loss {logs['total']:.4f}", flush=True)
        own = {id(p) for p in m.parameters()}
        params = [p for g in self.optim.param_groups for p in g["params"]]
        state = {i: self.optim.state[p] for i, p in enumerate(params) if id(p) in own and p in self.optim.state}
        torch.save({"member": m.state_dict(), "optim": state, "logs": logs_at}, path)

    def _parallel_steps(self, end: int, stop: int, t0: float, n0: int) -> dict[str, float]:
        """Steps ``self.step..end-1`` of every member side by side (:meth:`_member_steps`), merged back into this
        process's members and optimiser; writes the log lines. -> the last logs"""
        import multiprocessing

        ctx = multiprocessing.get_context("fork")
        tmp = self.out / ".members"
        tmp.mkdir(exist_ok=True)
        paths = [tmp / f"member{k}.pt" for k in range(len(self.members))]
        procs = [ctx.Process(target=self._member_steps, args=(k, end, stop, p)) for k, p in enumerate(paths)]
        for p in procs:
            p.start()
        for p in procs:
            p.join()
        failed = [k for k, p in enumerate(procs) if p.exitcode != 0]
        if failed:
            raise RuntimeError(
                f"predictor ensemble member(s) {failed} failed in their training process (exit codes "
                f"{[procs[k].exitcode for k in failed]}); set parallel_members = False to train them in this process"
            )
        params = [p for g in self.optim.param_groups for p in g["params"]]
        member_logs = []
        for m, path in zip(self.members, paths):
            d = torch.load(path, weights_only=False)
            m.load_state_dict(d["member"])
            for i, st in d["optim"].items():
                self.optim.state[params[i]] = st
            member_logs.append(d["logs"])
            path.unlink()
        tmp.rmdir()
        logs = {}
        for step in sorted(member_logs[0]):
            per = [dict(ml[step]) for ml in member_logs]
            when = max(p.pop("_time") for p in per)  # the step's rate as it was reached, not at the merge
            logs = {key: sum(p[key] for p in per) / len(per) for key in per[0]}
            logs["total"] = sum(p["total"] for p in per)
            self._log(step, logs, (step - n0) / max(when - t0, 1e-9))
        return logs

    def train(self) -> dict:
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        stop = cfg.steps if cfg.max_steps_this_run is None else min(cfg.steps, self.step + cfg.max_steps_this_run)
        set_resume_hint(resume_hint(self.ckpt, self.step))
        t0, n0, logs = time.perf_counter(), self.step, {}
        self.model.train()
        parallel = self.parallel()
        while parallel and self.step < stop:  # the members side by side, one checkpoint interval at a time
            end = min(stop, (self.step // cfg.checkpoint_every + 1) * cfg.checkpoint_every)
            logs = self._parallel_steps(end, stop, t0, n0)
            self.step = end
            self.save()
        while self.step < stop:
            logs = self._optimise(self.step)
            self.step += 1
            if self.average is not None:
                self._update_average()
            if self.step % cfg.log_every == 0 or self.step == stop:
                self._log(self.step, logs, (self.step - n0) / (time.perf_counter() - t0))
            if self.step % cfg.checkpoint_every == 0 or self.step == stop:
                self.save()
        for m in self.members:
            m.signals_only = False
        self.model.eval()
        self.result.eval()
        return {"step": self.step, **logs, "seconds": time.perf_counter() - t0}


def train_predictor(
    run: Path,
    cfg: PredictorTrainConfig,
    out: Path | None = None,
    device: str = "auto",
    evaluate: bool = True,
    force_out: bool = False,
) -> dict:
    """Targets -> model -> train (resumes) -> evaluate on the train and test segments (``eval.json``).

    ``force_out``: accept a non-empty ``out`` that is not a gsavatar predictor output (refused otherwise)."""
    loaded = load_run(run, device)
    claim_output_dir(predictor_dir(run, out), "predictor", force_out)
    net, scene = loaded.net, loaded.scene
    dev = next(net.parameters()).device
    targets = extract_targets(run, out, loaded=loaded)
    d = predictor_dir(run, out)
    data = sequence_data(scene.capture.motion, targets, dev)
    splits = scene.capture.splits
    train_segs = split_segments(data.frames, splits["train"].frames)
    if cfg.ensemble < 1:
        raise ValueError(f"ensemble must be >= 1, got {cfg.ensemble}")
    members = [
        build_predictor(
            scene, cfg.model, targets.latents.shape[-1], net.avatar.config.pca, cfg.seed + MEMBER_SEED_STRIDE * k
        )
        for k in range(cfg.ensemble)
    ]
    members = [m.to(dev) for m in members]
    info = prepare_model(members[0], data, train_segs)
    for m in members[1:]:  # the fitted normalisation and latent PCA depend on the data only: fit once, copy
        fitted = dict(members[0].named_buffers())
        for name, buf in m.named_buffers():
            buf.copy_(fitted[name])
    model = members[0] if cfg.ensemble == 1 else PredictorEnsemble(members)
    print(
        f"[predictor] {info['train_frames']} train frames in {len(train_segs)} segments, latent PCA keeps "
        f"{100 * info['latent_pca_explained_variance']:.1f}% of the variance",
        flush=True,
    )
    del net
    trainer = PredictorTrainer(
        model, data, train_segs, cfg, d, {"run": str(Path(run).resolve()), "targets_step": loaded.step}
    )
    summary = trainer.train()
    model = trainer.result
    if not evaluate or trainer.step < cfg.steps:
        return summary
    res = {"step": trainer.step, **info, "code": code_version(), "train": evaluate_predictor(model, data, train_segs)}
    if "test" in splits:
        res["test"] = evaluate_predictor(model, data, split_segments(data.frames, splits["test"].frames))
    atomic_write_json(d / "eval.json", res)
    return res
