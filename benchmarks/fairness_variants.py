"""Which history regressor can the capture's fairness check trust? One change per row, on written captures.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/fairness_variants.py \
        out/demo/capture out/cap2/capture \
        [--json docs/benchmarks/fairness_variants.json]

Rows (R^2 on the test frames pooled over the standardised states, each state its own CV-chosen ridge):
``stacked``: the last 10 frames' PCA features stacked (the check before 2026-12-04, alphas up to 1e4);
``stacked_wide``: the same with alphas up to 1e7; ``changes``: frame t and the 9 frame-to-frame changes (the
check now, :func:`gsavatar.synth.fairness.history_features`); ``changes_squared``: that plus every column squared
(and the pose-only features squared too), a second-order lift that could express speeds.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from gsavatar.data_schema import load_capture
from gsavatar.synth import fairness as fair
from gsavatar.synth.render import pose_joint_positions
from gsavatar.utils.io import read_npz


def _load(capture: Path):
    cap = load_capture(capture)
    m = cap.motion
    joints = pose_joint_positions(cap.rig, m.pose, m.root_rotation, m.root_translation)
    levels = read_npz(capture / "gt" / "motion_states.npz", keys=("levels",))["levels"]
    x = fair.pose_features(m.pose, m.root_translation, joints)
    return x, levels, np.asarray(cap.splits["train"].frames), np.asarray(cap.splits["test"].frames)


def _reduce(x: np.ndarray, train: np.ndarray, components: int = 12, raw: int = 1) -> np.ndarray:
    mu, sd = x[train].mean(0), x[train].std(0)
    z = (x - mu) / np.where(sd > 1e-9, sd, 1.0)
    keep = x.shape[1] - raw
    _, _, vt = np.linalg.svd(z[train][:, :keep], full_matrices=False)
    return np.concatenate([z[:, :keep] @ vt[:components].T, z[:, keep:]], 1)


def _score(X: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray, alphas) -> dict:
    fair_alphas, fair.ALPHAS = fair.ALPHAS, alphas
    try:
        pred = np.empty((len(test), y.shape[1]))
        chosen = []
        for e in range(y.shape[1]):
            chosen.append(fair.ridge_cv(X[train], y[train][:, [e]]))
            m = fair._ridge_fit(X[train], y[train][:, [e]], chosen[-1])
            pred[:, e] = np.clip(fair._ridge_predict(m, X[test])[:, 0], y[train][:, e].min(), y[train][:, e].max())
    finally:
        fair.ALPHAS = fair_alphas
    return {
        "r2": fair.pooled_r2(pred, y[test]),
        "per_state": [fair.pooled_r2(pred[:, [e]], y[test][:, [e]]) for e in range(y.shape[1])],
        "alpha": chosen,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("captures", type=Path, nargs="+")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    narrow, wide = tuple(10.0**k for k in range(-3, 5)), fair.ALPHAS
    out = {}
    for cap in a.captures:
        x, y, train, test = _load(cap)
        y = (y - y[train].mean(0)) / np.where(y[train].std(0) > 1e-9, y[train].std(0), 1.0)
        z = _reduce(x, train)
        stacked, changes = fair.stack_history(z, fair.HISTORY), fair.history_features(z, fair.HISTORY)
        sq = lambda m: np.concatenate([m, m**2], 1)  # noqa: E731
        rows = {
            "stacked": (z, stacked, narrow),
            "stacked_wide": (z, stacked, wide),
            "changes": (z, changes, wide),
            "changes_squared": (sq(z), sq(changes), wide),
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
