"""Accuracy report of ``project-uv`` against ground-truth UV textures (synthetic captures).

    python -m gsavatar.prep.report DATASET --out DIR [--compare-mean 4]

Metrics per frame, on texels outside the face region:
- ``coverage``: fraction of surface texels with a fused value (>= 1 view kept);
- ``psnr_2v``: PSNR of the fused texture vs ``gt/textures`` on texels seen by >= 2 views;
- with ``--compare-mean N``: the same PSNR when fusing with a plain mean instead of the
  median band (first N frames), which shows what the band buys when a view is corrupted.
Writes ``report.json`` and PNG previews (GT | projected | kept-view count).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from gsavatar.data_schema import load_capture
from gsavatar.data_schema.dataset import ShardReader, read_dataset_json, stage_dir
from gsavatar.data_schema.prepared import load_gt_texture, resize_face_mask
from gsavatar.prep.project_uv import ProjectConfig, UVProjector, load_frame_views
from gsavatar.prep.stages import load_atlas, load_atlas_face_mask
from gsavatar.utils.cli import run_reporting_errors
from gsavatar.utils.io import atomic_write_json, write_image
from gsavatar.utils.outdir import claim_output_dir


def texture_psnr(pred: np.ndarray, gt: np.ndarray, sel: np.ndarray) -> float:
    """PSNR (dB, peak 1) over selected texels. pred, gt: [S, S, 3]; sel: [S, S] bool."""
    if not sel.any():
        return float("nan")
    mse = float(np.mean((pred[sel].astype(np.float64) - gt[sel].astype(np.float64)) ** 2))
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def count_image(count: np.ndarray, max_views: int) -> np.ndarray:
    """Kept-view count as a colour map (black = 0 views). [S,S] -> [S,S,3]."""
    c = np.clip(count.astype(np.float32) / max(max_views, 1), 0, 1)
    rgb = cv2.applyColorMap((c * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[..., ::-1].astype(np.float32) / 255
    rgb[count == 0] = 0
    return rgb


def build_report(
    dataset: Path, out: Path, frames: list[int] | None = None, compare_mean: int = 0, previews: int = 3
) -> dict:
    dataset = Path(dataset)
    meta = read_dataset_json(dataset)
    cap_root = Path(meta["capture"])
    reader = ShardReader(stage_dir(dataset, "project-uv"))
    cfg = meta["stages"]["project-uv"]["config"]
    frames = frames or reader.frames
    rows = []
    cap = load_capture(cap_root, check_files=True)
    fmask = load_atlas_face_mask(dataset)
    face = resize_face_mask(fmask, int(cfg["tex_size"])) if fmask is not None else None

    tm, _, _ = load_atlas(dataset)
    surface = tm.valid & (~face if face is not None else True)
    for i, f in enumerate(frames):
        d = reader.get(f)
        tex = d["texture"].astype(np.float32)
        gt = load_gt_texture(cap_root, f, tex.shape[0])
        row = {"frame": f, "coverage": float((d["count"][surface] > 0).mean())}
        if gt is not None:
            row["psnr_2v"] = texture_psnr(tex, gt, surface & (d["count"] >= 2))
            row["psnr_1v"] = texture_psnr(tex, gt, surface & (d["count"] >= 1))
        rows.append(row)
        if i < previews:
            panels = [gt if gt is not None else np.zeros_like(tex), tex, count_image(d["count"], len(cfg["cameras"]))]
            write_image(out / f"uv_{f:08d}.png", np.concatenate(panels, 1))
    summary = {"frames": len(rows), "tex_size": cfg["tex_size"], "fusion": cfg["fusion"], "cameras": cfg["cameras"]}
    for k in ("coverage", "psnr_2v", "psnr_1v"):
        vals = [r[k] for r in rows if k in r and np.isfinite(r[k])]
        if vals:
            summary[k] = float(np.mean(vals))
    if compare_mean:
        summary["mean_fusion"] = _compare_mean(cap, dataset, cfg, frames[:compare_mean], surface)
    report = {"summary": summary, "per_frame": rows}
    atomic_write_json(out / "report.json", report)
    return report


def _compare_mean(cap, dataset: Path, cfg: dict, frames: list[int], surface: np.ndarray) -> dict:
    """Re-project ``frames`` with both fusion rules; PSNR on texels seen by >= 2 and >= 3 views
    (a median can only out-vote a bad sample when at least 3 views saw the texel)."""
    tm, _, _ = load_atlas(dataset)
    fmask = load_atlas_face_mask(dataset)
    posed = ShardReader(stage_dir(dataset, "pose-template"))
    fields = {k: v for k, v in cfg.items() if k in ProjectConfig.__dataclass_fields__}
    fields["band"] = tuple(fields["band"])
    out: dict[str, list[float]] = {"median_band": [], "mean": [], "median_band_3v": [], "mean_3v": []}
    for f in frames:
        views = load_frame_views(cap, f, cfg["cameras"])
        gt = load_gt_texture(cap.root, f, int(cfg["tex_size"]))
        if gt is None:
            continue
        for fusion in ("median_band", "mean"):
            proj = UVProjector(cap.template.faces, tm, ProjectConfig(**{**fields, "fusion": fusion}), fmask)
            r = proj.project(posed.get(f)["vertices"], views, frame=f)
            out[fusion].append(texture_psnr(r.texture, gt, surface & (r.seen >= 2)))
            out[f"{fusion}_3v"].append(texture_psnr(r.texture, gt, surface & (r.seen >= 3)))
    return {k: float(np.mean(v)) if v else float("nan") for k, v in out.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m gsavatar.prep.report", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--compare-mean", type=int, default=0, help="frames to re-project with plain-mean fusion")
    ap.add_argument("--previews", type=int, default=3)
    ap.add_argument(
        "--force",
        action="store_true",
        help="write into a non-empty --out that is not a report folder (refused otherwise)",
    )
    a = ap.parse_args(argv)

    def run() -> None:
        claim_output_dir(a.out, "report", a.force, register=True)
        rep = build_report(a.dataset, a.out, compare_mean=a.compare_mean, previews=a.previews)
        print(json.dumps(rep["summary"], indent=1))

    return run_reporting_errors(run)


if __name__ == "__main__":
    raise SystemExit(main())
