"""Accuracy of UV texel projection on synthetic captures (docs/prep.md figures).

    python benchmarks/prep_accuracy.py --out out/bench_prep [--presets small_unshaded hard_unshaded small]

For each capture variant: build it (skipped if present), run ``avatar-prep all`` into a dataset,
then report coverage and PSNR vs the ground-truth albedo on texels seen by >= 2 views, for
median-band and plain-mean fusion. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

VARIANTS = {  # the shaded variant is the lit `small_lit` (`small` is unlit since 2026-12-08, and the same as unshaded)
    "small": ("small_lit", {}),
    "small_unshaded": ("small", {"shading": False}),
    "hard_unshaded": ("hard", {"shading": False}),
}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--presets", nargs="+", default=["small_unshaded", "hard_unshaded"])
    ap.add_argument("--tex-size", type=int, default=512)
    ap.add_argument("--compare-frames", type=int, default=6)
    a = ap.parse_args()
    from gsavatar.prep.cli import main as prep
    from gsavatar.prep.report import build_report
    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset

    cache = Path(os.environ.get("ANNY_CACHE_DIR", ".cache/anny"))
    rows = []
    for name in a.presets:
        base, over = VARIANTS[name]
        cap = a.out / name / "capture"
        if not (cap / "capture.json").exists():
            t = time.perf_counter()
            make_capture(preset(base, **over), cap, cache, overwrite=True)
            print(f"[{name}] capture built in {time.perf_counter() - t:.0f}s")
        ds = a.out / name / f"dataset_{a.tex_size}"
        t = time.perf_counter()
        rc = prep(
            ["all", "--capture", str(cap), "--out", str(ds), "--project.tex-size", str(a.tex_size), "--no-figures"]
        )
        if rc:
            raise SystemExit(rc)
        prep_s = time.perf_counter() - t
        rep = build_report(ds, a.out / name / f"report_{a.tex_size}", compare_mean=a.compare_frames)
        s = rep["summary"]
        rows.append((name, s, prep_s))
        print(json.dumps(s, indent=1))
    print(
        "\n| capture | tex | frames | coverage | PSNR >=2 views (median band) "
        "| PSNR >=2 views, first frames: band / mean |"
    )
    print("|---|---|---|---|---|---|")
    for name, s, _ in rows:
        mf = s.get("mean_fusion", {})
        print(
            f"| {name} | {s['tex_size']} | {s['frames']} | {s['coverage']:.1%} | "
            f"{s.get('psnr_2v', float('nan')):.2f} dB | "
            f"{mf.get('median_band', float('nan')):.2f} / {mf.get('mean', float('nan')):.2f} dB |"
        )


if __name__ == "__main__":
    main()
