"""``avatar-prep``: staged, resumable data preparation. Each stage is a subcommand.

avatar-prep synth --out cap --preset tiny
avatar-prep import --layout thuman4 --src subject00 --smplx-model SMPLX_NEUTRAL.npz --out cap
avatar-prep fit-body --capture cap --keypoints openpose_json --out cap_fitted
avatar-prep all --capture cap --out ds
avatar-prep verify ds
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import tyro

from gsavatar.data_schema.dataset import verify_dataset
from gsavatar.prep.common import StageArgs
from gsavatar.prep.configs import LocalizeConfig, SamplePointsConfig
from gsavatar.prep.project_uv import ProjectConfig
from gsavatar.prep.table import STAGES, Stage, default_configs, run_stages
from gsavatar.importers.cli import Import  # the capture sources' commands: the one prep -> importers import
from gsavatar.synth.cli import Synth  # and the one prep -> synth import (docs/architecture.md)
from gsavatar.fitting.cli import FitBody  # and prep -> fitting (body poses from 2D keypoints)
from gsavatar.utils.cli import parse_args, run_reporting_errors


def stage_command(stage: Stage) -> type:
    """The ``avatar-prep <stage>`` subcommand: the common :class:`StageArgs` flags and the stage's config it
    holds (``config``, its fields as flags without a prefix, their defaults the config's); runs the stage after
    the upstream stages it needs (:func:`gsavatar.prep.table.run_stages`)."""

    def configs(self) -> dict[str, object]:
        return {stage.name: self.config}

    def run(self) -> None:
        run_stages(self, self.configs())

    name = "".join(w.capitalize() for w in stage.name.split("-"))  # uv-atlas -> UvAtlas
    config = (Annotated[stage.config, tyro.conf.arg(name="")], field(default_factory=stage.config))
    return dataclasses.make_dataclass(
        name,
        [("config", *config)],
        bases=(StageArgs,),
        namespace={"configs": configs, "run": run, "__doc__": stage.config.__doc__, "__module__": __name__},
    )


@dataclass
class All(StageArgs):
    """Run every stage in order, skipping those whose outputs are complete and valid."""

    project: ProjectConfig = field(default_factory=ProjectConfig)
    """Projection settings."""
    sample: SamplePointsConfig = field(default_factory=SamplePointsConfig)
    """Point counts of sample-points (e.g. ``--sample.gaussians 4000`` for a smaller-Gaussian-count dataset)."""
    figures: bool = LocalizeConfig.figures
    """Render the localization figures (pyvista off-screen)."""

    def configs(self) -> dict[str, object]:
        """Every stage's defaults, with ``--project.*`` set on project-uv's, ``--sample.*`` as sample-points' and
        ``--figures`` on localize's."""
        c = default_configs()
        c["project-uv"] = dataclasses.replace(c["project-uv"], project=self.project)
        c["sample-points"] = self.sample
        c["localize"] = dataclasses.replace(c["localize"], figures=self.figures)
        return c

    def run(self) -> None:
        run_stages(self, self.configs())


@dataclass
class Verify:
    """Check every checksum of a dataset (stage files and shards)."""

    dataset: tyro.conf.Positional[Path]

    def run(self) -> None:
        problems = verify_dataset(self.dataset)
        if problems:
            for p in problems:
                print(f"FAIL {p}", file=sys.stderr)
            raise SystemExit(1)
        print(f"{self.dataset}: all checksums ok")


COMMANDS: dict[str, type] = {
    "synth": Synth,
    "import": Import,
    "fit-body": FitBody,
    **{s.name: stage_command(s) for s in STAGES},
    "all": All,
    "verify": Verify,
}


def parse(argv: list[str] | None = None):
    """The subcommand object ``argv`` asks for (``--help`` exits here)."""
    return tyro.extras.subcommand_cli_from_dict(dict(COMMANDS), prog="avatar-prep", description=__doc__, args=argv)


def main(argv: list[str] | None = None) -> int:
    cmd = parse_args(lambda: parse(argv))  # a stage config that refuses a value: exit 2 naming it
    if isinstance(cmd, int):
        return cmd
    rc = run_reporting_errors(cmd.run)
    if rc:
        return rc
    timings = getattr(cmd, "timings", {})  # StageArgs commands record the stages they ran
    if timings:
        print("stage timings: " + ", ".join(f"{k} {v:.1f}s" for k, v in timings.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
