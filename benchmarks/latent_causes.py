"""What explains each principal direction of an avatar's appearance latents: the root's world orientation, the
capture's true motion-history states, or the current local pose.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/latent_causes.py --run out/demo/run_ours \
        --json docs/benchmarks/latent_causes_small.json

The encoder's latents of every textured frame are standardised per (anchor, dim) on the training frames and
projected on their global principal directions (the predictor's ``--model.latent-pca global`` space). For each of
the first ``--components`` directions, one ridge regression per input set is fit on the training frames and scored
(skill: the share of the training-mean latent's squared error on the test frames that it removes):

- ``orientation``: the root's world orientation (first two columns of its rotation matrix, 6 numbers);
- ``states``: the capture's true appearance states (``gt/motion_states.npz`` levels; synthetic captures only);
- ``pose``: the current local pose (every pose slot, no root);
- ``orientation+states``.

A direction that ``orientation`` explains and ``states`` does not is shading baked into the projected textures by
lights fixed in the room (the body turns under them): a function of the current root orientation, not of the
motion's history, that a pose-conditioned avatar in canonical space cannot model, so the latents carry it. Prints one
line per direction; ``--json`` writes them with the variance shares.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def ridge_skill(X: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray, ridge: float = 1e-3) -> float:
    """Skill on ``test`` rows of a ridge fit of ``y`` on standardised ``X`` (plus a bias) over ``train`` rows:
    ``1 - SSE / SSE of the training mean`` (1: exact; 0: no better than the training mean, the predictor's zero
    init; < 0: worse). Unlike R^2 about the test rows' own mean it credits predicting where the test segment sits,
    which is most of what a latent predictor gains over the training-mean latent."""
    from gsavatar.synth.fairness import ridge_fit, ridge_predict

    model = ridge_fit(X[train], y[train, None], ridge * len(train))
    res = y[test] - ridge_predict(model, X[test])[:, 0]
    tot = y[test] - y[train].mean()
    return float(1.0 - (res @ res) / max(float(tot @ tot), 1e-12))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="an avatar run with an appearance encoder")
    ap.add_argument("--components", type=int, default=4, help="principal directions to explain")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    import torch

    from gsavatar.models.predictor import orientation_features
    from gsavatar.runs.load import load_run
    from gsavatar.train.predictor import extract_targets

    torch.set_num_threads(1)
    loaded = load_run(a.run)
    cap = loaded.scene.capture
    targets = extract_targets(a.run, loaded=loaded)
    frames = np.asarray(targets.frames, dtype=np.int64)
    lat = np.asarray(targets.latents, dtype=np.float64).reshape(len(frames), -1)  # [n, A*L]
    split = {s: set(int(f) for f in cap.splits[s].frames) for s in ("train", "test")}
    train = np.flatnonzero([int(f) in split["train"] for f in frames])
    test = np.flatnonzero([int(f) in split["test"] for f in frames])
    if len(train) < 2 or len(test) < 2:
        raise SystemExit(f"{a.run}: needs textured train and test frames, got {len(train)} / {len(test)}")
    mu, sd = lat[train].mean(0), lat[train].std(0)
    z = (lat - mu) / np.maximum(sd, 1e-6)
    _, s, vt = np.linalg.svd(z[train], full_matrices=False)
    K = min(a.components, len(s))
    coef = z @ vt[:K].T  # [n, K]
    share = (s**2 / (s**2).sum())[:K]

    inputs = {
        "orientation": orientation_features(
            torch.as_tensor(np.asarray(cap.motion.root_rotation, dtype=np.float64)[frames])
        ).numpy(),
        "pose": np.asarray(cap.motion.pose, dtype=np.float64)[frames],
    }
    states_path = cap.root / "gt" / "motion_states.npz"
    if states_path.exists():
        st = np.load(states_path)
        inputs["states"] = np.asarray(st["levels"], dtype=np.float64)[frames]
        inputs["orientation+states"] = np.c_[inputs["orientation"], inputs["states"]]
        state_names = [str(n) for n in st["names"]]
    else:
        state_names = []
    rows = []
    for k in range(K):
        skill = {name: ridge_skill(X, coef[:, k], train, test) for name, X in inputs.items()}
        rms = float(np.sqrt(np.mean((coef[test, k] - coef[train, k].mean()) ** 2)))
        std = float(coef[train, k].std())
        rows.append(
            {
                "component": k + 1,
                "variance_share": float(share[k]),
                "test_skill": skill,
                "test_rms_about_train_mean": rms,
                "train_std": std,
            }
        )
        print(
            f"PC{k + 1} ({100 * share[k]:.1f}% of the training variance): test rms about the training mean "
            f"{rms:.1f} (training std {std:.1f}); skill " + ", ".join(f"{n} {v:.2f}" for n, v in skill.items())
        )
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        out = {
            "run": str(a.run),
            "train_frames": int(len(train)),
            "test_frames": int(len(test)),
            "states": state_names,
            "components": rows,
        }
        a.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
