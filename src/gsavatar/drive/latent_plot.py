"""Appearance over the test frames: the ground-truth states beside the latents the predictor drives with.

    python -m gsavatar.drive.latent_plot --run out/demo/run_ours --out out/demo/latent_states.png

Top panel: the capture's history-caused appearance states (``gt/motion_states.npz``, synthetic captures;
skipped when absent). Bottom panel: the first principal component (fit on the encoder latents of every
textured frame, anchors and dims flattened) of the encoder's latents, of the predictor's free-running
latents from zero (no texture at all) and from the encoder's latents of the first test frame, and the
training-mean latent. Latents only: nothing is rendered, so it takes seconds. A JSON beside the PNG holds
the curves and, per source, the L1 to the encoder latents and the correlation of its PC1 with the encoder's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from gsavatar.data_schema import SchemaError, load_capture
from gsavatar.runs.load import predictor_from_checkpoint, run_predictor_path
from gsavatar.utils.cli import run_reporting_errors
from gsavatar.utils.io import atomic_write_json, read_npz, write_image
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.outdir import claim_output_file, record_output_file

COLOURS = {
    "encoder": (20, 20, 20),
    "predictor (zero init)": (40, 110, 230),
    "predictor (encoder init)": (30, 160, 60),
    "training mean": (150, 150, 150),
}
STATE_COLOURS = [(200, 60, 40), (40, 140, 200), (170, 80, 190), (60, 170, 120), (220, 150, 30), (100, 100, 100)]


@dataclass
class LatentPlotArgs:
    run: Path
    """Trained run with a trained predictor (``avatar-train avatar`` + ``avatar-train predictor``)."""
    out: Path
    """PNG to write (a JSON with the curves beside it)."""
    capture: Path | None = None
    """The run's capture (default: the one its dataset was prepared from)."""
    split: str = "test"
    """Split whose frames to plot (its longest run of consecutive frames)."""
    force: bool = False
    """Replace an existing ``out`` (or its JSON) that is not a gsavatar figure (refused otherwise)."""


def _longest_run(frames: np.ndarray) -> np.ndarray:
    """The longest run of consecutive values in sorted ``frames``. [n] -> [m]"""
    if len(frames) == 0:
        return frames
    cut = np.flatnonzero(np.diff(frames) != 1) + 1
    parts = np.split(frames, cut)
    return max(parts, key=len)


