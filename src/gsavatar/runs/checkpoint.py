"""Atomic, resumable, safe-to-load checkpoints.

A checkpoint is one ``torch.save`` file of plain containers and tensors only (state
dicts, optimizer state, the step, the config as a JSON string), so it loads with
``torch.load(weights_only=True)``: no pickled code runs. No RNG state is stored: the
trainers derive every random draw from (seed, step), so the step is enough to resume.
Written through a temp file + rename; ``latest.pt`` is replaced only once a new
checkpoint is complete, so ``kill -9`` at any point leaves a loadable file.
"""

from __future__ import annotations

import io
from collections.abc import Callable
import json
from pathlib import Path

import torch

from gsavatar.utils.cli import set_resume_hint
from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_write_bytes
from gsavatar.utils.jsonio import is_int, parse_json_text

CHECKPOINT_FORMAT = "gsavatar-avatar-checkpoint"
CHECKPOINT_VERSION = 1


def save_checkpoint(
    path: str | Path,
    *,
    step: int,
    config: dict,
    modules: dict[str, torch.nn.Module],
    optimizer: torch.optim.Optimizer | None,
    extra: dict | None = None,
) -> None:
    """Write the checkpoint atomically and keep the command's resume hint true (:func:`resume_hint`): while ``path``
    is replaced a Ctrl-C may find the old file, the new one or (first save) none, so the hint is worded then; after,
    it names ``step``."""
    path = Path(path)
    set_resume_hint(lambda: resume_hint(path, None))
    state = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "step": int(step),
        "config": json.dumps(config, sort_keys=True),
        "modules": {k: m.state_dict() for k, m in modules.items()},
        "optimizer": optimizer.state_dict() if optimizer is not None else None,
        "extra": extra or {},
    }
    # Serialise in memory, then one atomic write: a full disk then raises OSError(ENOSPC) naming the file
    # (torch's zip writer turns it into "RuntimeError: ... unexpected pos"), and latest.pt stays intact.
    buf = io.BytesIO()
    torch.save(state, buf)
    atomic_write_bytes(path, buf.getbuffer())
    set_resume_hint(resume_hint(path, step))


def resume_hint(ckpt: Path, step: int | None) -> str:
    """What a command says about resuming when it is interrupted (Ctrl-C, disk full); ``step`` None: the step of the
    checkpoint on disk is not known (it is being replaced)."""
    if Path(ckpt).exists():
        if step is None:
            return f"re-run the same command to resume from its last checkpoint ({ckpt})"
        return f"re-run the same command to resume from step {step} ({ckpt})"
    return "no checkpoint yet: re-running the same command starts from step 0"


