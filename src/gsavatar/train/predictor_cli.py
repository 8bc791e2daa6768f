"""``avatar-train predictor``: train the autoregressive appearance predictor of an avatar run.

avatar-train predictor --run runs/small                     # RUN/predictor/{targets.npz,latest.pt,eval.json}
avatar-train predictor --run runs/small --steps 500 --window 8 --model.history 10
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from gsavatar.train.predictor import PredictorTrainConfig, train_predictor


@dataclass(kw_only=True)
class Predictor:
    """Train the appearance predictor on a run's encoder latents; resumes from RUN/predictor/latest.pt."""

    run: Path
    """Avatar run directory written by ``avatar-train avatar`` (needs the appearance encoder)."""
    train: Annotated[PredictorTrainConfig, tyro.conf.arg(name="")] = field(default_factory=PredictorTrainConfig)
    """The predictor's training configuration (flags without a prefix; its model under ``--model.*``)."""
    out: Path | None = None
    """Output directory (default: RUN/predictor)."""
    device: str = "auto"
    """``auto`` (CUDA if available), ``cpu`` or ``cuda[:i]``."""
    evaluate: bool = True
    """Report the L1 to the encoder latents on train and held-out test frames at the end (eval.json)."""
    force: bool = False
    """Write into a non-empty ``out`` that is not a gsavatar predictor output (refused otherwise)."""

    def execute(self) -> None:
        if not Path(self.run).is_dir():
            raise FileNotFoundError(f"run directory {self.run} does not exist")
        res = train_predictor(self.run, self.train, self.out, self.device, self.evaluate, force_out=self.force)
        print(json.dumps(res, indent=1))
