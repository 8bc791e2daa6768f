"""Which history regressor can the capture's fairness check trust? One change per row, on written captures.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fairness_variants.py \
        out/demo/capture out/cap2/capture \
        [--json docs/benchmarks/fairness_variants.json]

Rows (R^2 on the test frames pooled over the standardised states, each state its own CV-chosen ridge):
``stacked``: the last 10 frames' PCA features stacked (the check before 2026-12-04, alphas up to 1e4);
``stacked_wide``: the same with alphas up to 1e7; ``changes``: frame t and the 9 frame-to-frame changes (the
check now, :func:`gsavatar.synth.fairness.history_features`); ``changes_squared``: that plus every column squared
(and the pose-only features squared too), a second-order lift that could express speeds; ``changes_memory``:
``changes`` plus the predictor's memory features (:func:`gsavatar.models.predictor.memory_features`, time
constants 3, 10, 30 frames over the last 90: exponential averages of the value, |velocity| and velocity of every
feature), the history the ``--model.memory-timescales`` predictor option adds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from gsavatar.models.predictor import memory_features
from gsavatar.synth import fairness as fair

MEMORY_TIMESCALES = (3.0, 10.0, 30.0)


def memory_columns(z: np.ndarray, timescales=MEMORY_TIMESCALES) -> np.ndarray:
    """Every row's memory features over its ``ceil(3 max tau)``-frame window (clamped at row 0). [F, D] -> [F, 3MD]"""
    W = int(np.ceil(3 * max(timescales)))
    win = fair.stack_history(z, W).reshape(len(z), W, -1)  # oldest first
    return memory_features(torch.from_numpy(win), timescales).reshape(len(z), -1).numpy()


def _score(X: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray, alphas) -> dict:
    r2, per_state, chosen, _ = fair.ridge_r2(X, y, train, test, alphas)
    return {"r2": r2, "per_state": per_state, "alpha": chosen}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("captures", type=Path, nargs="+")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    narrow, wide = tuple(10.0**k for k in range(-3, 5)), fair.ALPHAS
    out = {}
    for cap in a.captures:
        x, levels, train, test = fair.capture_inputs(cap)
        y, _ = fair.standardise_states(levels, train)
        z = fair.reduce_features(x, train, raw_columns=1)
        stacked, changes = fair.stack_history(z, fair.HISTORY), fair.history_features(z, fair.HISTORY)
        sq = lambda m: np.concatenate([m, m**2], 1)  # noqa: E731
        rows = {
            "stacked": (z, stacked, narrow),
            "stacked_wide": (z, stacked, wide),
            "changes": (z, changes, wide),
            "changes_squared": (sq(z), sq(changes), wide),
            "changes_memory": (z, np.concatenate([changes, memory_columns(z)], 1), wide),
        }
        out[str(cap)] = {
            k: {"pose_only": _score(a_, y, train, test, al), "history": _score(b_, y, train, test, al)}
            for k, (a_, b_, al) in rows.items()
        }
        for k, r in out[str(cap)].items():
            print(
                f"{cap} {k:16s} pose only {r['pose_only']['r2']:6.3f}  history {r['history']['r2']:6.3f}  "
                f"per state {[round(v, 2) for v in r['history']['per_state']]}"
            )
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
