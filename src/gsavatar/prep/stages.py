"""Stage implementations behind the ``avatar-prep`` subcommands (thin glue over the math modules)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from gsavatar.data_schema import load_capture
from gsavatar.prep.common import StageArgs, open_capture, run_frame_stage, run_single_file_stage


def default_anny_cache() -> Path:
    env = os.environ.get("ANNY_CACHE_DIR")
    return Path(env) if env else Path.home() / ".cache" / "gsavatar" / "anny"


# --------------------------------------------------------------------------- pose-template
def _pose_shard(capture_dir: str, frames: list[int]) -> dict[str, np.ndarray]:
    from gsavatar.prep.pose_template import pose_vertices

    return {"vertices": pose_vertices(load_capture(capture_dir, check_files=False), frames)}


def pose_template(args: StageArgs) -> bool:
    cap = open_capture(args)
    frames = list(range(cap.num_frames))
    return run_frame_stage("pose-template", args, {"num_vertices": int(len(cap.template.vertices))}, frames,
                           functools.partial(_pose_shard, str(args.capture)))


# --------------------------------------------------------------------------- synth
def synth(cmd) -> None:
    from gsavatar.synth.make import make_capture
    from gsavatar.synth.presets import preset_config

    cfg = preset_config(cmd.preset, seed=cmd.seed)
    make_capture(cfg, Path(cmd.out), cmd.anny_cache or default_anny_cache())
    print(f"capture written to {cmd.out}")
