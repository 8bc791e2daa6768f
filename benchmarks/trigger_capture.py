"""`small_lit` (the demo capture until 2026-12-08) without the room's light, its ``sleeve`` flipped by another signal.

The capture of benchmarks/trigger_experiment.sh (docs/train.md "What a derivative trigger changes"):
``python benchmarks/trigger_capture.py OUT [SIGNAL] [--drop NAME ...]`` with SIGNAL one of the motion-effect signals
(default ``speed``; the preset's is ``height``); ``--drop`` leaves the named motion effects out (e.g. ``--drop sleeve``:
only the accumulator and the spring, the mechanisms driven by derivatives of the motion). Everything else is the
``small_lit`` preset rendered with ``shading=False``. ``--dynamic`` writes a design candidate instead (not a one-change
control): ``small_lit`` unlit with only mechanisms driven by derivatives of the motion, made stronger
(:func:`dynamic_config`); with ``--drop`` its named effects are left out (``--dynamic --drop sweat``: only the two
springs).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from gsavatar.synth.body import default_anny_cache
from gsavatar.synth.make import make_capture
from gsavatar.synth.motion_effects import MotionEffect
from gsavatar.synth.presets import PRESETS, SECOND_SPRINGS, SMALL_SPRINGS, SynthConfig

DERIVATIVE_SIGNALS = ("speed", "vertical_velocity", "vertical_acceleration")
"""Signals one pose does not show (a height does)."""


def unlit(preset: str, effects: tuple[MotionEffect, ...]) -> SynthConfig:
    """A preset rendered without the light, with these motion effects (each checked here, so an unknown signal is
    refused before any rendering)."""
    for e in effects:
        e.check()
    cfg = PRESETS[preset]
    return dataclasses.replace(
        cfg, shading=False, appearance=dataclasses.replace(cfg.appearance, motion_effects=effects)
    )


def trigger_config(signal: str, drop: tuple[str, ...] = ()) -> SynthConfig:
    """The ``small_lit`` preset, unlit, with the ``sleeve`` effect's signal replaced by ``signal`` and the effects
    named in ``drop`` left out."""
    cfg = PRESETS["small_lit"]
    names = [e.name for e in cfg.appearance.motion_effects]
    if "sleeve" not in names:
        raise ValueError("the small_lit preset has no 'sleeve' motion effect")
    unknown = sorted(set(drop) - set(names))
    if unknown:
        raise ValueError(f"--drop {unknown}: the small_lit preset's motion effects are {names}")
    if set(drop) == set(names):
        raise ValueError("--drop would leave no motion effect")
    effects = tuple(
        dataclasses.replace(e, signal=signal) if e.name == "sleeve" else e
        for e in cfg.appearance.motion_effects
        if e.name not in drop
    )
    return unlit("small_lit", effects)


def dynamic_config(drop: tuple[str, ...] = ()) -> SynthConfig:
    """``small_lit`` unlit, every motion effect driven by a derivative of the motion, stronger than the preset's: the
    ``sweat`` accumulator darkens by up to 80% (50%), the ``hem`` spring tints a wider band (0.50-0.70 of the body
    height instead of 0.56-0.66), and the ``sleeve`` hysteresis on the hand's height (which a no-history predictor
    latches from its own latents) is replaced by ``flap``, a spring (1.2 Hz, damping 0.3) on the feet's vertical
    acceleration that dyes the trousers. ``drop`` leaves the named effects of the candidate out (``sweat``, ``hem``,
    ``flap``)."""
    cfg = PRESETS["small_lit"]
    names = {"flap" if e.name == "sleeve" else e.name for e in cfg.appearance.motion_effects}
    unknown = sorted(set(drop) - names)
    if unknown:
        raise ValueError(f"--drop {unknown}: the --dynamic capture's motion effects are {sorted(names)}")
    if set(drop) == names:
        raise ValueError("--drop would leave no motion effect")
    effects = []
    for e in cfg.appearance.motion_effects:
        if e.name == "sweat":
            effects.append(dataclasses.replace(e, strength=0.8))
        elif e.name == "hem":
            effects.append(dataclasses.replace(e, y_range=(0.50, 0.70)))
        elif e.name == "sleeve":
            effects.append(next(f for f in SMALL_SPRINGS if f.name == "flap"))  # the `small` preset's since then
    return unlit("small_lit", tuple(e for e in effects if e.name not in drop))


def second_springs_config() -> SynthConfig:
    """``second_lit`` (CMU 01_03, another body and seed) unlit, its history-caused appearance three springs only
    (:data:`gsavatar.synth.presets.SECOND_SPRINGS`): the experiment that made them the ``second`` preset on
    2026-12-08 (which this equals but for its name). 01_03's motion is not a repeated cycle, so no single pose tells a
    spring's phase (unlike ``small_lit``'s hopping: docs/train.md "Springs on a periodic motion")."""
    return unlit("second_lit", SECOND_SPRINGS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="capture directory to write (must not hold a capture)")
    ap.add_argument("signal", nargs="?", default="speed", help="the sleeve's new signal (default: speed)")
    ap.add_argument("--drop", nargs="*", default=[], metavar="NAME", help="motion effects to leave out")
    ap.add_argument("--dynamic", action="store_true", help="the design candidate of dynamic_config() instead")
    ap.add_argument("--second-springs", action="store_true", help="second_springs_config() instead")
    args = ap.parse_args()
    try:
        if args.second_springs:
            cfg = second_springs_config()
        elif args.dynamic:
            cfg = dynamic_config(tuple(args.drop))
        else:
            cfg = trigger_config(args.signal, tuple(args.drop))
    except ValueError as e:
        raise SystemExit(f"trigger_capture.py: {e}") from None
    make_capture(cfg, args.out, default_anny_cache(), progress=True)


if __name__ == "__main__":  # the renderer's worker processes re-import this file
    main()
