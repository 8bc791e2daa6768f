"""Config serialisation (one helper for every recorded config) and the learning rates that reach the optimiser."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from gsavatar.models import AppearanceEncoder, LearningRates, ModelConfig, model_preset
from gsavatar.utils.jsonio import config_to_json


@dataclasses.dataclass
class _Inner:
    band: tuple[float, float] = (0.5, 2.0)


@dataclasses.dataclass
class _Outer:
    root: Path = Path("/data/x")
    maybe: Path | None = None
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    names: tuple[str, ...] = ("a", "b")
    workers: int = 3


def test_config_to_json_is_plain_json():
    d = config_to_json(_Outer(), exclude=("workers",))
    assert d == {"root": "/data/x", "maybe": None, "inner": {"band": [0.5, 2.0]}, "names": ["a", "b"]}
    assert json.loads(json.dumps(d)) == d


def test_model_config_to_json_is_what_runs_recorded():
    # Trainer.config_json used to fall back to this (``hasattr(mcfg, "to_json")`` never held); run
    # checkpoints compare it on resume, so the form must not change.
    cfg = model_preset("small", face_dim=3)
    legacy = {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.__dict__.items()}
    assert cfg.to_json() == legacy
    back = json.loads(json.dumps(cfg.to_json()))
    assert ModelConfig(**back) == cfg


def test_encoder_learning_rates_come_from_learning_rates():
    enc = AppearanceEncoder(latent_dim=4)
    (g,) = enc.param_groups()
    assert (g["name"], g["lr"], g["weight_decay"]) == ("encoder", 5e-4, 1e-3)  # the paper's (supp. D.2), as before
    (g,) = enc.param_groups(LearningRates(encoder=1e-3, encoder_weight_decay=0.5))
    assert (g["lr"], g["weight_decay"]) == (1e-3, 0.5)
    assert g["params"] == list(enc.parameters())
