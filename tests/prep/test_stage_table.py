"""The stage table: one set of defaults for ``avatar-prep all`` and the single-stage subcommands, upstream
stages run from the table, and what a stage declares is what it records."""

from __future__ import annotations

import dataclasses
import fnmatch
import json
from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema.dataset import STAGE_VERSIONS, read_dataset_json, stage_dir
from gsavatar.prep.cli import COMMANDS, main, parse
from gsavatar.prep.common import FRAME_FILES
from gsavatar.prep.configs import SamplePointsConfig, UvAtlasConfig
from gsavatar.prep.inputs import metadata_inputs
from gsavatar.prep.stages import auto_tex_size
from gsavatar.prep.table import BY_NAME, STAGES, default_configs, plan

ALL_ARGS = ["--workers", "1", "--project.tex-size", "128", "--no-figures"]
"""The session ``tiny_dataset``'s ``avatar-prep all`` options (tests/conftest.py) ..."""
STAGE_ARGS = {
    "pose-template": ["--workers", "1"],
    "uv-atlas": ["--tex-size", "128"],
    "project-uv": ["--workers", "1", "--project.tex-size", "128"],
    "fit-pca": [],
    "sample-points": [],
    "localize": ["--no-figures"],
}
"""... and the same settings given to each stage's own subcommand."""


def planned(argv: list[str], dataset: Path, capture: Path | None = None) -> dict[str, object]:
    """``{stage: config}`` that the command ``argv`` would run into ``dataset`` (nothing is run; without a
    ``capture``, one that does not exist: fine for a dataset with no stage recorded)."""
    capture = capture or dataset.parent / "no-capture"
    cmd = parse([*argv, "--capture", str(capture), "--out", str(dataset)])
    return {s.name: cfg for s, cfg in plan(cmd.configs(), dataset, capture)}


def test_table_is_in_dependency_order_and_covers_every_stage():
    assert [s.name for s in STAGES] == list(STAGE_VERSIONS)
    seen: set[str] = set()
    for s in STAGES:
        assert {u.stage for u in s.upstream} <= seen, f"{s.name} reads a stage listed after it"
        seen.add(s.name)
        assert dataclasses.is_dataclass(s.config) and s.config.__doc__, s.name
        assert all(
            f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
            for f in dataclasses.fields(s.config)
        ), f"{s.name}: every option needs its (one) default"
    assert list(COMMANDS) == ["synth", "import", "fit-body", *BY_NAME, "all", "verify"]  # capture sources first


@pytest.mark.parametrize(
    "argv_all, argv_stage", [([], {s: [] for s in STAGE_ARGS}), (ALL_ARGS, STAGE_ARGS)], ids=["defaults", "tiny"]
)
def test_all_and_each_stage_command_resolve_to_the_same_configs(tmp_path, argv_all, argv_stage):
    """Defaults live in one place: every stage a single-stage command would run (itself and the upstream
    stages it needs) gets the config ``avatar-prep all`` gives it, with no flags and with the tiny flags."""
    everything = planned(["all", *argv_all], tmp_path / "ds")
    assert list(everything) == list(BY_NAME)
    if not argv_all:
        assert everything == default_configs()
    for name, args in argv_stage.items():
        alone = planned([name, *args], tmp_path / "ds")
        assert name in alone
        for stage, cfg in alone.items():
            assert cfg == everything[stage], (
                f"`avatar-prep {name}` runs {stage} with {cfg}, `all` with {everything[stage]}"
            )
    # the upstream stages a single-stage command runs first
    assert list(planned(["project-uv"], tmp_path / "ds")) == ["pose-template", "uv-atlas", "project-uv"]
    assert list(planned(["localize"], tmp_path / "ds")) == ["sample-points", "localize"]
    assert list(planned(["fit-pca"], tmp_path / "ds")) == ["fit-pca"]


def test_projection_options_reach_the_atlas_it_reads(tmp_path):
    got = planned(["project-uv", "--project.tex-size", "64", "--project.gutter-px", "2"], tmp_path / "ds")
    assert got["uv-atlas"] == UvAtlasConfig(tex_size=64, gutter_px=2.0)
    got = planned(["all", "--project.gutter-px", "0.5"], tmp_path / "ds")
    assert got["uv-atlas"] == UvAtlasConfig(tex_size=None, gutter_px=0.5)  # None: derived from the capture


def _arrays(ds: Path) -> dict[str, bytes]:
    out = {}
    for p in sorted(ds.rglob("*.npz")):
        with np.load(p) as z:
            out |= {
                f"{p.relative_to(ds)}:{k}": z[k].tobytes() + str((z[k].dtype, z[k].shape)).encode() for k in z.files
            }
    return out


