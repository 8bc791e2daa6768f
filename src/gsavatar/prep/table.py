"""The declared table of ``avatar-prep`` stages, and the one way stages are run.

A row (:class:`Stage`) says what a stage is: its name (subcommand, ``dataset.json`` key, output folder),
its config dataclass (:mod:`gsavatar.prep.configs`, the only place its defaults live), the capture files
it reads, the stages whose outputs it reads, the files it writes and its run function. What a stage reads
is what it fingerprints (:func:`stage_inputs`), so a changed input or upstream stage re-runs it.

Both ``avatar-prep all`` and a single-stage subcommand name the stages they want with their configs;
:func:`plan` adds the upstream stages those need, :func:`run_stages` refuses a capture that a planned
stage's check rejects before anything runs, then runs the plan in table order (each stage skips itself
when its record is complete). No stage calls another.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gsavatar.data_schema import Capture
from gsavatar.data_schema.dataset import read_dataset_json, stage_complete
from gsavatar.prep import stages
from gsavatar.prep.common import StageArgs, open_capture
from gsavatar.prep.configs import (
    FitPcaConfig,
    LocalizeConfig,
    PoseTemplateConfig,
    ProjectUvConfig,
    SamplePointsConfig,
    UvAtlasConfig,
)
from gsavatar.prep.inputs import metadata_inputs, upstream_inputs

SHARDS = ("manifest.json", "shard-*.npz")
"""Outputs of a per-frame stage (:func:`gsavatar.prep.common.run_frame_stage`)."""


@dataclass(frozen=True)
class Upstream:
    """A stage whose outputs another stage reads."""

    stage: str
    config: Callable[[Any], Any] | None = None
    """The config the reading stage needs it to have, from the reading stage's config (project-uv's atlas
    has its texture size and gutter): it is run with that config, which wins over any other (and skips
    itself if complete with it). None: any complete record will do; a missing or stale one is recomputed
    with the config it recorded, else the defaults."""


@dataclass(frozen=True)
class Stage:
    name: str
    """Subcommand, ``dataset.json`` stage key and (``-`` -> ``_``) output folder."""
    config: type
    """Config dataclass: the subcommand's flags and their defaults; its docstring is the subcommand's help."""
    inputs: tuple[str, ...]
    """Capture files the stage reads (fingerprinted, :func:`gsavatar.prep.inputs.metadata_inputs`;
    ``template/`` = every file in it). Per-frame files are the run function's own (project-uv)."""
    upstream: tuple[Upstream, ...]
    """Stages whose outputs it reads: run before it, and fingerprinted by identity."""
    outputs: tuple[str, ...]
    """Files it writes under its output folder (glob patterns)."""
    run: Callable[[StageArgs, Capture, Any, dict[str, str]], bool]
    """``run(args, capture, config, inputs)``: compute and record unless complete; True if the stage ran
    or (per-frame) its manifest is complete."""
    check: Callable[[Capture, Any], None] | None = None
    """Refuses a capture the stage cannot use (raises), before any stage of the command runs."""


STAGES: tuple[Stage, ...] = (  # in dependency order: a stage comes after every stage it reads
    Stage(
        "pose-template",
        PoseTemplateConfig,
        ("capture.json", "motion.npz", "template/"),
        (),
        SHARDS,
        stages.pose_template,
    ),
    Stage("uv-atlas", UvAtlasConfig, ("template/",), (), ("atlas.npz",), stages.uv_atlas),
    Stage(
        "project-uv",
        ProjectUvConfig,
        ("capture.json", "calibration.json", "splits.json", "template/"),
        (
            Upstream("pose-template", lambda cfg: PoseTemplateConfig()),
            Upstream("uv-atlas", stages.atlas_for_projection),
        ),
        SHARDS,
        stages.project_uv,
        stages.check_project_uv,
    ),
    Stage(
        "fit-pca",
        FitPcaConfig,
        ("motion.npz", "splits.json", "template/rig.json"),
        (),
        ("local.npz", "global.npz"),
        stages.fit_pca,
    ),
    # the automatic counts come from calibration.json but are resolved into the recorded config
    Stage("sample-points", SamplePointsConfig, ("template/",), (), ("hierarchy.npz",), stages.sample_points),
    Stage(
        "localize",
        LocalizeConfig,
        ("template/",),
        (Upstream("sample-points"),),
        ("masks.npz", "hierarchy.png", "influence_*.png"),
        stages.localize,
    ),
)
BY_NAME: dict[str, Stage] = {s.name: s for s in STAGES}


def default_configs() -> dict[str, Any]:
    """Every stage's config with its defaults, by stage name."""
    return {s.name: s.config() for s in STAGES}


def stage_inputs(stage: Stage, dataset: Path, capture_root: Path) -> dict[str, str]:
    """Fingerprint of what ``stage`` reads: its capture files and the identity of its upstream stages."""
    return {
        **metadata_inputs(capture_root, stage.inputs),
        **upstream_inputs(Path(dataset), tuple(u.stage for u in stage.upstream)),
    }


def recorded_or_default(dataset: Path, name: str) -> Any:
    """The config a stage recorded in ``dataset`` (its fields that are options), else the defaults."""
    cls = BY_NAME[name].config
    rec = read_dataset_json(Path(dataset))["stages"].get(name) or {}
    options = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in (rec.get("config") or {}).items() if k in options})


def plan(targets: dict[str, Any], dataset: Path, capture_root: Path) -> list[tuple[Stage, Any]]:
    """The stages to run for ``targets`` (``{stage name: config}``), with their configs, in table order:
    the targets and the upstream stages they need (:class:`Upstream`). ``dataset``: where an upstream
    stage that any record satisfies may already be complete."""
    unknown = sorted(set(targets) - set(BY_NAME))
    if unknown:
        raise ValueError(f"unknown prep stages {unknown}; the stages are {list(BY_NAME)}")
    configs = dict(targets)
    for stage in reversed(STAGES):  # downstream first: a stage fixes its upstream configs before they are visited
        if stage.name not in configs:
            continue
        for up in stage.upstream:
            if up.config is not None:
                configs[up.stage] = up.config(configs[stage.name])
            elif up.stage not in configs and not stage_complete(
                dataset, up.stage, inputs=stage_inputs(BY_NAME[up.stage], dataset, capture_root)
            ):
                configs[up.stage] = recorded_or_default(dataset, up.stage)
    return [(s, configs[s.name]) for s in STAGES if s.name in configs]


def run_stages(args: StageArgs, targets: dict[str, Any]) -> None:
    """Run ``targets`` (``{stage name: config}``) and the upstream stages they need into ``args.out``: every
    planned stage's check first, then each stage in table order (skipped when its record is complete)."""
    cap = open_capture(args)
    steps = plan(targets, Path(args.out), cap.root)
    for stage, cfg in steps:
        if stage.check is not None:
            stage.check(cap, cfg)
    for stage, cfg in steps:  # inputs after the upstream stages ran: their identity may have changed
        stage.run(args, cap, cfg, stage_inputs(stage, Path(args.out), cap.root))
