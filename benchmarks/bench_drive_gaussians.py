"""Frames/s of live Gaussian generation (what ``avatar-drive --view`` does per frame, no rasterization).

    PYTHONPATH=src OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_drive_gaussians.py \
        --run out/demo/run_ours --frames 60 --threads 1

Per frame: the latent source's step (``--mode``, default the appearance predictor), the avatar's
forward pass, covariances from scales and quaternions, SH -> RGB for a viewing direction, and the
copy to numpy arrays (:class:`gsavatar.drive.live.LiveGaussians`), driven by the run's own capture.
Prints frames/s and each part's share; the avatar forward is split into its parts by timing the
functions it calls (pose head, control/offset interpolation, activations, skinning transforms, LBS
blend, posing: polar factor, quaternion <-> matrix). Then the same for the ``paper`` preset's model
built untrained on the run's dataset (``--paper-dataset`` for another; ``--no-paper`` skips it)
with an untrained paper-size predictor. ``--json FILE`` also writes the numbers.
"""

from __future__ import annotations

import argparse
import functools
import json
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import gsavatar  # noqa: F401  (first: sets GOMP_SPINCOUNT before torch loads libgomp, as the CLIs do)
import numpy as np
import torch

from gsavatar.drive.driver import DriveConfig, Driver, motion_inputs
from gsavatar.drive.live import LiveGaussians
from gsavatar.models.kernels import path_report, reset_paths
from gsavatar.drive.motion import load_driving_motion
from gsavatar.models import avatar as avatar_mod
from gsavatar.models import gaussians as gm

FORWARD_PARTS = {  # name -> (module, attribute); indented ones are called by "posing"; times are exclusive
    "pose head (anchor MLPs + bases)": (avatar_mod.GaussianAvatar, "pose_head"),
    "interpolation (ctrl, offsets, skin)": (gm, "sparse_interpolate"),
    "activations": None,
    "skinning transforms": (avatar_mod, "skinning_transforms"),
    "LBS + posing (fused at inference)": (gm, "pose_lbs"),
    "LBS blend": (gm, "blend_affine"),
    "posing": (gm, "pose_gaussians"),
    "  polar factor": (gm, "polar_rotation"),
    "  quat -> matrix": (gm, "quat_to_matrix"),
    "  matrix -> quat": (gm, "matrix_to_quat"),
}
ACTIVATIONS = ("activate_scale", "activate_quat", "activate_sh0", "activate_shn", "add_delta")


def _instrument(times: dict[str, float]) -> None:
    """Wrap the functions the avatar forward calls so each call adds its *exclusive* seconds to ``times``
    (time in a timed callee counts for the callee only, so the parts add up to the forward)."""
    stack: list[list[float]] = []

    def timed(name, fn):
        @functools.wraps(fn)
        def wrapper(*a, **k):
            stack.append([0.0])
            tic = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                dt = time.perf_counter() - tic
                child = stack.pop()[0]
                times[name] += dt - child
                if stack:
                    stack[-1][0] += dt

        return wrapper

    for name, where in FORWARD_PARTS.items():
        if where is None or name.startswith("pose head"):
            continue
        mod, attr = where
        setattr(mod, attr, timed(name, getattr(mod, attr)))
    for attr in ACTIVATIONS:
        setattr(gm, attr, timed("activations", getattr(gm, attr)))
    cls = avatar_mod.GaussianAvatar
    orig_forward = cls.forward

    def forward(self, *a, **k):  # the pose head is an nn.Module attribute: time it per instance call
        head = self.pose_head
        if not getattr(head, "_bench_timed", False):
            head.forward = timed("pose head (anchor MLPs + bases)", head.forward)
            head._bench_timed = True
        return orig_forward(self, *a, **k)

    cls.forward = forward


def measure(driver: Driver, motion, frames: int, warmup: int, sh0_only: bool, times: dict[str, float]) -> dict:
    """Time ``frames`` frames of live generation after ``warmup``; -> frames/s and seconds per part."""
    live = LiveGaussians(driver, sh0_only=sh0_only)
    T = motion.num_frames
    eye = np.array([0.0, -3.0, 1.0], np.float32)
    live.start(motion_inputs(motion, 0))
    for t in range(warmup):
        live.next(motion_inputs(motion, t % T), eye)
    live.reset_timings()
    times.clear()
    tic, cpu = time.perf_counter(), time.process_time()
    for t in range(warmup, warmup + frames):
        live.next(motion_inputs(motion, t % T), eye)
    total, cpu = time.perf_counter() - tic, time.process_time() - cpu
    av = driver.net.avatar
    return {
        "fps": frames / total,
        "ms_per_frame": 1e3 * total / frames,
        "gaussians": av.num_gaussians,
        "frames_per_cpu_s": frames / cpu,
        "anchors": av.num_anchors,
        "hidden": list(av.config.hidden),
        "sh_degree": driver.sh_degree,
        "parts_s": dict(live.timings),
        "forward_parts_s": dict(times),
        "total_s": total,
        "frames": frames,
    }