def test_one_stage_at_a_time_records_what_all_records(tiny_capture, tiny_dataset, tmp_path, capsys):
    """Each stage's own subcommand, in table order, into a fresh dataset: the same configs and input
    fingerprints in dataset.json as ``avatar-prep all`` (the session dataset), and bit-identical arrays.
    Every stage runs exactly once (its upstream stages are complete by then)."""
    ds = tmp_path / "ds"
    capsys.readouterr()
    for name, args in STAGE_ARGS.items():
        assert main([name, "--capture", str(tiny_capture), "--out", str(ds), *args]) == 0
    out = capsys.readouterr().out
    for name in STAGE_ARGS:
        assert out.count(f"[{name}] done in") + out.count(f"[{name}] 12 frames in") == 1, out
    ref, got = read_dataset_json(tiny_dataset)["stages"], read_dataset_json(ds)["stages"]
    assert list(got) == list(ref) == list(BY_NAME)
    for name in BY_NAME:
        assert got[name]["config"] == ref[name]["config"], name
        assert got[name]["inputs"] == ref[name]["inputs"], name
    assert _arrays(ds) == _arrays(tiny_dataset)


def test_recorded_files_and_inputs_are_the_declared_ones(tiny_capture, tiny_dataset):
    """What a row declares (outputs, capture files read, upstream stages) is what the stage records."""
    stages = read_dataset_json(tiny_dataset)["stages"]
    for s in STAGES:
        rec = stages[s.name]
        folder = stage_dir(tiny_dataset, s.name).name
        for rel in rec["files"]:
            assert rel.startswith(folder + "/") and any(
                fnmatch.fnmatch(rel[len(folder) + 1 :], pat) for pat in s.outputs
            ), f"{s.name} wrote {rel}, not among its declared outputs {s.outputs}"
        declared = set(metadata_inputs(tiny_capture, s.inputs)) | {f"stage:{u.stage}" for u in s.upstream}
        extra = {FRAME_FILES} if s.name == "project-uv" else set()  # images and masks of the projected views
        assert set(rec["inputs"]) == declared | extra, s.name


def test_single_stage_commands_run_missing_upstream_stages(tiny_capture, tmp_path, capsys):
    """localize takes any complete sample-points record (here seed 1) and runs it only when missing; uv-atlas
    alone derives its texture size like project-uv does; project-uv re-makes an atlas of another size."""
    cap, ds = str(tiny_capture), tmp_path / "ds"
    assert main(["localize", "--capture", cap, "--out", str(ds), "--no-figures"]) == 0
    assert read_dataset_json(ds)["stages"]["sample-points"]["config"]["seed"] == 0  # missing: the defaults
    assert main(["sample-points", "--capture", cap, "--out", str(ds), "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["localize", "--capture", cap, "--out", str(ds), "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "[sample-points]" not in out and "[localize] inputs changed (stage:sample-points), recomputing" in out
    assert read_dataset_json(ds)["stages"]["sample-points"]["config"]["seed"] == 1

    from gsavatar.data_schema import load_capture

    assert main(["uv-atlas", "--capture", cap, "--out", str(ds)]) == 0
    auto = auto_tex_size(load_capture(tiny_capture))
    assert read_dataset_json(ds)["stages"]["uv-atlas"]["config"] == {"tex_size": auto, "gutter_px": 1.0}
    capsys.readouterr()
    assert main(["project-uv", "--capture", cap, "--out", str(ds), "--workers", "1", "--project.tex-size", "128"]) == 0
    out = capsys.readouterr().out
    assert "[uv-atlas] config changed, recomputing" in out
    rec = read_dataset_json(ds)["stages"]
    assert rec["uv-atlas"]["config"]["tex_size"] == rec["project-uv"]["config"]["tex_size"] == 128


def test_a_stale_upstream_record_is_recomputed_with_its_own_config(tiny_capture, tmp_path):
    """The rule localize applied before the table: a sample-points record whose inputs changed is redone with
    the counts and seed it recorded, not with the defaults."""
    ds = tmp_path / "ds"
    assert (
        main(["sample-points", "--capture", str(tiny_capture), "--out", str(ds), "--seed", "3", "--anchors", "30"]) == 0
    )
    assert list(planned(["localize"], ds, tiny_capture)) == ["localize"]  # complete: kept as it is
    obj = json.loads((ds / "dataset.json").read_text())
    rec = obj["stages"]["sample-points"]
    rec["inputs"] = {k: "sha256:0" for k in rec["inputs"]}  # as if the template had changed since
    (ds / "dataset.json").write_text(json.dumps(obj))
    counts = rec["config"]
    assert planned(["localize"], ds, tiny_capture)["sample-points"] == SamplePointsConfig(
        anchors=30, control=counts["control"], gaussians=counts["gaussians"], seed=3
    )


def test_all_passes_point_counts_to_sample_points_like_its_own_command(tmp_path):
    """``avatar-prep all --sample.gaussians N`` (the results table's fewer-Gaussians dataset) gives sample-points
    the config its own command gets from ``--gaussians N``; the other stages keep their defaults."""
    flags = ["--sample.gaussians", "1234", "--sample.anchors", "40"]
    everything = planned(["all", *flags], tmp_path / "ds")
    assert everything["sample-points"] == SamplePointsConfig(anchors=40, gaussians=1234)
    alone = planned(["sample-points", "--gaussians", "1234", "--anchors", "40"], tmp_path / "ds")
    assert alone["sample-points"] == everything["sample-points"]
    defaults = default_configs()
    assert {k: v for k, v in everything.items() if k != "sample-points"} == {
        k: v for k, v in defaults.items() if k != "sample-points"
    }
