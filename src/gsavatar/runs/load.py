"""Load a trained run (``avatar-train avatar``/``predictor`` output) back into models.

RUN/config.json               {"train": TrainConfig, "model": ModelConfig, "dataset_id"}
RUN/checkpoints/latest.pt     the avatar net (:mod:`gsavatar.runs.checkpoint`)
RUN/predictor/latest.pt       the appearance predictor, when one was trained
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import torch

from gsavatar.data_schema.dataset import dataset_fingerprint
from gsavatar.data_schema.prepared import PreparedScene, load_scene
from gsavatar.models.config import ModelConfig
from gsavatar.models.net import AvatarNet, build_net
from gsavatar.models.predictor import (
    KINEMATICS_KEYS,
    LEGACY_CONFIG,
    AppearancePredictor,
    PredictorConfig,
    PredictorEnsemble,
)
from gsavatar.runs.checkpoint import check_same_dataset, load_checkpoint
from gsavatar.runs.config import TrainConfig, check_train_config, from_json, resolve, upgrade_run_json
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.jsonio import dataclass_defaults, read_json


class LoadedRun(NamedTuple):
    """A run rebuilt from disk by :func:`load_run`."""

    net: AvatarNet
    """The avatar net with the latest checkpoint's weights, in eval mode."""
    scene: PreparedScene
    """The prepared dataset the run was trained on."""
    config: TrainConfig
    """The run's training configuration, presets resolved."""
    step: int
    """Optimisation step of the checkpoint."""


def pick_device(name: str) -> torch.device:
    """``auto`` -> CUDA if available, else CPU; any other name as torch spells it (``cpu``, ``cuda:1``)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def load_run(run: str | Path, device: str = "auto") -> LoadedRun:
    """Rebuild the net of a run from its config and latest checkpoint (in eval mode, on ``device``:
    ``auto`` = CUDA if available). SchemaError names the file and field of a run that is not one."""
    run = Path(run)
    cfg_path = run / "config.json"
    if not cfg_path.exists():
        raise SchemaError(cfg_path, "", "not a training run (config.json missing)")
    saved = read_json(cfg_path)  # strict: duplicate keys, NaN, deep nesting, FIFOs are refused naming the file
    if not isinstance(saved, dict) or "train" not in saved:
        raise SchemaError(cfg_path, "train", "missing (not the config.json of a gsavatar run)")
    # the model the run was trained with (config.json), not today's preset: presets may change between versions
    cfg = from_json(saved["train"], cfg_path, model=saved.get("model"))
    try:
        check_train_config(cfg)
    except ValueError as e:
        raise SchemaError(cfg_path, "train", str(e)) from None
    cfg = resolve(cfg)
    dev = pick_device(device)
    scene = load_scene(cfg.dataset)
    net = build_net(scene, cfg.model, cfg.seed).to(dev)
    ckpt = run / "checkpoints" / "latest.pt"
    state = load_checkpoint(
        ckpt,
        saved,
        strict_config_keys=("model",),
        defaults={"model": dataclass_defaults(ModelConfig)},
        upgrade=upgrade_run_json,
    )
    check_same_dataset(ckpt, state["config"], cfg.dataset, dataset_fingerprint(cfg.dataset))
    net.load_state_dict(state["modules"]["net"])
    net.eval()
    if dev.type == "cpu":
        net.avatar.pack_bases_()  # one stream for the CPU inference kernel; same values
    return LoadedRun(net, scene, cfg, int(state["step"]))


def run_predictor_path(run: str | Path) -> Path:
    """Where ``avatar-train predictor`` writes the run's appearance predictor."""
    return Path(run) / "predictor" / "latest.pt"


def predictor_from_checkpoint(
    path: Path, device: str | torch.device = "cpu"
) -> AppearancePredictor | PredictorEnsemble:
    """Rebuild a trained predictor (or ensemble, config ``ensemble`` = K) from its checkpoint alone (slots and
    pose PCA are buffers)."""
    state = load_checkpoint(path)
    sd = state["modules"]["predictor"]
    cfg = PredictorConfig(**{**LEGACY_CONFIG, **state["config"]["model"]})  # fields older checkpoints lack
    K = int(state["config"].get("ensemble", 1))
    prefixes = [f"members.{k}." for k in range(K)] if K > 1 else [""]
    members = []
    for pre in prefixes:
        msd = {k[len(pre) :]: v for k, v in sd.items() if k.startswith(pre)}
        if not msd:
            raise SchemaError(path, "modules.predictor", f"ensemble of {K}: no weights under {pre!r}")
        pca = (msd["pose_pca_mean"], msd["pose_pca_basis"], msd["pose_pca_limit"]) if "pose_pca_basis" in msd else None
        kin = tuple(msd[k] for k in KINEMATICS_KEYS) if KINEMATICS_KEYS[0] in msd else None
        members.append(
            AppearancePredictor(
                cfg,
                msd["latent_mean"].shape[0],
                msd["pose_slots"],
                int(state["config"]["pose_dim"]),
                pca,
                kinematics=kin,
            )
        )
    m = members[0] if K == 1 else PredictorEnsemble(members)
    m.load_state_dict(sd)
    return m.to(device).eval()
