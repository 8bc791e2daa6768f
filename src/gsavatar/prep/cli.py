"""``avatar-prep``: staged, resumable data preparation. Each stage is a subcommand.

    avatar-prep synth --out cap --preset tiny
    avatar-prep all --capture cap --out ds
    avatar-prep verify ds
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro

from gsavatar.prep import stages
from gsavatar.prep.common import StageArgs
from gsavatar.prep.project_uv import ProjectConfig
from gsavatar.synth.cli import Synth  # the one prep -> synth import: the capture source's command (docs/architecture.md)
from gsavatar.utils.cli import run_reporting_errors


@dataclass
class PoseTemplate(StageArgs):
    """Pose the template by LBS for every frame; writes sharded posed vertices."""

    def run(self) -> None:
        stages.pose_template(self)


@dataclass
class UvAtlas(StageArgs):
    """Unwrap the template with xatlas if it has no UVs (cached), build the texel -> (triangle, barycentric) map."""

    tex_size: int = 0
    """UV texture resolution (0 = derived from the capture's image size; paper: 1024)."""
    gutter_px: float = 1.0
    """Texels within this distance outside a UV triangle still map to it (no holes at seams)."""

    def run(self) -> None:
        stages.uv_atlas(self, self.tex_size, self.gutter_px)


@dataclass
class ProjectUv(StageArgs):
    """Multi-view UV texel projection with eroded masks and median-band fusion (paper supp. C)."""

    project: ProjectConfig = field(default_factory=ProjectConfig)
    """Projection settings."""
    cameras: Literal["train", "all"] = "train"
    """Views projected into the textures (train: held-out cameras never leak into the encoder input)."""

    def run(self) -> None:
        stages.project_uv(self, self.project, self.cameras)


@dataclass
class FitPca(StageArgs):
    """Localized pose PCA (7 groups x 5 components, +-2 sigma clamp) and a global PCA for the baseline."""

    n_components: int = 5
    """Components per body-part group (paper: 5)."""
    global_components: int = 20
    """Components of the global PCA (MMLPs-dagger baseline, applied at test time only)."""
    clamp_sigma: float = 2.0
    """Clamp of PCA coefficients in standard deviations."""

    def run(self) -> None:
        stages.fit_pca(self, self.n_components, self.global_components, self.clamp_sigma)


@dataclass
class SamplePoints(StageArgs):
    """Anchors / control points / Gaussians on the template with 3-NN interpolation weights."""

    anchors: int = 0
    """Anchor count (0 = derived from the capture's image resolution, at most the paper's 300)."""
    control: int = 0
    """Control-point count (0 = derived, at most 10k)."""
    gaussians: int = 0
    """Gaussian count (0 = derived, at most 200k)."""
    seed: int = 0
    """Sampling seed."""

    def run(self) -> None:
        stages.sample_points(self, self.anchors, self.control, self.gaussians, self.seed)


@dataclass
class Localize(StageArgs):
    """Per-anchor pose and face masks from skinning weights (dilated once), plus figures."""

    ancestor_levels: int = 1
    """A parameter drives an anchor if its joint skins it or is up to this many levels above one that does."""
    k_neighbors: int = 6
    """Anchor neighbours used for the one-step dilation."""
    figure_param: str = "Neck.ry"
    """Pose parameter whose region of influence is drawn."""
    figures: bool = True
    """Render the hierarchy and influence pictures (pyvista off-screen)."""

    def run(self) -> None:
        stages.localize(self, self.ancestor_levels, self.k_neighbors, self.figure_param, self.figures)


@dataclass
class All(StageArgs):
    """Run every stage in order, skipping those whose outputs are complete and valid."""

    project: ProjectConfig = field(default_factory=ProjectConfig)
    """Projection settings."""
    figures: bool = True
    """Render the localization figures (pyvista off-screen)."""

    def run(self) -> None:
        stages.pose_template(self)
        stages.project_uv(self, self.project)  # runs uv-atlas at the (derived) texture size first
        stages.fit_pca(self)
        stages.sample_points(self)
        stages.localize(self, figures=self.figures)


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


COMMANDS: dict[str, type] = {
    "synth": Synth,
    "pose-template": PoseTemplate,
    "uv-atlas": UvAtlas,
    "project-uv": ProjectUv,
    "fit-pca": FitPca,
    "sample-points": SamplePoints,
    "localize": Localize,
    "all": All,
    "verify": Verify,
}


def main(argv: list[str] | None = None) -> int:
    cmd = tyro.extras.subcommand_cli_from_dict(
        {k: v for k, v in COMMANDS.items()}, prog="avatar-prep", description=__doc__, args=argv
    )
    rc = run_reporting_errors(cmd.run)
    if rc:
        return rc
    timings = getattr(cmd, "timings", {})  # StageArgs commands record the stages they ran
    if timings:
        print("stage timings: " + ", ".join(f"{k} {v:.1f}s" for k, v in timings.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
