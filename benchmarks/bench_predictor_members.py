"""An ensemble predictor's training steps with its members one after the other in this process, and side by side in
forked processes of one thread each (``PredictorTrainConfig.parallel_members``), in one run on one avatar.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_predictor_members.py --run out/demo/run_ours [--steps 20]

The demo's recipe (ensemble of 2, window 8, global latent PCA of 8 components, the root's world orientation), from
the same initial weights, ``--steps`` steps each into temporary folders. Prints seconds per step of both, their ratio
and the largest weight difference after the same steps (float rounding only: tests/train/test_predictor_train.py
checks the two paths against each other).
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import torch

from gsavatar.models.predictor import PredictorConfig, PredictorEnsemble
from gsavatar.runs.load import load_run
from gsavatar.train.predictor import (
    MEMBER_SEED_STRIDE,
    PredictorTrainConfig,
    PredictorTrainer,
    build_predictor,
    extract_targets,
    prepare_model,
    sequence_data,
    split_segments,
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True, help="an avatar run (its predictor/targets.npz is reused)")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the in-process path (default 2)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    loaded = load_run(a.run)
    scene = loaded.scene
    targets = extract_targets(a.run, loaded=loaded)
    data = sequence_data(scene.capture.motion, targets)
    segs = split_segments(data.frames, scene.capture.splits["train"].frames)
    mcfg = PredictorConfig(latent_pca="global", latent_pca_components=8, world_orientation=True)
    members = [
        build_predictor(scene, mcfg, targets.latents.shape[-1], loaded.net.avatar.config.pca, MEMBER_SEED_STRIDE * k)
        for k in range(2)
    ]
    prepare_model(members[0], data, segs)
    fitted = dict(members[0].named_buffers())
    for m in members[1:]:  # the fitted normalisation and latent PCA, as train_predictor copies them
        for name, buf in m.named_buffers():
            buf.copy_(fitted[name])
    base = PredictorEnsemble(members)
    cfg = PredictorTrainConfig(steps=a.steps, window=8, ensemble=2, checkpoint_every=10**6, log_every=10**6, model=mcfg)
    res, models = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, parallel in (("one process", False), ("side by side", True)):
            model = copy.deepcopy(base)
            tr = PredictorTrainer(
                model, data, segs, dataclasses.replace(cfg, parallel_members=parallel), Path(tmp) / label
            )
            if tr.parallel() != parallel:
                raise SystemExit(f"{label}: parallel_members={parallel} not taken with {a.threads} threads")
            t0 = time.perf_counter()
            tr.train()
            res[label] = (time.perf_counter() - t0) / a.steps
            models[label] = model.state_dict()
    one, side = models["one process"], models["side by side"]
    diff = max(float((one[k].double() - side[k].double()).abs().max()) for k in one if one[k].numel())
    print(
        json.dumps(
            {
                "steps": a.steps,
                "threads_in_process": a.threads,
                "s_per_step_one_process": round(res["one process"], 3),
                "s_per_step_side_by_side": round(res["side by side"], 3),
                "speedup": round(res["one process"] / res["side by side"], 2),
                "max_weight_difference": diff,
            }
        )
    )


if __name__ == "__main__":
    main()