def load_checkpoint(
    path: str | Path,
    config: dict | None = None,
    strict_config_keys: tuple[str, ...] = (),
    defaults: dict[str, dict] | None = None,
    upgrade: Callable[[dict], dict] | None = None,
) -> dict:
    """Load safely (``weights_only=True``) and check format and, for ``strict_config_keys``, the config.

    ``defaults``: per strict key, the values of config fields added since a checkpoint was written (a field
    missing from the saved dict counts as its default, so adding a field with a default that keeps the old
    behaviour does not orphan earlier runs). Raises SchemaError naming the file and the first mismatching
    config field, e.g. a checkpoint of another model size or another dataset. ``upgrade``: brings a saved
    config of an earlier layout into today's before the comparison (:func:`gsavatar.runs.config.upgrade_run_json`).
    """
    path = Path(path)
    if not path.exists():
        raise SchemaError(path, "", "checkpoint not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for corrupt files
        raise SchemaError(
            path, "", f"cannot load checkpoint (truncated or not a gsavatar checkpoint): {type(e).__name__}"
        ) from None
    # isinstance first: a tensor stored under a key would make ``!=`` a tensor ("Boolean value ... ambiguous")
    if not isinstance(state, dict) or not isinstance(state.get("format"), str) or state["format"] != CHECKPOINT_FORMAT:
        raise SchemaError(path, "format", "not a gsavatar avatar checkpoint")
    if not is_int(state.get("version")) or state["version"] != CHECKPOINT_VERSION:
        raise SchemaError(path, "version", f"unsupported checkpoint version {state.get('version')!r}"[:200])
    if not is_int(state.get("step")) or state["step"] < 0:
        raise SchemaError(path, "step", f"expected an integer >= 0, got {state.get('step')!r}"[:200])
    if not isinstance(state.get("modules"), dict) or not all(isinstance(v, dict) for v in state["modules"].values()):
        raise SchemaError(path, "modules", "expected an object of state dicts (not a gsavatar avatar checkpoint)")
    if not isinstance(state.get("config"), str):
        raise SchemaError(path, "config", "missing (not a gsavatar avatar checkpoint)")
    saved = parse_json_text(state["config"], path)
    if not isinstance(saved, dict):
        raise SchemaError(path, "config", f"expected a JSON object, got {type(saved).__name__}")
    if upgrade is not None:
        saved = upgrade(saved)
    state["config"] = saved
    if config is not None:
        for key in strict_config_keys:
            a, b = _get(saved, key), _get(config, key)
            if defaults and key in defaults:  # fields added since either side was written: their defaults
                a = {**defaults[key], **a} if isinstance(a, dict) else a
                b = {**defaults[key], **b} if isinstance(b, dict) else b
            if a != b:
                raise SchemaError(
                    path,
                    f"config.{key}",
                    f"checkpoint has {a!r}, this run has {b!r}: it belongs to another configuration",
                )
    return state


def check_same_dataset(ckpt: Path, saved: dict, dataset: Path, dataset_id: str) -> None:
    """Refuse a checkpoint trained on another dataset than ``dataset`` (content id ``dataset_id``,
    :func:`gsavatar.data_schema.dataset.dataset_fingerprint`): another subject, or another preparation,
    now at the same path. Checkpoints written before ``dataset_id`` existed are compared by resolved path.
    Raises SchemaError naming ``ckpt`` and the field."""
    saved_id = saved.get("dataset_id")
    if saved_id is not None and saved_id != dataset_id:
        raise SchemaError(
            ckpt,
            "config.dataset_id",
            f"checkpoint was trained on another dataset (content "
            f"{str(saved_id)[:12]}..., {dataset} now holds {dataset_id[:12]}...): the dataset was "
            f"replaced or re-prepared; train a new run (another --out)",
        )
    if saved_id is None:
        old = Path(saved["train"]["dataset"])
        if old.resolve() != Path(dataset).resolve():
            raise SchemaError(
                ckpt,
                "config.train.dataset",
                f"checkpoint has {str(old)!r}, this run has {str(dataset)!r}: it belongs to another configuration",
            )


def _get(d: dict, dotted: str):
    for k in dotted.split("."):
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def load_optimizer_by_group_name(optim: torch.optim.Optimizer, saved: dict, path: str | Path) -> None:
    """``optim.load_state_dict(saved)`` with the saved parameter groups matched to the optimiser's by their
    ``name`` (not by position): a checkpoint written when the groups came in another order (the property table,
    models/properties.py, changed it) or had fewer groups (a property added since: it starts without state)
    resumes onto the right parameters. Groups without names fall back to position. SchemaError(path,
    ``optimizer``) when a named group's parameter count differs."""
    groups = optim.param_groups
    saved_groups = saved.get("param_groups", [])
    if not all("name" in g for g in groups) or not all(isinstance(g, dict) and "name" in g for g in saved_groups):
        optim.load_state_dict(saved)
        return
    by_name = {g["name"]: g for g in saved_groups}
    fresh_id = max((i for g in saved_groups for i in g["params"]), default=-1) + 1
    ordered = []
    for g in groups:
        s = by_name.get(g["name"])
        if s is None:  # new since the checkpoint: the current hyper-parameters, no state
            s = {k: v for k, v in g.items() if k != "params"}
            s["params"] = list(range(fresh_id, fresh_id + len(g["params"])))
            fresh_id += len(g["params"])
        elif len(s["params"]) != len(g["params"]):
            raise SchemaError(
                path, f"optimizer.{g['name']}", f"{len(s['params'])} parameters saved, the model has {len(g['params'])}"
            )
        ordered.append(s)
    optim.load_state_dict({**saved, "param_groups": ordered})
