"""Outputs that are stale, of another dataset, or not ours at all, through the real entry points:

1. Stage records fingerprint their inputs: a capture file changed after ``avatar-prep all`` makes the
   stages that read it (and the stages downstream) re-run on the next ``avatar-prep all``; a sharded
   stage recomputes only the shards whose frames changed; unchanged inputs still skip.
2. ``avatar-train`` resuming a run whose ``--dataset`` path now holds a dataset of other content is refused.
3. A non-empty ``--out`` that is not a gsavatar output of that kind is refused (unless the force flag):
   the user's files stay byte-identical and nothing is written.

Each case works on copies of the session fixtures under ``tmp_path``, never on the fixtures.
docs/reliability.md lists the kinds; keep the two in step.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gsavatar.data_schema.dataset import ShardReader, dataset_fingerprint, read_dataset_json, verify_dataset
from gsavatar.drive.cli import main as drive_main
from gsavatar.prep.cli import main as prep_main
from gsavatar.prep.report import main as report_main
from gsavatar.train.cli import main as train_main
from gsavatar.utils.io import read_image, sha256_file, write_image
from gsavatar.utils.outdir import MARKER
from reliability.helpers import PREP_ARGS, copy_capture, copy_dataset, edit_json, edit_npz, tree_digest

TRAIN_ARGS = [
    "--preset",
    "tiny",
    "--lpips",
    "off",
    "--image-scale",
    "0.5",
    "--log-every",
    "1",
    "--no-evaluate",
    "--deterministic",
    "--checkpoint-every",
    "1",
]
DRIVE_ARGS = ["--lpips", "off", "--image-scale", "0.25", "--count", "2"]
STAGES = ("pose-template", "uv-atlas", "project-uv", "fit-pca", "sample-points", "localize")
IMG = "images/full00/00000003.png"
"""A training camera's image of frame 3."""


def run_cli(main, argv: list[str]) -> int | str | None:
    try:
        return main(argv)
    except SystemExit as e:  # tyro's parse errors exit through SystemExit
        return e.code


def files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def assert_refused(capsys, rc, *fragments: str) -> str:
    err = capsys.readouterr().err
    assert rc not in (0, None), f"exit code {rc!r}; stderr:\n{err}"
    assert "Traceback" not in err, err
    missing = [f for f in fragments if f not in err]
    assert not missing, f"message lacks {missing}:\n{err}"
    return err


def stage_lines(out: str) -> dict[str, str]:
    """What each stage said about its record: ``[s] complete, skipping ...`` or ``[s] <why>, recomputing``."""
    lines: dict[str, str] = {}
    for ln in out.splitlines():
        for s in STAGES:
            if ln.startswith(f"[{s}] ") and (", skipping" in ln or ln.endswith(", recomputing")):
                lines.setdefault(s, ln)
    return lines


def texture(ds: Path, frame: int) -> np.ndarray:
    return ShardReader(ds / "project_uv").get(frame)["texture"].astype(np.float32)


# --------------------------------------------------------------------------- 1. stale stage outputs
@pytest.fixture
def prepped(tmp_path, tiny_capture, tiny_dataset) -> tuple[Path, Path]:
    """A capture copy and its dataset (the session dataset, pointed at the copy)."""
    cap = copy_capture(tiny_capture, tmp_path / "capture")
    return cap, copy_dataset(tiny_dataset, tmp_path / "dataset", capture=cap)


