"""``avatar-prep synth``: build a synthetic capture, the first capture source of the pipeline.

The command lives here, with the generator, so ``prep`` knows synth only through this one class that
:mod:`gsavatar.prep.cli` registers as a subcommand (docs/architecture.md). ``python -m gsavatar.synth.make``
is the same generator with every preset field exposed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from gsavatar.data_schema import load_capture
from gsavatar.synth.body import default_anny_cache
from gsavatar.synth.fairness import few_event_states
from gsavatar.synth.make import make_capture
from gsavatar.synth.presets import preset
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.outdir import claim_output_dir


@dataclass
class Synth:
    """Build a synthetic capture (real anny body + real CMU mocap) in capture format v1."""

    out: Path
    """Output capture directory."""
    preset: Literal["tiny", "small", "small_lit", "small_random", "second", "second_lit", "hard"] = "tiny"
    """Size/difficulty preset (tiny: tests, small: demo, small_random: appearance random in time, second: another
    body/motion/mechanisms, small_lit / second_lit: the lit captures before 2026-12-08, hard: stability cases)."""
    seed: int | None = None
    """Random seed (same seed -> identical capture); None: the preset's."""
    anny_cache: Path | None = None
    """Cache of the anny body build (default: $ANNY_CACHE_DIR or ~/.cache/gsavatar/anny)."""
    overwrite: bool = False
    """Replace an existing capture in ``out`` (otherwise a valid one is reused)."""
    force_out: bool = False
    """Write into a non-empty ``out`` that holds no capture (refused otherwise, so a user's files are never
    overwritten)."""

    def run(self) -> None:
        cfg = preset(self.preset) if self.seed is None else preset(self.preset, seed=self.seed)
        if (Path(self.out) / "capture.json").exists() and not self.overwrite:
            load_capture(self.out)  # validates; an existing complete capture is reused, not rebuilt
            print(f"{self.out} already holds a valid capture; reusing it (--overwrite to rebuild)")
            return
        # not registered as an output root: it fills the anny cache too
        claim_output_dir(Path(self.out), "capture", self.force_out, "--force-out")
        make_capture(cfg, Path(self.out), self.anny_cache or default_anny_cache(), overwrite=self.overwrite)
        print(f"capture written to {self.out}")
        fair = Path(self.out) / "gt" / "fairness.json"
        if fair.exists():
            d = read_json(fair)
            print(
                f"history-caused appearance ({', '.join(e.name for e in cfg.appearance.motion_effects)}): R^2 on test "
                f"frames from the current pose {d['pose_only']:.2f}, from the last {d['history_frames']} poses "
                f"{d['history']:.2f} ({fair})"
            )
            for w in few_event_states(d, [e.name for e in cfg.appearance.motion_effects]):
                print(f"warning: {w}")
