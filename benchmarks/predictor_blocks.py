"""Where in the test segment a predictor's rollout loses, and what its fed-back latents are worth.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/predictor_blocks.py --run out/cap2/run_ours \
        --predictors base=out/cap2/run_ours/predictor/latest.pt mem=out/cap2/run_ours/predictor_mem/latest.pt \
        --block 30 --json docs/benchmarks/predictor_memory_second.json

Latent space only (no rendering; seconds): the L1 to the encoder's latents (the predictor's targets,
``RUN/predictor/targets.npz``) of every test frame but the first, averaged over blocks of ``--block`` test
frames and over the segment, for

- ``zero_init``: the free-running rollout from the zero context (the training-mean latent), as ``eval.json``;
- ``no_feedback``: every frame predicted from the pose window and the zero context, nothing fed back (the
  same weights; what the rollout's own latents add over the pose window alone);
- ``train_mean``: the training-mean latent, the floor any predictor must beat.

A cold-start problem shows as a first block far above the rest; a generalisation gap as every block above
``one_step`` of ``eval.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch


def block_means(err: np.ndarray, block: int) -> list[float]:
    """Mean of ``err`` [T] over consecutive blocks of ``block`` frames (the last may be shorter)."""
    return [round(float(err[i : i + block].mean()), 4) for i in range(0, len(err), block)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--predictors", nargs="+", required=True, help="LABEL=CHECKPOINT")
    ap.add_argument("--block", type=int, default=30, help="test frames per block")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    if a.block < 1:
        ap.error(f"--block must be >= 1, got {a.block}")
    torch.set_num_threads(1)

    from gsavatar.data_schema.prepared import load_scene
    from gsavatar.runs.load import predictor_from_checkpoint
    from gsavatar.utils.jsonio import read_json
    from gsavatar.train.predictor import TargetLatents, sequence_data, split_segments

    targets_path = a.run / "predictor" / "targets.npz"
    if not targets_path.exists():
        raise SystemExit(f"{targets_path}: no encoder latents (run `avatar-train predictor --run {a.run}` first)")
    z = np.load(targets_path)
    cap = load_scene(read_json(a.run / "config.json")["train"]["dataset"]).capture
    data = sequence_data(cap.motion, TargetLatents(z["latents"], z["frames"]), "cpu")
    segments = split_segments(data.frames, cap.splits["test"].frames)
    train = split_segments(data.frames, cap.splits["train"].frames)
    train_rows = torch.cat([torch.arange(s, e) for s, e in train])
    mean = data.latents[train_rows].mean(0)
    out: dict = {"run": str(a.run), "block": a.block, "segments": segments, "predictors": {}}
    for s, e in segments:
        gt = data.latents[s:e]
        out["train_mean"] = block_means((mean - gt[1:]).abs().mean((1, 2)).numpy(), a.block)
    for spec in a.predictors:
        label, _, path = spec.partition("=")
        if not path:
            ap.error(f"--predictors wants LABEL=CHECKPOINT, got {spec!r}")
        m = predictor_from_checkpoint(Path(path), "cpu").eval()
        res = {}
        for s, e in segments:  # the test split is one segment in every capture we write
            P, R, T, gt = data.pose[s:e], data.root_rotation[s:e], data.root_translation[s:e], data.latents[s:e]
            with torch.no_grad():
                runs = {
                    "zero_init": m.rollout(P, R, T, m.zero_latents()),
                    "no_feedback": m.rollout(
                        P, R, T, m.zero_latents(), reinit_every=1, reinit_latents=lambda t: m.zero_latents()
                    ),
                }
            for k, v in runs.items():
                err = (v[1:] - gt[1:]).abs().mean((1, 2)).numpy()
                res[k] = {"blocks": block_means(err, a.block), "mean": round(float(err.mean()), 4)}
        out["predictors"][label] = res
        print(label, json.dumps(res), flush=True)
    print("train_mean", out["train_mean"], flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
