"""PSNR inside the mask of predictor variants on a run's test frames, without a full drive per variant.

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/predictor_psnr.py --run out/demo/run_ours \
        --predictors base=out/demo/run_ours/predictor/latest.pt abs=out/demo/run_ours/pred_exp/e3/latest.pt \
        --every 3 --json docs/benchmarks/predictor_variants_small.json

A label's checkpoints joined by ``+`` are averaged step by step (``PredictorEnsemble``, as ``--ensemble K``
trains them). Rolls every predictor out over the whole test segment (latents only: zero init, and encoder init = the
encoder's latents of the first test frame, then free-running) and renders every ``--every``-th test frame
from every held-out camera with those latents, the encoder's and the training-mean latent. Prints one JSON
line per source: PSNR inside the mask (pooled squared error over the rendered views), the recovery
(gain over the mean latent / the encoder's) and the L1 to the encoder latents over all test frames. The
numbers are the drive's (same renderer, cameras and masks); ``avatar-drive`` renders every frame.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch


def ridge_latents(
    X: np.ndarray, capture_root: Path, targets, frames: list[int], held: list[int | None], ridge: float = 1e-3
) -> list[torch.Tensor]:
    """Latents of ``frames`` read from per-frame features ``X`` [F, D] (every capture frame) by an affine ridge fit on
    the training frames' encoder latents; the features are standardised on the training frames. For each entry of
    ``held``: the read-out with that feature column held at its training mean (``None``: none held).
    -> [T, A, L] each"""
    from gsavatar.data_schema.capture import load_capture
    from gsavatar.synth.fairness import ridge_fit, ridge_predict

    lat = np.asarray(targets.latents, dtype=np.float64)  # [n, A, L]
    shape = lat.shape[1:]
    train = set(int(f) for f in load_capture(capture_root).splits["train"].frames)
    rows = [i for i, f in enumerate(targets.frames) if int(f) in train]
    ftr = np.asarray(targets.frames)[rows]
    model = ridge_fit(X[ftr], lat[rows].reshape(len(rows), -1), ridge * len(rows))
    mu = model[0]
    Xf = X[np.asarray(frames)]
    out = []
    for h in held:
        Xh = Xf.copy()
        if h is not None:
            Xh[:, h] = mu[h]  # the training mean
        out.append(torch.as_tensor(ridge_predict(model, Xh).reshape(len(frames), *shape), dtype=torch.float32))
    return out


def oracle_latents(
    capture_root: Path, targets, frames: list[int], root_rotation: np.ndarray, pose: np.ndarray
) -> dict[str, torch.Tensor]:
    """Upper bounds read from what a capture's appearance is a function of, by :func:`ridge_latents`:

    - ``true states``: every ``gt/motion_states.npz`` level (a perfect predictor of the states, rendered through the
      best linear map to the latent space), and for each state the same with that state held at its mean (a perfect
      predictor of every other state that never learnt this one);
    - ``orientation``: the root's world orientation alone (what an input with no memory at all can read of the
      shading by lights fixed in the room, docs/train.md);
    - ``current pose + orientation``: everything a frame shows, with no memory (the linear no-history bound);
    - ``orientation + true states``."""
    from gsavatar.models.predictor import orientation_features

    orient = orientation_features(torch.as_tensor(np.asarray(root_rotation, dtype=np.float64))).numpy()
    pose = np.asarray(pose, dtype=np.float64)
    out = {
        "oracle: orientation": ridge_latents(orient, capture_root, targets, frames, [None])[0],
        "oracle: current pose + orientation": ridge_latents(np.c_[pose, orient], capture_root, targets, frames, [None])[
            0
        ],
    }
    path = capture_root / "gt" / "motion_states.npz"
    if not path.exists():
        return out
    z = np.load(path)
    levels, names = z["levels"].astype(np.float64), [str(n) for n in z["names"]]  # [F, E]
    lats = ridge_latents(levels, capture_root, targets, frames, [None] + list(range(len(names))))
    out["oracle: true states"] = lats[0]
    for n, lat in zip(names, lats[1:]):
        out[f"oracle: true states, {n} at its mean"] = lat
    out["oracle: orientation + true states"] = ridge_latents(
        np.c_[orient, levels], capture_root, targets, frames, [None]
    )[0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument(
        "--predictors", nargs="+", default=[], help="LABEL=CHECKPOINT, or LABEL=CKPT+CKPT+... for their ensemble"
    )
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--oracles",
        action="store_true",
        help="also render two upper bounds: the encoder's latents through the first predictor's output clamp, and "
        "ridges from the capture's true states (gt/motion_states.npz), from the root's world orientation and from "
        "both to the encoder's latents, fit on the training frames (what a predictor that knew them exactly could "
        "render), and the test frames' mean latent (a constant: the share of the gain that is the segment's level)",
    )
    a = ap.parse_args()
    torch.set_num_threads(1)

    from gsavatar.drive.driver import DriveConfig, Driver, motion_inputs
    from gsavatar.drive.metrics import load_ground_truth
    from gsavatar.drive.motion import load_driving_motion
    from gsavatar.runs.latents import mean_train_latent
    from gsavatar.models.predictor import PredictorEnsemble
    from gsavatar.runs.load import load_run, predictor_from_checkpoint
    from gsavatar.train.predictor import extract_targets

    loaded = load_run(a.run)
    net, scene = loaded.net, loaded.scene
    cap = scene.capture
    cams = list(cap.splits["test"].cameras)
    d = Driver(
        a.run,
        DriveConfig(mode="encoder", capture_cameras=tuple(cams), image_scale=a.image_scale),
        loaded=loaded,
        predictor=None,
    )
    d.use_capture_cameras(cap)
    motion = load_driving_motion(cap.root, cap.rig, d.fps, split="test")
    frames = list(motion.gt.frames)
    T = len(frames)
    targets = extract_targets(a.run, loaded=loaded)
    row = {int(f): i for i, f in enumerate(targets.frames)}
    enc = torch.as_tensor(targets.latents[[row[int(f)] for f in frames]])  # [T, A, L]
    P, R, Tr = (
        torch.as_tensor(np.asarray(x)[frames], dtype=torch.float32)
        for x in (cap.motion.pose, cap.motion.root_rotation, cap.motion.root_translation)
    )
    sources = {
        "encoder": enc,
        "mean latent": mean_train_latent(net, scene, d.device, loaded.config.texture_source).cpu().expand_as(enc),
    }
    for spec in a.predictors:
        label, _, paths = spec.partition("=")
        ms = [predictor_from_checkpoint(Path(p)) for p in paths.split("+")]  # A+B+...: their step-wise ensemble
        m = ms[0] if len(ms) == 1 else PredictorEnsemble(ms).eval()
        with torch.no_grad():
            sources[f"{label} zero init"] = m.rollout(P, R, Tr, m.zero_latents())
            sources[f"{label} encoder init"] = m.rollout(P, R, Tr, enc[0], first_is_given=True)
            if m.initial is not None and bool(m.initial_ready):
                sources[f"{label} pose only"] = m.initial_latents(P)  # drive mode pose_regression: no memory
    if a.oracles:
        if a.predictors:
            first = predictor_from_checkpoint(Path(a.predictors[0].partition("=")[2].split("+")[0]))
            sources["oracle: encoder clamped"] = first.clamp_latents(enc)
        # a constant that knows the test segment: how much of the gain is the segment's level, not its frames
        sources["oracle: test frames' mean latent"] = enc.mean(0, keepdim=True).expand_as(enc)
        sources.update(
            oracle_latents(cap.root, targets, frames, np.asarray(cap.motion.root_rotation), np.asarray(cap.motion.pose))
        )
    picks = list(range(0, T, a.every))
    sse = {k: 0.0 for k in sources}
    npx = 0
    t0 = time.perf_counter()
    with torch.no_grad():
        for t in picks:
            x = d.check_inputs(motion_inputs(motion, t))
            gts = load_ground_truth(cap, frames[t], cams, a.image_scale, d.bg.cpu())
            for k, lat in sources.items():
                imgs = d.render(x, lat[t].to(d.device))[0]
                for c in cams:
                    gi, gm = gts[c]
                    m = gm > 0.5
                    sse[k] += float(((imgs[c].cpu() - gi) ** 2)[m].sum())
            npx += sum(int((gts[c][1] > 0.5).sum()) * 3 for c in cams)
    psnr = {k: float(10 * np.log10(1.0 / max(v / max(npx, 1), 1e-12))) for k, v in sse.items()}
    gain = psnr["encoder"] - psnr["mean latent"]
    out = {
        "run": str(a.run),
        "test_frames": T,
        "rendered_frames": len(picks),
        "cameras": cams,
        "seconds": time.perf_counter() - t0,
        "sources": {},
    }
    for k in sources:
        out["sources"][k] = {
            "psnr_fg": psnr[k],
            "recovery": (psnr[k] - psnr["mean latent"]) / gain if gain >= 0.1 else None,  # results_table.py's bound
            "l1_to_encoder": float((sources[k] - enc).abs().mean()),
        }
        print(json.dumps({"source": k, **out["sources"][k]}))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
