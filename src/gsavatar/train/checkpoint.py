"""Atomic, resumable, safe-to-load checkpoints.

A checkpoint is one ``torch.save`` file of plain containers and tensors only (state
dicts, optimizer state, the step, the config as a JSON string), so it loads with
``torch.load(weights_only=True)``: no pickled code runs. No RNG state is stored: the
trainers derive every random draw from (seed, step), so the step is enough to resume.
Written through a temp file + rename; ``latest.pt`` is replaced only once a new
checkpoint is complete, so ``kill -9`` at any point leaves a loadable file.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from gsavatar.data_schema.errors import SchemaError
from gsavatar.utils.io import atomic_path

CHECKPOINT_FORMAT = "gsavatar-avatar-checkpoint"
CHECKPOINT_VERSION = 1


def save_checkpoint(path: str | Path, *, step: int, config: dict, modules: dict[str, torch.nn.Module],
                    optimizer: torch.optim.Optimizer | None, extra: dict | None = None) -> None:
    state = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "step": int(step),
        "config": json.dumps(config, sort_keys=True),
        "modules": {k: m.state_dict() for k, m in modules.items()},
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "extra": extra or {},
    }
    with atomic_path(path, suffix=".pt") as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: str | Path, config: dict | None = None, strict_config_keys: tuple[str, ...] = ()) -> dict:
    """Load safely (``weights_only=True``) and check format and, for ``strict_config_keys``, the config.

    Raises SchemaError naming the file and the first mismatching config field, e.g. a
    checkpoint of another model size or another dataset.
    """
    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "checkpoint not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for corrupt files
        raise SchemaError(path, "", f"cannot load checkpoint (truncated or not a gsavatar checkpoint): {type(e).__name__}") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise SchemaError(path, "format", "not a gsavatar avatar checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise SchemaError(path, "version", f"unsupported checkpoint version {state.get('version')!r}")
    saved = json.loads(state["config"])
    state["config"] = saved
    if config is not None:
        for key in strict_config_keys:
            a, b = _get(saved, key), _get(config, key)
            if a != b:
                raise SchemaError(path, f"config.{key}", f"checkpoint has {a!r}, this run has {b!r}: it belongs to another configuration")
    return state


def _get(d: dict, dotted: str):
    for k in dotted.split("."):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d
