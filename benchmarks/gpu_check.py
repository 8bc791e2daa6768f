"""Helpers of ``benchmarks/gpu_check.sh``: environment report, dataset relocation, summary.

Not a test. The shell script runs the commands; this file only reads and writes
JSON / markdown so that the numbers it reports come from the runs' own logs:

* ``env``: Python, torch, CUDA device and gsplat versions -> JSON.
* ``relocate``: point a carried dataset's ``dataset.json`` at the carried capture
  (``avatar-prep`` records the capture's absolute path, which differs on another machine).
* ``drive-bench``: frames/s of the streaming driver (predictor + avatar + rasterizer,
  images copied back to the host), the motion replayed until ``--frames`` frames.
  ``avatar-drive`` itself always encodes an mp4 (ffmpeg), which would dominate on a GPU.
* ``summarize``: training iterations/s from the run's ``metrics.jsonl``, driving
  frames/s from ``drive_bench.json`` / ``drive.json``, the rasterizer tests from pytest's
  JUnit XML, wall times -> ``gpu_check.json`` + ``gpu_check.md``.

    python benchmarks/gpu_check.py env --out env.json
    python benchmarks/gpu_check.py relocate --dataset DS --capture CAP
    python benchmarks/gpu_check.py drive-bench --run RUN --motion CAP --frames 240 --size 512 --out db.json
    python benchmarks/gpu_check.py summarize --work W --out O --mode gpu --timings W/timings.tsv
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path


def _write_json(path: Path, obj: dict) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2) + "\n")
    os.replace(tmp, path)


def environment() -> dict:
    """Versions and the accelerator, as seen by the interpreter that runs the check."""
    import torch

    info = {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "torch": torch.__version__,
        "torch_cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "device": "cpu",
    }
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        info.update(
            device=torch.cuda.get_device_name(0),
            capability=list(torch.cuda.get_device_capability(0)),
            device_memory_gib=round(p.total_memory / 2**30, 1),
            device_count=torch.cuda.device_count(),
        )
    try:
        import importlib.metadata as md

        import importlib.util

        info["gsplat"] = md.version("gsplat")
        info["gsplat_path"] = str(Path(importlib.util.find_spec("gsplat").origin).parent)
    except Exception as e:  # noqa: BLE001 - reported, not raised
        info["gsplat"] = f"missing ({type(e).__name__})"
    return info


def relocate(dataset: Path, capture: Path) -> None:
    """Rewrite ``dataset.json``'s ``capture`` to ``capture`` (absolute)."""
    path = dataset / "dataset.json"
    obj = json.loads(path.read_text())
    obj["capture"] = str(capture.resolve())
    _write_json(path, obj)


def train_rate(metrics_jsonl: Path) -> dict:
    """Iterations/s of a fresh run from its log lines (``steps_per_s`` is cumulative since step 0).

    ``steady`` excludes everything up to the first log line: the first steps pay for
    CUDA context creation, gsplat's kernel loading and cuDNN autotuning.
    """
    lines = [json.loads(s) for s in metrics_jsonl.read_text().splitlines() if s.strip()]
    pts = [(ln["step"], ln["step"] / ln["steps_per_s"]) for ln in lines if ln.get("steps_per_s")]
    if not pts:
        return {"steps": 0}
    (s0, t0), (s1, t1) = pts[0], pts[-1]
    out = {
        "steps": s1,
        "seconds": round(t1, 3),
        "iterations_per_s": round(s1 / t1, 3),
        "first_logged_step": s0,
        "final_loss": lines[-1].get("total"),
    }
    if s1 > s0 and t1 > t0:
        out["steady_iterations_per_s"] = round((s1 - s0) / (t1 - t0), 3)
    return out