def report(label: str, r: dict) -> None:
    total = r["total_s"]
    print(
        f"\n{label}: {r['fps']:.1f} frames/s ({r['ms_per_frame']:.1f} ms/frame; {r['gaussians']} Gaussians, "
        f"{r['anchors']} anchors, MLP {r['hidden']}, SH degree {r['sh_degree']}; {r['frames']} frames; "
        f"{r['frames_per_cpu_s']:.1f} frames per CPU-second of the process, less disturbed by other jobs)"
    )
    p, f = r["parts_s"], r["forward_parts_s"]
    rows = [("predictor (latent source step)", p.get("predictor", 0.0)), ("avatar forward", p.get("avatar", 0.0))]
    rows += [("  " + k + (" (rest)" if k == "posing" else ""), f.get(k, 0.0)) for k in FORWARD_PARTS]
    rows.append(("  other (inputs, PCA, stacking)", p.get("avatar", 0.0) - sum(f.values())))
    rows.append(("covariance + SH -> RGB (fused)", p.get("covariance + SH -> RGB", 0.0)))
    rows.append(("loop / motion inputs", total - sum(p.values())))
    for name, s in rows:
        print(f"  {name:<36s} {1e3 * s / r['frames']:8.2f} ms  {100 * s / total:5.1f} %")


def paper_driver(dataset: Path, mode: str) -> Driver:
    """An untrained ``paper``-preset avatar (and paper-size predictor) on ``dataset``."""
    from gsavatar.data_schema.prepared import load_scene
    from gsavatar.models.net import build_net
    from gsavatar.models.predictor import PredictorConfig
    from gsavatar.runs.config import TrainConfig, model_config, resolve
    from gsavatar.runs.load import LoadedRun
    from gsavatar.train.predictor import build_predictor

    scene = load_scene(dataset)
    cfg = resolve(TrainConfig(dataset=dataset, out=Path(tempfile.gettempdir()) / "unused", preset="paper"))
    mcfg = model_config(cfg)
    net = build_net(scene, mcfg, 0).eval()
    net.avatar.pack_bases_()  # as load_run does on CPU
    pred = build_predictor(scene, PredictorConfig(), net.avatar.latent_in, mcfg.pca).eval()
    return Driver(
        Path("<untrained paper>"),
        DriveConfig(mode=mode, device="cpu", cameras="orbit"),
        loaded=LoadedRun(net, scene, cfg, 0),
        predictor=pred,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=Path("out/demo/run_ours"), help="trained run (small preset)")
    ap.add_argument("--paper-dataset", type=Path, default=None, help="dataset of the untrained paper model")
    ap.add_argument("--no-paper", action="store_true")
    ap.add_argument("--mode", default="predictor")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the 2-core box: 1 or 2)")
    ap.add_argument("--sh0-only", action="store_true", help="colour from SH band 0 (no view direction)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    times: dict[str, float] = defaultdict(float)
    _instrument(times)
    results = {"threads": torch.get_num_threads(), "mode": a.mode}
    d = Driver(a.run, DriveConfig(mode=a.mode, device="cpu", cameras="orbit"))
    motion = load_driving_motion(d.scene.capture.root, d.scene.capture.rig, d.fps)
    reset_paths()
    results["run"] = measure(d, motion, a.frames, a.warmup, a.sh0_only, times)
    results["run"]["kernel_paths"] = path_report()  # compiled or torch per fast kernel, and why
    report(f"{a.run} (preset {d.train_cfg.preset}, trained, mode {a.mode})", results["run"])
    for name, p in results["run"]["kernel_paths"].items():
        print(f"  path {name:<26s} compiled {p['compiled']:5d}  torch {p['torch']:5d}  {p['why_torch'] or ''}")
    if not a.no_paper:
        dp = paper_driver(a.paper_dataset or Path(d.scene.dataset), a.mode)
        results["paper"] = measure(dp, motion, max(a.frames // 4, 5), 2, a.sh0_only, times)
        report("preset paper (untrained)", results["paper"])
    print(
        f"\ntorch threads {results['threads']}; "
        f"load average {' '.join(f'{x:.2f}' for x in __import__('os').getloadavg())}"
    )
    if a.json:
        a.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
