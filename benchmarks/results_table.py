"""Regenerate docs/results.md and docs/results.json: the paper's comparison on synthetic captures.

    PYTHONPATH=src .venv/bin/python benchmarks/results_table.py --runs small=out/demo second=out/cap2 \
        --out docs/results.md          # also writes docs/results.json

Per capture (``LABEL=DIR``), expects runs trained on the same dataset (``avatar-train avatar``): ``run_ours``
(with a trained predictor, ``avatar-train predictor``), optionally ``run_oracle`` (``--texture-source gt``:
the encoder reads the ground-truth albedo, an upper bound of the latent path), ``run_mmlps``
(``--variant mmlps_dagger``), ``run_nrfgca``
(``--variant nrfgca_dagger``) and, when
present, ``run_wo_local_pose`` / ``run_wo_local_pca`` and ``run_ours_tinymodel`` (``--preset tiny --steps 1200
--correctives-step 200``: the same schedule with (64, 64) anchor MLPs instead of (128, 128, 128), for speed
against error). Every row drives the held-out TEST frames
of the capture from the capture's held-out cameras (``avatar-drive``) and reports PSNR / SSIM /
LPIPS, temporal error (mean |(r_t - r_t-1) - (g_t - g_t-1)| inside the mask) and frames/s.
The locality test (paper fig. 6) perturbs one pose parameter by +0.3 rad at a test frame and
measures the mean colour change of Gaussians OUTSIDE that parameter's region of influence.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import sys
import textwrap
import time
from pathlib import Path

import torch

from gsavatar.models.batch import FrameBatch
from gsavatar.utils.io import atomic_write_json

ROWS = [
    # (label, run dir, drive mode[, predictor folder inside the run])
    ("Ours (predictor, encoder init)", "run_ours", "predictor_encoder_init"),
    ("Ours (predictor, zero init)", "run_ours", "predictor"),
    (
        "Ours, no history: N_b = 1, no velocities (encoder init)",
        "run_ours",
        "predictor_encoder_init",
        "predictor_nohist",
    ),
    ("Ours, no history: N_b = 1, no velocities (zero init)", "run_ours", "predictor", "predictor_nohist"),
    ("Ours (predictor, pose init)", "run_ours", "pose_init"),
    ("Ours, pose only: no window, no fed-back latents", "run_ours", "pose_regression"),
    ("Ours (re-init. 30)", "run_ours", "reinit"),
    ("Ours (re-init. 8)", "run_ours", "reinit8"),
    ("Ours (encoder)", "run_ours", "encoder"),
    ("Ours (training-mean latent)", "run_ours", "train_mean"),
    ("Ours, tiny MLPs (64, 64) (encoder)", "run_ours_tinymodel", "encoder"),
    ("Ours, a quarter of the Gaussians (encoder)", "run_ours_fewgauss", "encoder"),
    ("MMLPs-dagger", "run_mmlps", "predictor"),
    ("nRFGCA-dagger", "run_nrfgca", "predictor"),
    ("Ours w/o local pose (encoder)", "run_wo_local_pose", "encoder"),
    ("Ours w/o local PCA (encoder)", "run_wo_local_pca", "encoder"),
]


def drive_row(run: Path, mode: str, out: Path, image_scale: float, predictor: str = "predictor") -> dict:
    """Drive the run's test frames in ``mode`` (with the predictor in ``run/predictor``); reuses ``out/row.json``
    when it is newer than the run's checkpoints."""
    from gsavatar.drive.cli import main as drive

    cached = out / "row.json"
    ckpts = [p for p in (run / "checkpoints" / "latest.pt", run / predictor / "latest.pt") if p.exists()]
    if cached.exists() and all(cached.stat().st_mtime > p.stat().st_mtime for p in ckpts):
        row = json.loads(cached.read_text())
        if row.get("image_scale") == image_scale:
            return row
    capture = str(_capture_of(run))
    t = time.perf_counter()
    extra = []
    if mode.startswith("reinit") and mode != "reinit":  # reinitK: encoder every K frames
        extra, mode = ["--reinit-every", mode[len("reinit") :]], "reinit"
    if predictor != "predictor":
        extra += ["--predictor", str(run / predictor / "latest.pt")]
    rc = drive(
        [
            "--run",
            str(run),
            "--motion",
            capture,
            "--split",
            "test",
            "--mode",
            mode,
            "--out",
            str(out),
            "--image-scale",
            str(image_scale),
            *extra,
        ]
    )
    if rc:
        raise SystemExit(f"avatar-drive failed for {run} {mode}")
    info = json.loads((out / "drive.json").read_text())
    m = info["metrics"]
    views = info["frames"] * len(info["cameras"])
    row = {
        **m,
        "frames": info["frames"],
        "fps_drive": views / max(time.perf_counter() - t, 1e-9),
        "lpips_net": json.loads((out / "metrics.json").read_text()).get("lpips_net"),
        "image_scale": image_scale,
    }
    atomic_write_json(cached, row)
    return row


