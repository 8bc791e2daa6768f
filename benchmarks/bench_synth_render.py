"""One synthetic view, stage by stage: where `avatar-prep synth` spends a camera's time, and the supersample
filter against numpy's block mean it replaced (bit-identical; tests/synth/test_synth_render.py), in one run.

    PYTHONPATH=src .venv/bin/python benchmarks/bench_synth_render.py --capture out/demo/capture [--threads 1]

Uses a written capture's body (its template, motion frame 0 posed with its rig), cameras and the ground-truth
texture of frame 0, at the preset's supersampling (2: a 512^2 ray grid for a 256^2 view). Prints ms per camera of
ray casting, shading (cast and texture lookup, unlit), the old and the new box filter, the whole ``render_view``,
medians over ``--repeats``, and the largest difference of the two filters (0 expected).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from gsavatar.data_schema.capture import load_capture
from gsavatar.synth.render import FrameScene, box_downsample, pose_vertices, render_view, supersampled_rays
from gsavatar.utils.io import read_image


def median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - t0))
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--capture", type=Path, required=True, help="a capture written by `avatar-prep synth`")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1, help="open3d ray-casting threads (the synth workers use 1)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    cap = load_capture(args.capture)
    cfg = json.loads((args.capture / "gt" / "config.json").read_text())
    s = int(cfg.get("supersample", 2))
    m = cap.motion
    verts = pose_vertices(cap.template, cap.rig, m.pose[:1], m.root_rotation[:1], m.root_translation[:1])[0]
    faces, corner_uvs = np.asarray(cap.template.faces), cap.template.corner_uvs
    tex = read_image(args.capture / "gt" / "textures" / f"{0:08d}.png")
    scene = FrameScene(verts, faces, corner_uvs, nthreads=args.threads)

    rows = []
    for name, cam in sorted(cap.cameras.items()):
        rays = supersampled_rays(cam, s)
        flat = rays.reshape(-1, 6)
        color, _ = scene.shade(flat, tex, None, (0.0, 0.0, 0.0))
        big = color.reshape(cam.height * s, cam.width * s, 3)
        old = big.reshape(cam.height, s, cam.width, s, 3).mean((1, 3))
        new = box_downsample(big, s)
        rows.append(
            {
                "camera": name,
                "cast_ms": median_ms(lambda: scene.cast(flat), args.repeats),
                "shade_ms": median_ms(lambda: scene.shade(flat, tex, None, (0.0, 0.0, 0.0)), args.repeats),
                "filter_old_ms": median_ms(
                    lambda: big.reshape(cam.height, s, cam.width, s, 3).mean((1, 3)), args.repeats
                ),
                "filter_new_ms": median_ms(lambda: box_downsample(big, s), args.repeats),
                "render_view_ms": median_ms(
                    lambda: render_view(scene, cam, tex, supersample=s, rays=rays), args.repeats
                ),
                "filter_max_diff": float(np.abs(old - new).max()),
            }
        )
    keys = [k for k in rows[0] if k != "camera"]
    print(f"{len(rows)} cameras, {cam.width}x{cam.height} at supersample {s}, {args.threads} thread(s); medians in ms")
    for k in keys:
        vals = [r[k] for r in rows]
        print(f"  {k:16s} mean {np.mean(vals):8.2f}   max {np.max(vals):8.2f}")
    ratio = np.mean([r["filter_old_ms"] for r in rows]) / np.mean([r["filter_new_ms"] for r in rows])
    print(f"box filter: old / new {ratio:.1f}x")


if __name__ == "__main__":
    main()