def _plot(
    curves: dict[str, np.ndarray], colours: dict[str, tuple], title: str, width: int = 960, height: int = 300
) -> np.ndarray:
    """A line plot with a legend, drawn with OpenCV. curves: label -> [T]. -> [height, width, 3] uint8 (RGB)."""
    img = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 50, 190, 30, 30
    vals = np.concatenate([np.asarray(v, np.float64) for v in curves.values()]) if curves else np.zeros(1)
    lo, hi = float(np.nanmin(vals)), float(np.nanmax(vals))
    if hi - lo < 1e-9:
        lo, hi = lo - 1, hi + 1
    pad = 0.05 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    w, h = width - left - right, height - top - bottom
    cv2.rectangle(img, (left, top), (left + w, top + h), (0, 0, 0), 1)
    for frac in (0.0, 0.5, 1.0):
        y = int(top + h * (1 - frac))
        cv2.putText(
            img, f"{lo + frac * (hi - lo):.2f}", (2, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA
        )
    cv2.putText(img, title, (left, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for k, (label, v) in enumerate(curves.items()):
        v = np.asarray(v, np.float64)
        n = len(v)
        xs = left + (np.arange(n) / max(n - 1, 1)) * w
        ys = top + (1 - (v - lo) / (hi - lo)) * h
        pts = np.stack([xs, ys], 1).round().astype(np.int32)[np.isfinite(ys)]
        c = colours.get(label, STATE_COLOURS[k % len(STATE_COLOURS)])
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, c, 2, cv2.LINE_AA)
        cv2.line(img, (left + w + 10, top + 12 + 18 * k), (left + w + 30, top + 12 + 18 * k), c, 2, cv2.LINE_AA)
        cv2.putText(
            img, label, (left + w + 35, top + 16 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA
        )
    cv2.putText(
        img, "test frame", (left + w // 2 - 30, height - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA
    )
    return img


def _read_targets(path: Path):
    """The encoder latents ``avatar-train predictor`` cached for its training (``targets.npz``). -> (latents
    [F, A, L], frames [F])"""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: missing; `avatar-train predictor` writes it with the predictor")
    z = read_npz(path, keys=("latents", "frames"))
    if "latents" not in z or "frames" not in z or z["latents"].ndim != 3 or len(z["frames"]) != len(z["latents"]):
        raise SchemaError(path, "latents", "expected latents [F, A, L] and frames [F]")
    return z["latents"].astype(np.float32), z["frames"].astype(np.int64)


@torch.no_grad()
def latent_curves(run: Path, capture: Path | None = None, split: str = "test") -> dict:
    """PC1 of the encoder / predictor / mean latents and the ground-truth states over ``split``'s frames."""
    run = Path(run)
    ppath = run_predictor_path(run)
    if not ppath.exists():
        raise FileNotFoundError(f"{ppath}: no trained predictor (run `avatar-train predictor --run {run}` first)")
    if capture is None:
        ds = read_json(run / "config.json")["train"]["dataset"]
        capture = Path(read_json(Path(ds) / "dataset.json")["capture"])
    cap = load_capture(capture)
    if split not in cap.splits:
        raise ValueError(f"{capture}: no split {split!r} (has {sorted(cap.splits)})")
    targets = _read_targets(ppath.parent / "targets.npz")
    model = predictor_from_checkpoint(ppath)
    t_lat, t_frames = targets
    have = set(int(f) for f in t_frames)
    frames = _longest_run(np.array(sorted(f for f in cap.splits[split].frames if f in have), np.int64))
    if len(frames) < 2:
        raise ValueError(f"{capture}: split {split!r} has fewer than 2 consecutive textured frames")
    row = {int(f): i for i, f in enumerate(t_frames)}
    enc = torch.as_tensor(t_lat[[row[int(f)] for f in frames]])  # [T, A, L]
    m = cap.motion
    P, R, T = (
        torch.as_tensor(np.asarray(a)[frames], dtype=torch.float32)
        for a in (m.pose, m.root_rotation, m.root_translation)
    )
    zero = model.rollout(P, R, T, model.zero_latents())
    teach = model.rollout(P, R, T, enc[0], first_is_given=True)
    mean = model.latent_mean.expand_as(enc)
    allx = torch.as_tensor(t_lat).reshape(len(t_frames), -1).double()
    mu = allx.mean(0)
    _, _, vh = torch.linalg.svd(allx - mu, full_matrices=False)
    pc = vh[0]
    proj = lambda x: ((x.reshape(len(frames), -1).double() - mu) @ pc).numpy()  # noqa: E731
    sources = {"encoder": enc, "predictor (zero init)": zero, "predictor (encoder init)": teach, "training mean": mean}
    curves = {k: proj(v) for k, v in sources.items()}
    e1 = curves["encoder"]
    stats = {}
    for k, v in sources.items():
        c = curves[k]
        corr = float(np.corrcoef(c, e1)[0, 1]) if c.std() > 1e-9 and e1.std() > 1e-9 else None
        stats[k] = {"l1_to_encoder": float((v - enc).abs().mean()), "pc1_corr_with_encoder": corr}
    states = {}
    gt = capture / "gt" / "motion_states.npz"
    if gt.exists():
        z = read_npz(gt, keys=("names", "levels"))
        states = {str(n): z["levels"][frames, i].astype(np.float64) for i, n in enumerate(z["names"])}
    return {
        "run": str(run),
        "capture": str(capture),
        "split": split,
        "frames": frames.tolist(),
        "pc1": {k: v.tolist() for k, v in curves.items()},
        "states": {k: v.tolist() for k, v in states.items()},
        "sources": stats,
    }


def write_latent_plot(args: LatentPlotArgs) -> dict:
    """The figure and its JSON (module docstring); returns the JSON's content."""
    claim_output_file(args.out, "figure", args.force, companions=(Path(args.out).with_suffix(".json"),))
    res = latent_curves(args.run, args.capture, args.split)
    panels = []
    if res["states"]:
        panels.append(
            _plot(
                {k: np.asarray(v) for k, v in res["states"].items()},
                {},
                "ground-truth appearance states (gt/motion_states.npz)",
            )
        )
    panels.append(
        _plot(
            {k: np.asarray(v) for k, v in res["pc1"].items()},
            COLOURS,
            f"first principal component of the latents ({res['split']} frames)",
        )
    )
    write_image(args.out, np.concatenate(panels, 0).astype(np.float32) / 255.0)
    atomic_write_json(Path(args.out).with_suffix(".json"), res)
    record_output_file(args.out, "figure")
    return res


def main(argv: list[str] | None = None) -> int:
    import tyro

    args = tyro.cli(LatentPlotArgs, args=argv)

    def run() -> None:
        res = write_latent_plot(args)
        for k, v in res["sources"].items():
            corr = "-" if v["pc1_corr_with_encoder"] is None else f"{v['pc1_corr_with_encoder']:+.2f}"
            print(f"{k:26s} L1 to encoder {v['l1_to_encoder']:.4f}  PC1 corr {corr}")
        print(f"wrote {args.out}")

    return run_reporting_errors(run)


if __name__ == "__main__":
    raise SystemExit(main())
