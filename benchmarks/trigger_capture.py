"""`small` without the room's light, its ``sleeve`` hysteresis flipped by another signal of the right hand.

The capture of benchmarks/trigger_experiment.sh (docs/train.md "What a derivative trigger changes"):
``python benchmarks/trigger_capture.py OUT [SIGNAL]`` with SIGNAL one of the motion-effect signals (default
``speed``; the preset's is ``height``). Everything else is the ``small`` preset rendered with ``shading=False``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from gsavatar.synth.body import default_anny_cache
from gsavatar.synth.make import make_capture
from gsavatar.synth.presets import PRESETS, SynthConfig


def trigger_config(signal: str) -> SynthConfig:
    """The ``small`` preset, unlit, with the ``sleeve`` effect's signal replaced by ``signal``."""
    cfg = PRESETS["small"]
    effects = tuple(
        dataclasses.replace(e, signal=signal) if e.name == "sleeve" else e for e in cfg.appearance.motion_effects
    )
    if not any(e.name == "sleeve" for e in effects):
        raise ValueError("the small preset has no 'sleeve' motion effect")
    for e in effects:
        e.check()  # an unknown signal is refused here, before any rendering
    return dataclasses.replace(
        cfg, shading=False, appearance=dataclasses.replace(cfg.appearance, motion_effects=effects)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="capture directory to write (must not hold a capture)")
    ap.add_argument("signal", nargs="?", default="speed", help="the sleeve's new signal (default: speed)")
    args = ap.parse_args()
    try:
        cfg = trigger_config(args.signal)
    except ValueError as e:
        raise SystemExit(f"trigger_capture.py: {e}") from None
    make_capture(cfg, args.out, default_anny_cache(), progress=True)


if __name__ == "__main__":  # the renderer's worker processes re-import this file
    main()