def test_unchanged_inputs_skip_every_stage_and_change_nothing(prepped, capsys):
    cap, ds = prepped
    before = tree_digest(ds, cap)
    capsys.readouterr()
    assert prep_main(["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert sorted(lines) == sorted(STAGES) and all("complete, skipping" in v for v in lines.values()), lines
    assert tree_digest(ds, cap) == before


def test_changed_image_recomputes_only_its_shard(prepped, tmp_path, capsys):
    """Sharded per-frame stage: the shard holding the changed image is recomputed, not resumed; the
    others are kept byte-identical; no other stage re-runs; a second re-run skips everything."""
    cap, _ = prepped
    ds = copy_dataset(tmp_path / "dataset", tmp_path / "sharded", capture=cap, drop=("pose-template", "project-uv"))
    argv = ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS, "--shard-size", "4"]
    assert prep_main(argv) == 0  # 3 shards of 4 frames
    old_tex = texture(ds, 3)
    old_inputs = read_dataset_json(ds)["stages"]["project-uv"]["inputs"]
    shards = {i: (ds / f"project_uv/shard-{i:05d}.npz").read_bytes() for i in range(3)}
    img = read_image(cap / IMG)
    write_image(cap / IMG, img[..., ::-1] * 0.5)  # another picture of the same size
    capsys.readouterr()
    assert prep_main(argv) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert lines["project-uv"] == f"[project-uv] inputs changed ({IMG}), recomputing", lines
    assert all("complete, skipping" in lines[s] for s in STAGES if s != "project-uv"), lines
    assert (ds / "project_uv/shard-00000.npz").read_bytes() != shards[0]  # frames 0-3: recomputed
    assert all((ds / f"project_uv/shard-{i:05d}.npz").read_bytes() == shards[i] for i in (1, 2))  # resumed
    assert not np.array_equal(texture(ds, 3), old_tex)
    assert read_dataset_json(ds)["stages"]["project-uv"]["inputs"] != old_inputs
    assert verify_dataset(ds) == []
    before = tree_digest(ds)
    capsys.readouterr()
    assert prep_main(argv) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert sorted(lines) == sorted(STAGES) and all("complete, skipping" in v for v in lines.values()), lines
    assert tree_digest(ds) == before


def test_changed_metadata_reruns_the_stages_that_read_it_and_those_downstream(prepped, capsys):
    """motion.npz feeds pose-template and fit-pca (content hash); project-uv reads pose-template's output,
    so it re-runs because its upstream did. sample-points -> localize the same way."""
    cap, ds = prepped
    with np.load(cap / "motion.npz") as z:
        pose = z["pose"].copy()
    pose[5, 0] += 0.05
    edit_npz(cap / "motion.npz", pose=pose)
    capsys.readouterr()
    assert prep_main(["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert lines["pose-template"] == "[pose-template] inputs changed (motion.npz), recomputing", lines
    assert lines["project-uv"] == "[project-uv] inputs changed (stage:pose-template), recomputing", lines
    assert lines["fit-pca"] == "[fit-pca] inputs changed (motion.npz), recomputing", lines
    assert all("complete, skipping" in lines[s] for s in ("uv-atlas", "sample-points", "localize")), lines
    assert verify_dataset(ds) == []
    # a recomputed upstream stage (here by a config change) re-runs its downstream stage
    assert prep_main(["sample-points", "--capture", str(cap), "--out", str(ds), "--seed", "1"]) == 0
    capsys.readouterr()
    assert prep_main(["localize", "--capture", str(cap), "--out", str(ds), "--no-figures"]) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert lines["localize"] == "[localize] inputs changed (stage:sample-points), recomputing", lines


def strip_fingerprints(ds: Path) -> None:
    """Make ``ds`` look prepared by a gsavatar from before input fingerprints (records, sidecars, manifests)."""
    for sc in ds.glob("*/shard-*.json"):
        edit_json(sc, lambda o: [o.pop(k) for k in ("inputs", "inputs_hash")])
    for m in ds.glob("*/manifest.json"):
        edit_json(m, lambda o: [s.pop("inputs_hash") for s in o["shards"]])

    def strip(o: dict) -> None:
        for rec in o["stages"].values():
            rec.pop("inputs")
            rec["files"] = {rel: sha256_file(ds / rel) for rel in rec["files"]}  # the manifests' new bytes

    edit_json(ds / "dataset.json", strip)


def test_records_without_input_fingerprint_are_adopted_then_tracked(prepped, capsys):
    """Records of gsavatar versions before fingerprints whose outputs verify adopt the current inputs:
    nothing is recomputed, so the dataset's identity (and every run trained on it) survives the upgrade;
    from then on a changed input re-runs the stage (every shard: old sidecars have no fingerprint)."""
    cap, ds = prepped
    strip_fingerprints(ds)
    outputs = {p: d for p, d in tree_digest(ds).items() if not p.endswith("dataset.json")}
    ident = dataset_fingerprint(ds)
    argv = ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]
    capsys.readouterr()
    assert prep_main(argv) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert sorted(lines) == sorted(STAGES) and all("the current inputs are adopted" in v for v in lines.values()), lines
    assert {p: d for p, d in tree_digest(ds).items() if not p.endswith("dataset.json")} == outputs
    assert dataset_fingerprint(ds) == ident
    assert all(isinstance(r["inputs"], dict) for r in read_dataset_json(ds)["stages"].values())
    write_image(cap / IMG, read_image(cap / IMG) * 0.5)
    capsys.readouterr()
    assert prep_main(argv) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert lines["project-uv"] == "[project-uv] inputs changed (per-frame files), recomputing", lines
    assert all("complete, skipping" in lines[s] for s in STAGES if s != "project-uv"), lines
    assert verify_dataset(ds) == []


# --------------------------------------------------------------------------- 2. resume on another dataset
def test_a_run_whose_dataset_path_now_holds_other_content_is_refused(tiny_dataset, tmp_path, capsys):
    ds = copy_dataset(tiny_dataset, tmp_path / "dataset")
    run = tmp_path / "run"
    assert train_main(["avatar", "--dataset", str(ds), "--out", str(run), *TRAIN_ARGS, "--steps", "1"]) == 0
    capture = Path(read_dataset_json(ds)["capture"])
    shutil.rmtree(ds)  # the path now holds another preparation (other PCA outputs)
    copy_dataset(tiny_dataset, ds)
    assert prep_main(["fit-pca", "--capture", str(capture), "--out", str(ds), "--n-components", "4"]) == 0
    before = tree_digest(run, ds)
    capsys.readouterr()
    rc = train_main(["avatar", "--dataset", str(ds), "--out", str(run), *TRAIN_ARGS, "--steps", "3"])
    assert_refused(capsys, rc, "latest.pt", "dataset", "another dataset")
    # every reader of the run checks it too: evaluating, driving
    assert_refused(capsys, run_cli(train_main, ["eval", "--run", str(run)]), "latest.pt", "config.dataset_id")
    out = tmp_path / "drive"
    rc = drive_main(["--run", str(run), "--motion", str(capture), "--out", str(out), *DRIVE_ARGS, "--mode", "encoder"])
    assert_refused(capsys, rc, "latest.pt", "config.dataset_id")
    assert tree_digest(run, ds) == before and not out.exists()


# --------------------------------------------------------------------------- 3. --out that is not ours
def user_folder(root: Path) -> Path:
    """A user's folder with files our commands would write (config.json, metrics.jsonl, hierarchy.png)."""
    (root / "localize").mkdir(parents=True)
    (root / "notes.txt").write_text("my notes\n")
    (root / "config.json").write_text(json.dumps({"lr": 0.1}))
    (root / "metrics.jsonl").write_text('{"step": 1}\n')
    write_image(root / "localize" / "hierarchy.png", np.full((8, 8, 3), 0.5))
    return root


def refusal_argv(
    cli: str, out: Path, tiny_capture: Path, tiny_dataset: Path, run: Path
) -> tuple[object, list[str], str]:
    """(main, argv, force flag) of each command that takes --out DIR."""
    return {
        "avatar-prep all": (
            prep_main,
            ["all", "--capture", str(tiny_capture), "--out", str(out), *PREP_ARGS],
            "--force-out",
        ),
        "avatar-prep synth": (prep_main, ["synth", "--out", str(out)], "--force-out"),
        "avatar-train avatar": (
            train_main,
            ["avatar", "--dataset", str(tiny_dataset), "--out", str(out), *TRAIN_ARGS, "--steps", "1"],
            "--force",
        ),
        "avatar-train predictor": (train_main, ["predictor", "--run", str(run), "--out", str(out)], "--force"),
        "avatar-drive": (
            drive_main,
            ["--run", str(run), "--motion", str(tiny_capture), "--out", str(out), *DRIVE_ARGS],
            "--force",
        ),
        "prep.report": (report_main, [str(tiny_dataset), "--out", str(out)], "--force"),
    }[cli]


CLIS = [
    "avatar-prep all",
    "avatar-prep synth",
    "avatar-train avatar",
    "avatar-train predictor",
    "avatar-drive",
    "prep.report",
]


@pytest.mark.parametrize("cli", CLIS)
def test_nonempty_foreign_out_is_refused_and_left_untouched(
    cli, tmp_path, tiny_capture, tiny_dataset, pose_only_run, capsys
):
    out = user_folder(tmp_path / "mine")
    main, argv, flag = refusal_argv(cli, out, tiny_capture, tiny_dataset, pose_only_run)
    before = tree_digest(tmp_path, pose_only_run)
    capsys.readouterr()
    err = assert_refused(capsys, run_cli(main, argv), str(out), "not empty", flag)
    assert any(ln.startswith(f"error: {out}: ") for ln in err.splitlines()), err
    assert tree_digest(tmp_path, pose_only_run) == before  # byte-identical, and nothing new anywhere


def test_prep_force_out_writes_beside_the_users_files_then_resumes(tmp_path, tiny_capture, capsys):
    out = user_folder(tmp_path / "mine")
    mine = tree_digest(out / "notes.txt", out / "config.json", out / "metrics.jsonl", out / "localize")
    outside = tree_digest(tiny_capture)
    argv = ["fit-pca", "--capture", str(tiny_capture), "--out", str(out)]
    assert prep_main([*argv, "--force-out"]) == 0
    assert (out / MARKER).exists() and (out / "fit_pca" / "local.npz").exists()
    assert tree_digest(out / "notes.txt", out / "config.json", out / "metrics.jsonl", out / "localize") == mine
    capsys.readouterr()
    assert prep_main(argv) == 0  # ours now: no flag needed, the stage is complete
    assert "[fit-pca] complete, skipping" in capsys.readouterr().out
    assert tree_digest(tiny_capture) == outside


def test_train_and_drive_force_write_into_a_foreign_folder_then_resume(
    tmp_path, tiny_dataset, pose_only_run, tiny_capture
):
    run = user_folder(tmp_path / "run")
    notes = (run / "notes.txt").read_bytes()
    protected = tree_digest(tiny_dataset, pose_only_run, tiny_capture)
    argv = [
        "avatar",
        "--dataset",
        str(tiny_dataset),
        "--out",
        str(run),
        *TRAIN_ARGS,
        "--steps",
        "2",
        "--max-steps-this-run",
        "1",
        "--variant",
        "mmlps_dagger",
    ]
    assert train_main([*argv, "--force"]) == 0
    assert (run / "checkpoints" / "latest.pt").exists() and (run / "notes.txt").read_bytes() == notes
    assert train_main(argv) == 0  # resumes into its own run without --force
    assert json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])["step"] == 2
    drive = user_folder(tmp_path / "drive")
    dargv = ["--run", str(run), "--motion", str(tiny_capture), "--out", str(drive), *DRIVE_ARGS]
    assert drive_main([*dargv, "--force"]) == 0
    assert (drive / "drive.json").exists() and (drive / "notes.txt").read_bytes() == notes
    assert drive_main(dargv) == 0  # an earlier drive's folder is reused
    assert tree_digest(tiny_dataset, pose_only_run, tiny_capture) == protected


