"""Which inputs let a small gated recurrence learn a capture's history-caused states from its training frames?

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/state_identifiability.py --capture out/cap2/capture \
        --inputs all speeds joint:left_knee --seeds 0 1 --json docs/benchmarks/state_identifiability_second.json

The same model for every input set: ``s_t = s_{t-1} + g (c - s_{t-1})`` over the standardised true states
(``gt/motion_states.npz``), gate ``g`` and candidate ``c`` from an MLP (one hidden layer of 64, ReLU) of the frame's
standardised input features, trained like the predictor (AdamW 1e-3, weight decay 1e-2, windows of 8 frames from
the true and the zero state, L1) and scored by R^2 of the free-running rollout over the test frames from the
training mean. Input sets: ``all`` (the paper's pose-slot tokens' features and every joint's heading-frame
position features and speeds, flattened), ``joints`` (the joints' only), ``speeds`` (every joint's speeds over the
window) and ``joint:NAME`` (one body part's speeds: an oracle that knows which joint drives the state). The
difference between ``speeds`` and ``joint:NAME`` is what the learner must find from the data alone.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch


HISTORY = 10
"""N_b: frames in the window (the paper's)."""


def capture_features(capture: Path, history: int = HISTORY):
    """(pose-slot features [F, S*F1], joint features [F, J, 3F+N-1], levels [F, E], train, test, names, joint names)"""
    from gsavatar.data_schema import load_capture
    from gsavatar.geometry.lbs import KinematicChain
    from gsavatar.models.predictor import AppearancePredictor, PredictorConfig
    from gsavatar.train.predictor import history_index

    cap = load_capture(capture)
    z = np.load(capture / "gt" / "motion_states.npz")
    lv = z["levels"].astype(np.float64)
    cfg = PredictorConfig(
        history=history,
        latent_dim=lv.shape[1],
        latent_pca_components=lv.shape[1],
        joint_tokens=True,
        joint_speeds=True,
        initial_net=False,
    )
    m = cap.motion
    model = AppearancePredictor(
        cfg, 1, np.arange(cap.rig.pose_dim), cap.rig.pose_dim, None, kinematics=KinematicChain.from_rig(cap.rig)
    )
    F = len(lv)
    h = history_index(torch.arange(F), torch.zeros(F, dtype=torch.long), history)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)[h]  # noqa: E731
    with torch.no_grad():
        x, xj = model.input_features(t(m.pose), t(m.root_rotation), t(m.root_translation))
    names = [str(n) for n in z["names"]]
    joints = [j.name for j in cap.rig.joints]
    tr, te = np.asarray(cap.splits["train"].frames), np.asarray(cap.splits["test"].frames)
    return x.reshape(F, -1).numpy(), xj.numpy(), lv, tr, te, names, joints