@torch.no_grad()
def locality(run: Path, param: str, delta: float = 0.3) -> dict:
    """Mean |d colour| and |d position| of Gaussians outside/inside ``param``'s region when it changes."""
    from gsavatar.models.config import SH_C0
    from gsavatar.runs.config import model_config
    from gsavatar.runs.load import load_run

    net, scene, cfg, _ = load_run(run)
    cap = scene.capture
    frame = cap.splits["test"].frames[0]
    slot = [i for i, p in enumerate(cap.rig.params) if p.name == param]
    if not slot:
        return {}
    slot = cap.rig.slot_params().index(slot[0])
    from gsavatar.train.data import ViewDataset

    data = ViewDataset(scene, "test", with_texture=net.encoder is not None)
    b = {k: (v[None] if torch.is_tensor(v) else v) for k, v in data.frame_inputs(frame).items()}
    sh = model_config(cfg).sh_degree
    lat = None
    if net.encoder is not None:
        lat = net.latents(b["texture"], None)[0]
    batch = FrameBatch.from_dict(b, lat)
    outs = []
    for d in (0.0, delta):
        pose = batch.pose.clone()
        pose[0, slot] += d
        outs.append(net(batch._replace(pose=pose), sh_degree=sh).avatar)
    h = scene.hierarchy
    active_anchor = torch.from_numpy(scene.masks.pose[:, slot])
    region = active_anchor[torch.from_numpy(h.gauss_anchor_idx)].any(1)
    # colour of each Gaussian (SH band 0) and its canonical (pose-corrective) position
    dc = ((outs[1].sh[0, :, 0] - outs[0].sh[0, :, 0]) * SH_C0).abs().mean(1)
    dx = (outs[1].canonical_means[0] - outs[0].canonical_means[0]).norm(dim=1)
    return {
        "param": param,
        "outside_colour": float(dc[~region].mean()),
        "inside_colour": float(dc[region].mean()),
        "outside_pos_mm": 1000 * float(dx[~region].mean()),
        "inside_pos_mm": 1000 * float(dx[region].mean()),
        "region_fraction": float(region.float().mean()),
    }


RUN_DIRS = (
    "run_ours",
    "run_oracle",
    "run_mmlps",
    "run_nrfgca",
    "run_wo_local_pose",
    "run_wo_local_pca",
    "run_ours_tinymodel",
    "run_ours_fewgauss",
)
SEED_RUNS = ("run_ours", "run_ours_seed1", "run_ours_seed2")  # Ours with seeds 0, 1, 2: the run-to-run spread
SEED_MODES = ("encoder", "predictor", "predictor_encoder_init", "train_mean")