def drive_bench(run: Path, motion: Path, frames: int, size: int, views: int, device: str) -> dict:
    """Time ``Driver.frames`` (mode ``predictor``, orbit cameras) over ``frames`` frames.

    The first frame of every replay (``start``: first predictor state, lazy CUDA init)
    is excluded from ``frames_per_s``; each frame's images are on the host when timed.
    """
    import torch

    from gsavatar.drive.driver import DriveConfig, Driver
    from gsavatar.drive.motion import load_driving_motion

    d = Driver(run, DriveConfig(mode="predictor", cameras="orbit", orbit_views=views, orbit_size=size, device=device))
    m = load_driving_motion(motion, d.scene.capture.rig, d.fps)
    steady, first, n = 0.0, [], 0
    while n < frames:
        t_prev = time.perf_counter()
        for t, _ in enumerate(d.frames(m)):
            now = time.perf_counter()
            if t == 0:
                first.append(now - t_prev)
            else:
                steady += now - t_prev
            t_prev, n = now, n + 1
            if n >= frames:
                break
    timed = n - len(first)
    return {
        "mode": "predictor",
        "frames": n,
        "timed_frames": timed,
        "motion_frames": m.num_frames,
        "cameras": views,
        "image_size": size,
        "device": str(d.device),
        "frames_per_s": round(timed / steady, 3) if steady > 0 else None,
        "first_frame_seconds": [round(x, 3) for x in first],
        "cuda_max_memory_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2) if d.device.type == "cuda" else None,
    }


def junit_summary(xml_path: Path) -> dict:
    """Counts and per-test outcome of a pytest ``--junitxml`` file."""
    root = ET.parse(xml_path).getroot()
    cases = {}
    for tc in root.iter("testcase"):
        outcome = "passed"
        for child in tc:
            if child.tag in ("failure", "error"):
                outcome = "failed"
            elif child.tag == "skipped":
                outcome = "skipped: " + (child.get("message") or "")
        cases[tc.get("name")] = outcome
    n = lambda p: sum(v.startswith(p) for v in cases.values())  # noqa: E731
    return {"passed": n("passed"), "failed": n("failed"), "skipped": n("skipped"), "cases": cases}


def _dataset_facts(run: Path) -> dict:
    """Model and data sizes of the timed run (from its config and the dataset it names)."""
    facts: dict = {}
    cfg_path = run / "config.json"
    if not cfg_path.exists():
        return facts
    cfg = json.loads(cfg_path.read_text())
    train = cfg.get("train", cfg)
    for key in ("preset", "steps", "batch_size", "image_scale", "backend", "device", "lpips"):
        if key in train:
            facts[key] = train[key]
    model = cfg.get("model", {})
    for key in ("hidden", "n_basis", "latent_dim", "sh_degree"):
        if key in model:
            facts[f"model_{key}"] = model[key]
    try:
        import numpy as np

        ds = Path(train.get("dataset", ""))
        with np.load(ds / "sample_points" / "hierarchy.npz") as z:
            for part in ("anchors", "control", "gaussians"):
                facts[f"num_{part}"] = int(z[f"{part}.position"].shape[0])
        capture = Path(json.loads((ds / "dataset.json").read_text())["capture"])
        calib = json.loads((capture / "calibration.json").read_text())
        sizes = {"x".join(str(v) for v in c["imgSize"]) for c in calib.values() if "imgSize" in c}
        facts["num_cameras"] = len(calib)
        facts["camera_sizes"] = sorted(sizes)
    except Exception as e:  # noqa: BLE001 - facts are best effort
        facts["facts_error"] = f"{type(e).__name__}: {e}"
    return facts


def summarize(work: Path, out: Path, mode: str, timings: Path) -> dict:
    t = {}
    if timings.exists():
        for line in timings.read_text().splitlines():
            name, _, sec = line.partition("\t")
            if sec:
                t[name] = float(sec)
    env = json.loads((work / "env.json").read_text()) if (work / "env.json").exists() else environment()
    summary: dict = {"mode": mode, "environment": env, "wall_seconds": t}
    if (work / "pytest_rasterize.xml").exists():
        summary["rasterize_tests"] = junit_summary(work / "pytest_rasterize.xml")
    run = work / "run"
    if (run / "metrics.jsonl").exists():
        summary["train"] = {**train_rate(run / "metrics.jsonl"), **_dataset_facts(run)}
    if (work / "drive_bench.json").exists():
        summary["drive"] = json.loads((work / "drive_bench.json").read_text())
    drive_json = work / "drive" / "drive.json"
    if drive_json.exists():  # avatar-drive: includes mp4 encoding and the first frame
        d = json.loads(drive_json.read_text())
        summary["drive_cli"] = {
            "mode": d.get("mode"),
            "frames": d.get("frames"),
            "cameras": len(d.get("cameras") or []),
            "image_size": (d.get("config") or {}).get("orbit_size"),
            "seconds": d.get("seconds"),
            "frames_per_s": round(d["frames"] / d["seconds"], 3) if d.get("seconds") else None,
        }
    out.mkdir(parents=True, exist_ok=True)
    _write_json(out / "gpu_check.json", summary)
    (out / "gpu_check.md").write_text(markdown(summary))
    return summary