def fit_gated(X: np.ndarray, Y: np.ndarray, tr: np.ndarray, te: np.ndarray, steps: int, seed: int) -> dict:
    """Train the gated recurrence on the training frames; R^2 of its free rollouts (per state and pooled)."""
    torch.manual_seed(seed)
    mu, sd = X[tr].mean(0), X[tr].std(0)
    keep = sd > 1e-6
    Xs = torch.tensor((X[:, keep] - mu[keep]) / sd[keep], dtype=torch.float32)
    Ys = torch.tensor((Y - Y[tr].mean(0)) / (Y[tr].std(0) + 1e-6), dtype=torch.float32)
    E = Ys.shape[1]
    net = torch.nn.Sequential(torch.nn.Linear(Xs.shape[1], 64), torch.nn.ReLU(), torch.nn.Linear(64, 2 * E))
    with torch.no_grad():
        net[-1].bias[E:].fill_(-2.0)
    opt = torch.optim.AdamW(net.parameters(), 1e-3, weight_decay=1e-2)

    def step(s: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        o = net(x)
        return s + torch.sigmoid(o[..., E:]) * (o[..., :E] - s)

    win, B = 8, 8
    from gsavatar.train.predictor import split_segments

    segments = split_segments(np.arange(len(Y)), tr)  # windows stay inside runs of consecutive training frames
    starts = torch.as_tensor([k for s, e in segments for k in range(s + 1, e - win + 1)])
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        b = starts[torch.randint(len(starts), (B,), generator=gen)]
        s, loss = torch.cat([Ys[b - 1], torch.zeros(B, E)]), 0.0
        for k in range(win):
            s = step(s, Xs[b + k].repeat(2, 1))
            loss = loss + (s - Ys[b + k].repeat(2, 1)).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    def r2(frames: np.ndarray) -> tuple[list[float], float]:
        s, out = torch.zeros(E), []
        with torch.no_grad():
            for f in frames:
                s = step(s, Xs[f])
                out.append(s)
        p, y = torch.stack(out).numpy(), Ys[frames].numpy()
        res, tot = ((p - y) ** 2).sum(0), ((y - y.mean(0)) ** 2).sum(0)
        return [float(v) for v in 1 - res / tot], float(1 - res.sum() / tot.sum())

    per, pooled = r2(te)
    return {"test_per_state": per, "test_pooled": pooled, "train_pooled": r2(tr)[1]}


def hysteresis_windows(capture: Path, tr: np.ndarray, te: np.ndarray, history: int = HISTORY) -> list[dict]:
    """For every hysteresis state: the share of training / test frames whose state an event (the signal at or
    beyond a threshold) inside the last ``history`` frames decides, i.e. what a window of the signal can tell."""
    z = np.load(capture / "gt" / "motion_states.npz")
    effects = json.loads((capture / "gt" / "states.json").read_text())["motion_effects"]
    out = []
    for k, name in enumerate(str(n) for n in z["names"]):
        c = effects.get(name, {}).get("constants", {})
        if not {"low", "high"} <= set(c):
            continue
        u = z["signals"][:, k]
        event = (u >= c["high"]) | (u <= c["low"])
        last, back = -(10**9), np.empty(len(u), dtype=np.int64)
        for t in range(len(u)):
            last = t if event[t] else last
            back[t] = t - last
        decided = back < history
        out.append(
            {
                "state": name,
                "window": history,
                "decided_train": float(decided[tr].mean()),
                "decided_test": float(decided[te].mean()),
            }
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True)
    ap.add_argument("--inputs", nargs="+", default=["all", "joints", "speeds"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    from gsavatar.synth.motion_effects import resolve_joint

    x, xj, lv, tr, te, names, joints = capture_features(a.capture)
    F, J = xj.shape[:2]
    speeds = xj[:, :, -(HISTORY - 1) :]  # the N_b - 1 speeds of every joint
    windows = hysteresis_windows(a.capture, tr, te)
    for w in windows:
        print(json.dumps(w))
    rows = []
    for inp in a.inputs:
        if inp == "all":
            X = np.c_[x, xj.reshape(F, -1)]
        elif inp == "joints":
            X = xj.reshape(F, -1)
        elif inp == "speeds":
            X = speeds.reshape(F, -1)
        elif inp.startswith("joint:"):
            X = speeds[:, resolve_joint(inp.split(":", 1)[1], joints)]
        else:
            raise SystemExit(f"--inputs: unknown input set {inp!r} (all, joints, speeds, joint:NAME)")
        for seed in a.seeds:
            t0 = time.perf_counter()
            r = {"inputs": inp, "columns": int(X.shape[1]), "seed": seed, **fit_gated(X, lv, tr, te, a.steps, seed)}
            r["seconds"] = time.perf_counter() - t0
            print(json.dumps(r))
            rows.append(r)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        out = {
            "command": "benchmarks/state_identifiability.py "
            + " ".join(
                f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}"
                for k, v in vars(a).items()
                if k != "json" and v is not None
            ),
            "machine": f"{platform.machine()}, {platform.system()}, one torch thread",
            "states": names,
            "train_frames": int(len(tr)),
            "test_frames": int(len(te)),
            "hysteresis_decided_by_the_window": windows,
            "rows": rows,
        }
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