def run_summary(run: Path) -> dict:
    """Evaluation numbers and training cost of one finished run (``eval/metrics.json``, ``timing.json``)."""
    ev = json.loads((run / "eval" / "metrics.json").read_text())
    out = {"variant": ev.get("variant")}
    for split in ("train_frames_heldout_cams", "test_frames_heldout_cams", "test_frames_heldout_cams_mean_latent"):
        if split in ev:
            out[split] = {k: ev[split][k] for k in ("psnr", "psnr_fg", "ssim", "lpips") if k in ev[split]}
    out["latent_gain_db"] = ev.get("latent_gain_db")
    fd = ev.get("frame_dependence")
    out["frame_dependence_ratio"] = None if fd is None else fd["ratio"]
    out["frame_dependence"] = fd
    cfg = json.loads((run / "config.json").read_text())["train"]
    out["texture_source"] = cfg.get("texture_source", "projected")
    out["params"] = param_count(run)
    t = run / "timing.json"
    if t.exists():
        out.update(
            {
                k: v
                for k, v in json.loads(t.read_text()).items()
                if k in ("steps", "seconds", "steps_per_s", "threads", "code", "commits")
            }
        )
    pe = run / "predictor" / "eval.json"
    if pe.exists():  # the code that trained the run's predictor
        out["predictor_code"] = json.loads(pe.read_text()).get("code")
    return out


def _provenance_line(summaries: dict) -> str:
    """Which commits trained the rows' runs (their ``timing.json``, predictors' ``eval.json``), so a reader can
    check that nothing in the table is older than the code it describes."""
    commits: dict[str, list[str]] = {}
    for rdir, s in summaries.items():
        for c in s.get("commits") or ["unrecorded"]:
            commits.setdefault(c, []).append(rdir)
        pc = (s.get("predictor_code") or {}).get("commit")
        if pc:
            commits.setdefault(pc, []).append(f"{rdir}/predictor")
    if not commits:
        return "Training commits: none recorded."
    parts = [f"`{c[:12]}` ({', '.join(sorted(set(r)))})" for c, r in sorted(commits.items())]
    # "unrecorded": runs trained before timing.json carried the commit
    return "Training commits (per run's `timing.json` and predictor `eval.json`): " + "; ".join(parts) + "."


def param_count(run: Path) -> dict:
    """Trainable parameters of a run's avatar (with its encoder and face embedding) and of its predictor."""

    def count(path: Path) -> int:
        state = torch.load(path, map_location="cpu", weights_only=False)
        modules = state.get("modules", state)
        tensors = [v for m in modules.values() if isinstance(m, dict) for v in m.values() if torch.is_tensor(v)]
        return int(sum(v.numel() for v in tensors if v.is_floating_point()))

    out = {"avatar": count(run / "checkpoints" / "latest.pt")}
    if (run / "predictor" / "latest.pt").exists():
        out["predictor"] = count(run / "predictor" / "latest.pt")
    return out


def _mean_std(values: list[float]) -> dict:
    """Mean, sample standard deviation and range of a few runs' numbers."""
    v = torch.tensor(values, dtype=torch.float64)
    std = float(v.std()) if len(values) > 1 else 0.0
    return {"values": values, "mean": float(v.mean()), "std": std, "range": float(v.max() - v.min())}


def seed_spread(runs: Path, image_scale: float) -> dict:
    """Ours trained with the seeds of :data:`SEED_RUNS`: per mode the test PSNR inside the mask of each seed,
    mean, sample std and range; the predictor's recovery likewise."""
    per_mode: dict[str, list[float]] = {m: [] for m in SEED_MODES}
    recovery, used = [], []
    for rdir in SEED_RUNS:
        run = runs / rdir
        if not (run / "eval" / "metrics.json").exists() or not (run / "predictor" / "eval.json").exists():
            continue
        print(f"[results] {runs.name}: seed spread {rdir}", flush=True)
        got = {m: drive_row(run, m, runs / "drive" / f"{rdir}_{m}", image_scale)["psnr_fg"] for m in SEED_MODES}
        for m, v in got.items():
            per_mode[m].append(v)
        gain = got["encoder"] - got["train_mean"]
        # a ratio of two small differences says nothing: recovery only where the encoder gains >= 0.1 dB
        recovery.append((got["predictor"] - got["train_mean"]) / gain if gain >= 0.1 else float("nan"))
        used.append(rdir)
    if len(used) < 2:
        return {}
    rec = [r for r in recovery if r == r]
    return {
        "runs": used,
        "psnr_fg": {m: _mean_std(v) for m, v in per_mode.items()},
        "recovery": _mean_std(rec) if rec else None,
    }


