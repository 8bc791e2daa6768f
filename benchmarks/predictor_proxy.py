"""Can the appearance predictor learn a capture's history-caused states? The predictor trained on the
ground-truth states themselves (``gt/motion_states.npz``) instead of encoder latents: one "anchor" whose
latent is the state vector. An upper bound on what pose history can tell it, free of the avatar.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/predictor_proxy.py --capture out/demo/capture \
        --name base [--history 10] [--no-velocities] [--steps 600] [--window 16] [--json out.json]

Prints one JSON line: R^2 (pooled over standardised states) on the test frames of the free-running rollout
from zero (``zero_init``) and from the first test frame's true state (``teacher_first``), next to holding the
first test frame's state (``hold_first``) and the training mean (``train_mean``, R^2 <= 0 by construction).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True)
    ap.add_argument("--name", default="base")
    ap.add_argument("--history", type=int, default=10)
    ap.add_argument("--no-velocities", action="store_true", help="ablation: N_b = 1, no velocities/accelerations")
    ap.add_argument("--steps", type=int, default=600)
    ap.add_argument("--window", type=int, default=16)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--weight-decay", type=float, default=1e-2)
    ap.add_argument("--absolute", action="store_true", help="l_t = mean + head(h) (not residual)")
    ap.add_argument("--joint-tokens", action="store_true", help="joint-position tokens in the heading frame")
    ap.add_argument("--joint-speeds", action="store_true", help="with --joint-tokens: the joints' speeds too")
    ap.add_argument("--gate", action="store_true", help="gated update l + g (c - l) (PredictorConfig.gate)")
    ap.add_argument(
        "--no-latent-tokens", action="store_true", help="with --gate: the previous latents only enter the gate"
    )
    ap.add_argument("--signals", action="store_true", help="the kinematic signal readout (readout='signals')")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-frames", type=int, default=None, help="train on the last N training frames only")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    from gsavatar.data_schema import load_capture
    from gsavatar.geometry.lbs import KinematicChain
    from gsavatar.models.predictor import AppearancePredictor, PredictorConfig
    from gsavatar.synth.fairness import pooled_r2
    from gsavatar.train.predictor import (
        PredictorTrainConfig,
        PredictorTrainer,
        SequenceData,
        prepare_model,
        split_segments,
    )

    torch.manual_seed(a.seed)
    cap = load_capture(a.capture)
    z = np.load(a.capture / "gt" / "motion_states.npz")
    lv = torch.as_tensor(z["levels"], dtype=torch.float32)  # [F, E]
    F = lv.shape[0]
    m = cap.motion
    data = SequenceData(
        torch.arange(F),
        torch.as_tensor(m.pose, dtype=torch.float32),
        torch.as_tensor(m.root_rotation, dtype=torch.float32),
        torch.as_tensor(m.root_translation, dtype=torch.float32),
        lv[:, None],
    )
    cfg = PredictorConfig(
        history=a.history,
        latent_dim=lv.shape[1],
        latent_pca_components=lv.shape[1],
        width=a.width,
        residual=not a.absolute,
        initial_net=False,
        velocities=not a.no_velocities,
        joint_tokens=a.joint_tokens,
        joint_speeds=a.joint_speeds,
        gate=a.gate,
        latent_tokens=not a.no_latent_tokens,
        readout="signals" if a.signals else "transformer",
        latent_pca="global" if a.signals else "anchor",
    )
    if a.no_velocities:
        cfg = dataclasses.replace(cfg, history=1)
    slots = np.arange(cap.rig.pose_dim)
    model = AppearancePredictor(
        cfg,
        1,
        slots,
        cap.rig.pose_dim,
        None,
        seed=a.seed,
        kinematics=KinematicChain.from_rig(cap.rig) if cfg.needs_kinematics else None,
    )
    train_frames = np.asarray(cap.splits["train"].frames)
    if a.train_frames is not None:  # one change: the amount of training data, the test frames unchanged
        train_frames = train_frames[-a.train_frames :]
    train = split_segments(data.frames, train_frames)
    test = split_segments(data.frames, cap.splits["test"].frames)
    prepare_model(model, data, train)
    tcfg = PredictorTrainConfig(
        steps=a.steps,
        window=a.window,
        batch_size=a.batch,
        weight_decay=a.weight_decay,
        seed=a.seed,
        checkpoint_every=10**9,
        log_every=10**9,
        model=cfg,
    )
    out = Path("/tmp/predictor_proxy") / a.name
    if (out / "latest.pt").exists():
        (out / "latest.pt").unlink()
    t0 = time.perf_counter()
    PredictorTrainer(model, data, train, tcfg, out).train()
    secs = time.perf_counter() - t0
    model.eval()
    res = {
        "name": a.name,
        "history": cfg.history,
        "velocities": cfg.velocities,
        "joint_tokens": cfg.joint_tokens,
        "joint_speeds": cfg.joint_speeds,
        "gate": cfg.gate,
        "latent_tokens": cfg.latent_tokens,
        "readout": cfg.readout,
        "steps": a.steps,
        "train_frames": int(len(train_frames)),
        "seconds": secs,
    }
    s, e = test[0]
    gt = lv[s:e]
    P, R, T = data.pose[s:e], data.root_rotation[s:e], data.root_translation[s:e]
    zero = model.rollout(P, R, T, torch.zeros(1, lv.shape[1]))[:, 0]
    # "zero" latents for the real predictor are the avatar's standardised zero = roughly the training mean;
    # here the states' zero is a real state, so start from the training mean like the drive's zero-init does.
    mean0 = model.rollout(P, R, T, model.latent_mean.clone())[:, 0]
    teach = model.rollout(P, R, T, gt[:1], first_is_given=True)[:, 0]
    sd = lv[np.asarray(cap.splits["train"].frames)].std(0).clamp_min(1e-6)  # the same scale for any --train-frames
    r2 = lambda p: pooled_r2((p / sd).numpy(), (gt / sd).numpy())  # noqa: E731
    res.update(
        {
            "zero_init": r2(zero),
            "mean_init": r2(mean0),
            "teacher_first": r2(teach),
            "hold_first": r2(gt[:1].expand_as(gt)),
            "train_mean": r2(model.latent_mean[0].expand_as(gt)),
            "per_state_mean_init": [
                pooled_r2((mean0[:, [k]] / sd[k]).numpy(), (gt[:, [k]] / sd[k]).numpy()) for k in range(gt.shape[1])
            ],
            "states": [str(x) for x in z["names"]],
        }
    )
    print(json.dumps(res))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        with open(a.json, "a") as f:
            f.write(json.dumps(res) + "\n")


if __name__ == "__main__":
    main()
