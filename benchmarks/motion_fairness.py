"""Does a motion reach the same poses along different paths? The fairness check of a preset's motion effects on
another BVH motion, before rendering anything (seconds).

    PYTHONPATH=src .venv/bin/python benchmarks/motion_fairness.py --preset small \
        --bvh /usr/share/assimp/models/BVH/Boxing_Toes.bvh --start 0 [--springs-of second] [--tempo 0.35 --seed 2]

Poses the preset's body with the BVH segment (``--start`` source frame, the preset's frame count and rate), computes
the states of the preset's motion effects (``--springs-of P``: those of preset P instead, e.g. to try `small`'s springs
on another motion; ``--tempo``: the motion at another tempo variation, ``--seed``: another tempo draw) and prints
:func:`gsavatar.synth.fairness.history_fairness` per state: R^2 on the test frames from the current pose and from the
last 10 poses. On a motion that repeats a cycle (CMU 01_01's hops) a spring's phase is a function of the pose, and the
pose-only read is high (docs/train.md "Springs on a periodic motion"), unless the motion is played at a varying tempo
(docs/synth.md "Why `small` plays its motion at a varying tempo").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from gsavatar.synth.body import build_anny_body, default_anny_cache
from gsavatar.synth.fairness import history_fairness
from gsavatar.synth.make import load_motion, split_frames
from gsavatar.synth.motion_effects import effect_level, joint_signal
from gsavatar.synth.presets import PRESETS
from gsavatar.synth.render import pose_joint_positions


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="small", choices=sorted(PRESETS))
    ap.add_argument("--bvh", type=Path, default=None, help="BVH motion (default: the preset's)")
    ap.add_argument("--start", type=int, default=None, help="first source frame (default: the preset's)")
    ap.add_argument(
        "--springs-of", default=None, choices=sorted(PRESETS), help="take the motion effects of this preset"
    )
    ap.add_argument("--tempo", type=float, default=None, help="tempo_variation (default: the preset's)")
    ap.add_argument("--seed", type=int, default=None, help="seed of the tempo curve (default: the preset's)")
    a = ap.parse_args()
    cfg = PRESETS[a.preset]
    over = {}
    if a.bvh is not None:
        over["bvh_path"] = str(a.bvh)
    if a.start is not None:
        over["bvh_start"] = a.start
    if a.tempo is not None:
        over["tempo_variation"] = a.tempo
    if a.seed is not None:
        over["seed"] = a.seed
    cfg = dataclasses.replace(cfg, **over)
    effects = PRESETS[a.springs_of or a.preset].appearance.motion_effects
    if not effects:
        raise SystemExit(f"preset {a.springs_of or a.preset!r} has no motion effects")
    _, rig = build_anny_body(default_anny_cache(), decimate_to=cfg.decimate_to, seed=cfg.body_seed)
    motion = load_motion(cfg, rig)
    joints = pose_joint_positions(rig, motion.pose, motion.root_rotation, motion.root_translation)
    names = [j.name for j in rig.joints]
    levels = np.stack([effect_level(e, joint_signal(joints, names, e, cfg.fps), cfg.fps)[0] for e in effects], 1)
    train, test = (np.asarray(f) for f in split_frames(cfg))
    r = history_fairness(motion, levels, train, test, joints=joints)  # what make_capture writes to gt/fairness.json
    print(
        json.dumps(
            {
                "bvh": cfg.bvh_path,
                "start": cfg.bvh_start,
                "frames": cfg.num_frames,
                "tempo_variation": cfg.tempo_variation,
                "seed": cfg.seed,
                "states": [e.name for e in effects],
                "pose_only": r["pose_only"],
                "history": r["history"],
                "per_state": r["per_state"],
                "crossings": r["crossings"],
            }
        )
    )


if __name__ == "__main__":
    main()