def markdown(s: dict) -> str:
    env = s["environment"]
    dev = env.get("device", "?")
    lines = [
        f"# gpu_check ({s['mode']})",
        "",
        f"device: {dev}; torch {env.get('torch')} (CUDA {env.get('torch_cuda')}); gsplat {env.get('gsplat')}; "
        f"python {env.get('python')}; {env.get('cpu_count')} CPUs",
        "",
    ]
    rt = s.get("rasterize_tests")
    if rt:
        cuda = rt["cases"].get("test_torch_backend_matches_gsplat_cuda", "not run")
        lines += [
            f"tests/render/test_rasterize.py: {rt['passed']} passed, {rt['failed']} failed, "
            f"{rt['skipped']} skipped; gsplat CUDA vs CPU compositor: {cuda}",
            "",
        ]
    lines += ["| measurement | value |", "| --- | --- |"]
    tr = s.get("train", {})
    if tr:
        lines.append(
            f"| train: preset / steps / batch | {tr.get('preset')} / {tr.get('steps')} / {tr.get('batch_size')} |"
        )
        lines.append(f"| train: iterations/s (all steps) | {tr.get('iterations_per_s')} |")
        lines.append(f"| train: iterations/s (after the first log line) | {tr.get('steady_iterations_per_s')} |")
    dr = s.get("drive", {})
    if dr:
        lines.append(
            f"| drive-bench: frames x cameras (size) | {dr.get('timed_frames')} timed of {dr.get('frames')} "
            f"x {dr.get('cameras')} ({dr.get('image_size')}^2 px) |"
        )
        lines.append(f"| drive-bench: frames/s (predictor + avatar + render) | {dr.get('frames_per_s')} |")
    dc = s.get("drive_cli", {})
    if dc:
        lines.append(f"| avatar-drive: frames/s incl. mp4 ({dc.get('frames')} frames) | {dc.get('frames_per_s')} |")
    for k, v in s.get("wall_seconds", {}).items():
        lines.append(f"| wall seconds: {k} | {v} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("env")
    e.add_argument("--out", type=Path, required=True)
    r = sub.add_parser("relocate")
    r.add_argument("--dataset", type=Path, required=True)
    r.add_argument("--capture", type=Path, required=True)
    b = sub.add_parser("drive-bench")
    b.add_argument("--run", type=Path, required=True)
    b.add_argument("--motion", type=Path, required=True, help="a capture directory or motion.npz")
    b.add_argument("--frames", type=int, default=240)
    b.add_argument("--size", type=int, default=512)
    b.add_argument("--views", type=int, default=1)
    b.add_argument("--device", default="auto")
    b.add_argument("--out", type=Path, required=True)
    s = sub.add_parser("summarize")
    s.add_argument("--work", type=Path, required=True)
    s.add_argument("--out", type=Path, required=True)
    s.add_argument("--mode", choices=["gpu", "cpu_smoke"], required=True)
    s.add_argument("--timings", type=Path, required=True)
    a = ap.parse_args(argv)
    if a.cmd == "env":
        info = environment()
        _write_json(a.out, info)
        print(json.dumps(info))
    elif a.cmd == "relocate":
        relocate(a.dataset, a.capture)
    elif a.cmd == "drive-bench":
        res = drive_bench(a.run, a.motion, a.frames, a.size, a.views, a.device)
        _write_json(a.out, res)
        print(json.dumps(res))
    else:
        print(markdown(summarize(a.work, a.out, a.mode, a.timings)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