@pytest.mark.parametrize("cli", ["avatar-train avatar", "avatar-drive", "avatar-prep all"])
def test_out_holding_another_kind_of_our_outputs_is_refused_even_with_force(
    cli, tmp_path, tiny_capture, tiny_dataset, pose_only_run, capsys
):
    other = {
        "avatar-train avatar": ("dataset", tiny_dataset),
        "avatar-drive": ("run", pose_only_run),
        "avatar-prep all": ("run", pose_only_run),
    }[cli]
    out = tmp_path / "other"
    shutil.copytree(other[1], out)
    main, argv, flag = refusal_argv(cli, out, tiny_capture, tiny_dataset, pose_only_run)
    before = tree_digest(tmp_path)
    capsys.readouterr()
    assert_refused(capsys, run_cli(main, [*argv, flag]), str(out), f"holds a gsavatar {other[0]} output")
    assert tree_digest(tmp_path) == before


def test_outputs_of_older_versions_without_marker_are_still_ours(
    tmp_path, tiny_capture, tiny_dataset, drive_output, pose_only_run, capsys
):
    ds = copy_dataset(tiny_dataset, tmp_path / "dataset")
    (ds / MARKER).unlink()
    capsys.readouterr()
    assert prep_main(["all", "--capture", str(tiny_capture), "--out", str(ds), *PREP_ARGS]) == 0
    lines = stage_lines(capsys.readouterr().out)
    assert sorted(lines) == sorted(STAGES) and all("complete, skipping" in v for v in lines.values()), lines
    assert json.loads((ds / MARKER).read_text())["kind"] == "dataset"
    out = tmp_path / "drive"
    shutil.copytree(drive_output, out)
    (out / MARKER).unlink()
    assert drive_main(["--run", str(pose_only_run), "--motion", str(tiny_capture), "--out", str(out), *DRIVE_ARGS]) == 0
    assert json.loads((out / MARKER).read_text())["kind"] == "drive"
