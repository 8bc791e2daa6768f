"""``avatar-prep``: staged, resumable data preparation. Each stage is a subcommand.

    avatar-prep synth --out cap --preset tiny
    avatar-prep all --capture cap --out ds
    avatar-prep verify ds
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

from gsavatar.data_schema import SchemaError
from gsavatar.prep import stages
from gsavatar.prep.common import TIMINGS, StageArgs


@dataclass
class PoseTemplate(StageArgs):
    """Pose the template by LBS for every frame; writes sharded posed vertices."""

    def run(self) -> None:
        stages.pose_template(self)


@dataclass
class Verify:
    """Check every checksum of a dataset (stage files and shards)."""

    dataset: tyro.conf.Positional[Path]

    def run(self) -> None:
        from gsavatar.data_schema.dataset import verify_dataset

        problems = verify_dataset(self.dataset)
        if problems:
            for p in problems:
                print(f"FAIL {p}", file=sys.stderr)
            raise SystemExit(1)
        print(f"{self.dataset}: all checksums ok")


@dataclass
class Synth:
    """Build a synthetic capture (real anny body + real CMU mocap) in capture format v1."""

    out: Path
    """Output capture directory."""
    preset: Literal["tiny", "small", "hard"] = "tiny"
    """Size/difficulty preset (tiny: tests, small: demo, hard: stability cases)."""
    seed: int = 0
    """Random seed (same seed -> identical capture)."""
    anny_cache: Path | None = None
    """Cache of the anny body build (default: $ANNY_CACHE_DIR or ~/.cache/gsavatar/anny)."""

    def run(self) -> None:
        stages.synth(self)


COMMANDS: dict[str, type] = {
    "synth": Synth,
    "pose-template": PoseTemplate,
    "verify": Verify,
}


def main(argv: list[str] | None = None) -> int:
    cmd = tyro.extras.subcommand_cli_from_dict(
        {k: v for k, v in COMMANDS.items()}, prog="avatar-prep", description=__doc__, args=argv
    )
    try:
        cmd.run()
    except SchemaError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if TIMINGS:
        print("stage timings: " + ", ".join(f"{k} {v:.1f}s" for k, v in TIMINGS.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