def grid_picture(runs: Path, drive_tags: dict[str, str], out: Path) -> dict:
    """One test frame seen by one held-out camera: the ground truth beside every row's render (the frames its
    ``avatar-drive`` wrote into ``runs/drive/TAG``, 8-bit PNG), PSNR inside the mask under each. The frame is where
    the encoder's render differs most from the training-mean latent's (the appearance the latent carries), the
    camera the first test one. ``drive_tags``: row label -> drive folder. -> the picture's record."""
    import cv2
    import numpy as np

    from gsavatar.data_schema import load_capture
    from gsavatar.drive.compare import body_box
    from gsavatar.drive.metrics import load_ground_truth
    from gsavatar.metrics.image import psnr
    from gsavatar.utils.io import read_image, write_image

    drives = {
        lab: runs / "drive" / tag for lab, tag in drive_tags.items() if (runs / "drive" / tag / "frames").is_dir()
    }
    if not drives:
        return {}
    cap = load_capture(_capture_of(runs / "run_ours"))
    cam = cap.splits["test"].cameras[0]
    T = len(cap.splits["test"].frames)
    enc, mean = drives.get("Ours (encoder)"), drives.get("Ours (training-mean latent)")
    t = T // 2
    if enc is not None and mean is not None:
        diffs = [
            np.abs(
                read_image(enc / "frames" / cam / f"{i:06d}.png") - read_image(mean / "frames" / cam / f"{i:06d}.png")
            ).mean()
            if (enc / "frames" / cam / f"{i:06d}.png").exists()
            else -1.0
            for i in range(T)
        ]
        t = int(np.argmax(diffs))
    frame = cap.splits["test"].frames[t]
    gt, mask = load_ground_truth(cap, frame, [cam], 1.0, torch.zeros(3))[cam]
    y0, y1, x0, x1 = body_box(mask)
    gt_b, mask_b = gt.permute(2, 0, 1)[None], (mask > 0.5)[None, None]
    H = max(256, 2 * (y1 - y0))

    def panel(img: np.ndarray, lines: list[str]) -> np.ndarray:
        a = (np.clip(img[y0:y1, x0:x1, :3], 0, 1) * 255).round().astype(np.uint8)
        w = max(1, round(a.shape[1] * H / a.shape[0]))
        a = cv2.resize(a, (w, H), interpolation=cv2.INTER_NEAREST)
        if w < 210:  # room for the caption
            a = np.pad(a, ((0, 0), ((210 - w) // 2, 210 - w - (210 - w) // 2), (0, 0)))
        foot = np.full((18 * len(lines) + 8, a.shape[1], 3), 255, np.uint8)
        for i, text in enumerate(lines):
            cv2.putText(foot, text, (4, 18 * i + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        return np.concatenate([a, foot], 0)

    panels, scores = [panel(gt.numpy(), ["ground truth", f"test frame {frame}, {cam}"])], {}
    for lab, d in drives.items():
        f = d / "frames" / cam / f"{t:06d}.png"
        if not f.exists():
            continue
        img = read_image(f)[..., :3]
        scores[lab] = float(psnr(torch.from_numpy(img).permute(2, 0, 1)[None], gt_b, mask=mask_b)[0])
        panels.append(panel(img, [*textwrap.wrap(lab, 30)[:3], f"{scores[lab]:.2f} dB (mask)"]))
    h = max(p.shape[0] for p in panels)
    panels = [np.pad(p, ((0, h - p.shape[0]), (0, 0), (0, 0)), constant_values=255) for p in panels]
    per_row = 6
    width = sum(p.shape[1] for p in panels[:per_row])
    grid_rows = []
    for i in range(0, len(panels), per_row):
        line = np.concatenate(panels[i : i + per_row], 1)
        grid_rows.append(np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0)), constant_values=255))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_image(out, np.concatenate(grid_rows, 0).astype(np.float32) / 255.0)
    return {"figure": str(out), "capture_frame": int(frame), "test_index": t, "camera": cam, "psnr_fg": scores}


MIN_ENCODER_GAIN_DB = 0.1
"""Below this gain of the encoder's latents over the training-mean latent (test frames, in the mask) the predictor's
recovery is recorded as undefined (null, with the reason) instead of a ratio of two small noisy differences."""


def recovery_fields(
    mean: float | None,
    encoder: float | None,
    zero_init: float | None,
    no_history: float | None = None,
    pose_only: float | None = None,
) -> dict:
    """results.json's predictor-recovery fields from PSNRs inside the mask (test frames, held-out cameras):
    ``predictor_recovery`` = the zero-init predictor's gain over the training-mean latent / the encoder's (and the same
    for the no-history and pose-only rows when given). With an encoder gain below :data:`MIN_ENCODER_GAIN_DB`
    (a capture whose latents buy nothing on its test frames) the recovery is ``None`` and
    ``predictor_recovery_undefined`` says why (also when one of the three rows is missing)."""
    missing = [
        name
        for name, v in (("training-mean latent", mean), ("encoder", encoder), ("zero init", zero_init))
        if v is None
    ]
    if missing:
        return {"predictor_recovery": None, "predictor_recovery_undefined": f"no driven row of: {', '.join(missing)}"}
    gain = encoder - mean
    if gain < MIN_ENCODER_GAIN_DB:  # the ratio would be noise over noise, or of the wrong sign
        out = {
            "predictor_recovery": None,
            "predictor_recovery_undefined": (
                f"the encoder's gain over the training-mean latent is {gain:+.2f} dB (< {MIN_ENCODER_GAIN_DB} dB): "
                f"no gain to divide by; the zero-init predictor's own gain is {zero_init - mean:+.2f} dB"
            ),
            "mean_latent_psnr_fg": mean,
        }
        for key, psnr in (("no_history", no_history), ("pose_only", pose_only)):
            if psnr is not None:
                out[f"predictor_recovery_{key}"] = None
        return out
    out = {"predictor_recovery": (zero_init - mean) / gain, "mean_latent_psnr_fg": mean}
    for key, psnr in (("no_history", no_history), ("pose_only", pose_only)):
        if psnr is not None:
            out[f"predictor_recovery_{key}"] = (psnr - mean) / gain
    return out


def capture_tables(
    label: str, runs: Path, image_scale: float, params: list[str], grid: Path | None = None, md_dir: Path = Path(".")
) -> tuple[list[str], dict]:
    """Markdown lines and the JSON record of one capture's runs (``runs/run_*``)."""
    rows, tags = [], {}
    for row_label, rdir, mode, *pred in ROWS:
        run = runs / rdir
        pred = pred[0] if pred else "predictor"
        if not (run / "eval" / "metrics.json").exists():  # written when training has finished
            continue
        if mode != "encoder" and rdir == "run_ours" and not (run / pred / "eval.json").exists():
            continue
        print(f"[results] {label}: {row_label}", flush=True)
        tag = f"{rdir}_{mode}" + ("" if pred == "predictor" else f"_{pred}")
        rows.append((row_label, rdir, mode, drive_row(run, mode, runs / "drive" / tag, image_scale, pred)))
        tags[row_label] = tag
    loc = []
    for rdir in ("run_ours", "run_mmlps", "run_nrfgca", "run_wo_local_pose", "run_wo_local_pca"):
        if (runs / rdir / "eval" / "metrics.json").exists():
            for p in params:
                r = locality(runs / rdir, p)
                if r:
                    loc.append((rdir, r))
    summaries = {r: run_summary(runs / r) for r in RUN_DIRS if (runs / r / "eval" / "metrics.json").exists()}
    lp = next((r[3]["lpips_net"] for r in rows if r[3].get("lpips_net")), "off")
    lines = [
        f"## {label}",
        "",
        f"Runs in `{runs}`. Held-out TEST frames (last 20% of the capture, novel poses and "
        f"appearance states) seen from the held-out cameras, driven by `avatar-drive`. Protocol `ours`: black "
        f"background, LPIPS = {lp}; protocol `ag` (Animatable Gaussians / MMLPs): ground truth white outside its "
        f"mask, full image (docs/train.md; its LPIPS needs `--ag-lpips on`, off on this CPU box).",
        "",
        "Speed against error on the same rows: *params* of the avatar (with its encoder; + the predictor's where "
        "the row uses it), *train min* and *steps/s* of the run's training (`timing.json`), *drive views/s* of "
        "`avatar-drive` on this box; *train (mask)* is the run's `avatar-train eval` on training frames from the "
        "held-out cameras with the encoder's latents (the same for every row of one run).",
        "",
        "| method | PSNR | PSNR (mask) | SSIM | LPIPS | PSNR (ag) | SSIM (ag) | temporal error | train (mask) "
        "| params | train min | steps/s | drive views/s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    f = lambda m, k, fmt: format(m[k], fmt) if m.get(k) is not None else "-"  # noqa: E731
    for row_label, rdir, mode, m in rows:
        run = summaries.get(rdir, {})
        n = run.get("params", {})
        n_params = n.get("avatar", 0) + (
            n.get("predictor", 0) if mode.startswith(("predictor", "pose_init", "pose_regression", "reinit")) else 0
        )
        m["params"] = n_params or None
        for k in ("seconds", "steps_per_s"):
            m[f"train_{k}"] = run.get(k)
        m["train_psnr_fg"] = run.get("train_frames_heldout_cams", {}).get("psnr_fg")
        minutes = f"{run['seconds'] / 60:.1f}" if run.get("seconds") else "-"
        lines.append(
            f"| {row_label} | {m['psnr']:.2f} | {m['psnr_fg']:.2f} | {m['ssim']:.4f} | {f(m, 'lpips', '.4f')} | "
            f"{f(m, 'ag_psnr', '.2f')} | {f(m, 'ag_ssim', '.4f')} | {m['temporal_error']:.4f} | "
            f"{f(m, 'train_psnr_fg', '.2f')} | {f'{n_params / 1e6:.2f}M' if n_params else '-'} | {minutes} | "
            f"{f(m, 'train_steps_per_s', '.2f')} | {m['fps_drive']:.2f} |"
        )
    if summaries:
        lines += [
            "",
            "Training runs (`avatar-train eval`, encoder latents; held-out cameras; PSNR inside the mask). "
            "*Latent gain*: test frames with the encoder's latents minus the same with the training frames' mean "
            "latent. *Frame dependence*: the avatar's per-Gaussian colour std over 24 training frames / the "
            "ground-truth albedo's at the same points (1 = all of the change, 0 = static). The oracle encodes "
            "the ground-truth albedo instead of the projected texture.",
            "",
            "| run | train frames (mask) | test frames (mask) | latent gain (dB) | frame dependence | steps | "
            "minutes | steps/s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for rdir, m in summaries.items():
            g = m.get("latent_gain_db")
            fd = m.get("frame_dependence_ratio")
            minutes = f"{m['seconds'] / 60:.1f}" if "seconds" in m else "-"
            lines.append(
                f"| {rdir} | {m['train_frames_heldout_cams']['psnr_fg']:.2f} | "
                f"{m.get('test_frames_heldout_cams', {}).get('psnr_fg', float('nan')):.2f} | "
                f"{'-' if g is None else f'{g:+.2f}'} | {'-' if fd is None else f'{fd:.2f}'} | {m.get('steps', '-')} | "
                f"{minutes} | {m.get('steps_per_s', '-')} |"
            )
    if loc:
        lines += [
            "",
            "Locality (paper fig. 6): +0.3 rad on one pose parameter at the first test frame; mean change "
            "of Gaussian colour (RGB, 0..1) and canonical position outside / inside the parameter's region.",
            "",
            (
                "| run | parameter | colour outside | colour inside | position outside (mm) "
                "| position inside (mm) | region |"
            ),
            "|---|---|---|---|---|---|---|",
        ]
        for rdir, r in loc:
            lines.append(
                f"| {rdir} | {r['param']} | {r['outside_colour']:.5f} | {r['inside_colour']:.5f} | "
                f"{r['outside_pos_mm']:.3f} | {r['inside_pos_mm']:.3f} | {r['region_fraction']:.1%} |"
            )
    spread = seed_spread(runs, image_scale)
    if spread:
        lines += [
            "",
            f"Run-to-run spread of Ours ({', '.join(spread['runs'])}: seeds 0, 1, 2; the same recipe), test frames, "
            "held-out cameras, PSNR inside the mask:",
            "",
            "| latent source | per seed (dB) | mean | std | range |",
            "|---|---|---|---|---|",
        ]
        for mode, st in spread["psnr_fg"].items():
            vals = ", ".join(f"{v:.2f}" for v in st["values"])
            lines.append(f"| {mode} | {vals} | {st['mean']:.2f} | {st['std']:.2f} | {st['range']:.2f} |")
        r = spread["recovery"]
        if r is not None:
            lines.append(
                f"| predictor recovery (zero init) | {', '.join(f'{v:.0%}' for v in r['values'])} | "
                f"{r['mean']:.0%} | {r['std']:.0%} | {r['range']:.0%} |"
            )
        else:
            lines.append("| predictor recovery (zero init) | the encoder gains < 0.1 dB: undefined | - | - | - |")
        lines += _ranking_lines(rows, spread)
    lines += ["", _provenance_line(summaries)]
    picture = grid_picture(runs, tags, grid) if grid else {}
    if picture:
        link = os.path.relpath(picture["figure"], md_dir)
        lines += [
            "",
            f"Every row on test frame {picture['capture_frame']} from {picture['camera']} (the frame where the "
            f"encoder's render differs most from the training-mean latent's; PSNR inside the mask of the 8-bit "
            f"frames `avatar-drive` wrote):",
            "",
            f"![every row on one test frame]({link})",
        ]
    record = {
        "runs_dir": str(runs),
        "seed_spread": spread,
        "grid": picture,
        "runs": summaries,
        "drive_rows": [{"method": lab, "run": rdir, "mode": mode, **m} for lab, rdir, mode, m in rows],
        "locality": [{"run": rdir, **r} for rdir, r in loc],
    }
    ours, oracle = summaries.get("run_ours", {}), summaries.get("run_oracle", {})
    if ours.get("latent_gain_db") is not None and oracle.get("latent_gain_db"):
        record["latent_gain_vs_oracle"] = ours["latent_gain_db"] / oracle["latent_gain_db"]
    by_label = {lab: m for lab, _, _, m in rows}
    mean = by_label.get("Ours (training-mean latent)", {}).get("psnr_fg")  # same frames and cameras as the rows
    record.update(
        recovery_fields(
            mean,
            *(by_label.get(f"Ours ({k})", {}).get("psnr_fg") for k in ("encoder", "predictor, zero init")),
            no_history=by_label.get("Ours, no history: N_b = 1, no velocities (zero init)", {}).get("psnr_fg"),
            pose_only=by_label.get("Ours, pose only: no window, no fed-back latents", {}).get("psnr_fg"),
        )
    )
    capture = _capture_of(runs / "run_ours") if (runs / "run_ours" / "config.json").exists() else None
    fair = capture / "gt" / "fairness.json" if capture is not None else None
    if fair is not None and fair.exists():
        f = json.loads(fair.read_text())
        record["history_fairness"] = {"pose_only": f["pose_only"], "history": f["history"]}
    lines += _summary_lines(record, mean)
    return lines, record


RANKING = ("Ours (encoder)", "Ours (re-init. 30)", "Ours (predictor, encoder init)", "MMLPs-dagger")


def _ranking_lines(rows: list, spread: dict) -> list[str]:
    """The paper's ranking (encoder > re-init 30 > predictor > MMLPs-dagger) step by step, each difference next
    to the seed spread: a difference counts as outside it when it exceeds the largest range of Ours' numbers
    over the seeds (any latent source)."""
    by = {lab: m["psnr_fg"] for lab, _, _, m in rows}
    bound = max(st["range"] for st in spread["psnr_fg"].values())
    out = ["", f"The paper's ranking against the spread (largest range over the seeds: {bound:.2f} dB):", ""]
    for a, b in zip(RANKING, RANKING[1:]):
        if a in by and b in by:
            d = by[a] - by[b]
            verdict = "outside the spread" if abs(d) > bound else "inside the spread"
            out.append(f"- {a} - {b}: {d:+.2f} dB ({'holds' if d > 0 else 'reversed'}, {verdict})")
    return out


def _capture_of(run: Path) -> Path:
    ds = json.loads((run / "config.json").read_text())["train"]["dataset"]
    return Path(json.loads((Path(ds) / "dataset.json").read_text())["capture"])


def _summary_lines(record: dict, mean: float | None) -> list[str]:
    out = []
    if mean is not None:
        out += [
            "",
            f"Training-mean latent on the same frames and cameras (drive mode `train_mean`): PSNR (mask) {mean:.2f}.",
        ]
    if record.get("predictor_recovery") is not None:
        out.append(
            f"Predictor recovery (zero init, no texture: its gain over the training-mean latent / the encoder's): "
            f"{record['predictor_recovery']:.0%}"
            + (
                f"; without history {record['predictor_recovery_no_history']:.0%}"
                if "predictor_recovery_no_history" in record
                else ""
            )
            + (
                f"; from the current pose alone {record['predictor_recovery_pose_only']:.0%}"
                if "predictor_recovery_pose_only" in record
                else ""
            )
            + "."
        )
    if "predictor_recovery_undefined" in record:
        out.append(f"Predictor recovery: undefined, {record['predictor_recovery_undefined']}.")
    if "history_fairness" in record:
        f = record["history_fairness"]
        out.append(
            f"History fairness of the capture (R^2 of the appearance states on test frames, docs/synth.md): "
            f"current pose {f['pose_only']:.2f}, last 10 poses {f['history']:.2f}."
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", nargs="+", required=True, help="LABEL=DIR (or DIR) of each capture's runs")
    ap.add_argument("--out", type=Path, default=Path("docs/results.md"))
    ap.add_argument("--json", type=Path, default=None, help="machine-readable copy (default: --out with .json)")
    ap.add_argument("--image-scale", type=float, default=1.0)
    ap.add_argument("--params", nargs="+", default=["RightHand.rz", "Neck.ry"])
    ap.add_argument(
        "--grid-dir", type=Path, default=None, help="where results_grid_LABEL.png go (default: beside --out)"
    )
    ap.add_argument("--study-minutes", type=float, default=None, help="wall time of the study, recorded")
    a = ap.parse_args()
    torch.set_num_threads(1)
    caps = []
    for spec in a.runs:
        label, sep, d = spec.partition("=")
        caps.append((label, Path(d)) if sep else (Path(spec).name, Path(spec)))
    lines = [
        "# Results on synthetic captures",
        "",
        "Regenerated by:",
        "",
        "```bash",
        "PYTHONPATH=src .venv/bin/python benchmarks/results_table.py " + " ".join(map(shlex.quote, sys.argv[1:])),
        "```",
        "",
        "after the runs it reads were trained by `bash scripts/study.sh` (both captures) or `STUDY=1 bash "
        "scripts/demo.sh` (one: `OUT`, `PRESET`, `SYNTH`), which also run this command.",
        "",
        f"Machine: {platform.system()} {platform.machine()}, CPU only, torch {torch.__version__}; training threads "
        f"as in each run's `timing.json` (the 2-core box was shared by two trainings at a time, so steps/s are "
        f"comparable only within a table).",
        "",
    ]
    import subprocess

    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip() or None
    record = {
        "machine": {
            "system": platform.system(),
            "machine": platform.machine(),
            "torch": torch.__version__,
            "device": "cpu",
        },
        "commit": commit,
        "study_minutes": a.study_minutes,
        "captures": {},
    }
    if a.study_minutes is not None:
        lines += [f"The study (`bash scripts/study.sh`) took {a.study_minutes:.0f} minutes on this box.", ""]
    for label, runs in caps:
        grid = (a.grid_dir or a.out.parent) / f"results_grid_{label}.png"
        cl, cr = capture_tables(label, runs, a.image_scale, a.params, grid, a.out.parent)
        lines += cl + [""]
        record["captures"][label] = cr
    notes = a.out.with_name(a.out.stem + "_notes.md")  # docs/results.md -> docs/results_notes.md
    if notes.exists():  # the hand-written reading of the numbers, kept beside the regenerated tables
        lines += [notes.read_text().rstrip()]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text("\n".join(lines) + "\n")
    atomic_write_json(a.json or a.out.with_suffix(".json"), record)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
