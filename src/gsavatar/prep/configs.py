"""Options of each ``avatar-prep`` stage: the one place their defaults live.

A stage's subcommand takes these fields as flags (:mod:`gsavatar.prep.cli` builds it from the stage
table, :mod:`gsavatar.prep.table`), ``avatar-prep all`` starts from the same defaults, and a stage run
as another's upstream gets its config from the table too. The class docstring is the subcommand's help.
A field ``0 = derived`` is resolved from the capture by the stage itself, so the resolved value is
recorded in ``dataset.json`` and the unresolved one never is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from gsavatar.prep.project_uv import ProjectConfig


@dataclass
class PoseTemplateConfig:
    """Pose the template by LBS for every frame; writes sharded posed vertices."""


@dataclass
class UvAtlasConfig:
    """Unwrap the template with xatlas if it has no UVs (cached), build the texel -> (triangle, barycentric) map."""

    tex_size: int | None = ProjectConfig.tex_size
    """UV texture resolution (None = derived from the capture's image size; paper: 1024)."""
    gutter_px: float = ProjectConfig.gutter_px
    """Texels within this distance outside a UV triangle still map to it (no holes at seams)."""


@dataclass
class ProjectUvConfig:
    """Multi-view UV texel projection with eroded masks and median-band fusion (paper supp. C)."""

    project: ProjectConfig = field(default_factory=ProjectConfig)
    """Projection settings."""
    cameras: Literal["train", "all"] = "train"
    """Views projected into the textures (train: held-out cameras never leak into the encoder input)."""


@dataclass
class FitPcaConfig:
    """Localized pose PCA (7 groups x 5 components, +-2 sigma clamp) and a global PCA for the baseline."""

    n_components: int = 5
    """Components per body-part group (paper: 5)."""
    global_components: int = 20
    """Components of the global PCA (MMLPs-dagger baseline, applied at test time only)."""
    clamp_sigma: float = 2.0
    """Clamp of PCA coefficients in standard deviations."""


@dataclass
class SamplePointsConfig:
    """Anchors / control points / Gaussians on the template with 3-NN interpolation weights."""

    anchors: int | None = None
    """Anchor count (None = derived from the capture's image resolution, at most the paper's 300)."""
    control: int | None = None
    """Control-point count (None = derived, at most 10k)."""
    gaussians: int | None = None
    """Gaussian count (None = derived, at most 200k)."""
    seed: int = 0
    """Sampling seed."""


@dataclass
class LocalizeConfig:
    """Per-anchor pose and face masks from skinning weights (dilated once), plus figures."""

    ancestor_levels: int = 1
    """A parameter drives an anchor if its joint skins it or is up to this many levels above one that does."""
    k_neighbors: int = 6
    """Anchor neighbours used for the one-step dilation."""
    figure_param: str = "Neck.ry"
    """Pose parameter whose region of influence is drawn."""
    figures: bool = True
    """Render the hierarchy and influence pictures (pyvista off-screen)."""
