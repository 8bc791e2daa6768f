"""Bad input through the real entry points of all three CLIs: every kind must give a non-zero exit,
a message naming the offending file and/or field, no traceback, and leave everything that was
already on disk (the capture, a dataset, a run, earlier drive results) byte-identical.

Each case corrupts copies of the session fixtures under ``tmp_path``, never the fixtures.
docs/reliability.md lists the kinds; keep the two in step.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from gsavatar.drive.cli import main as drive_main
from gsavatar.prep.cli import main as prep_main
from gsavatar.train.cli import main as train_main
from gsavatar.utils.io import write_image
from reliability.helpers import (
    PREP_ARGS,
    Case,
    Env,
    case_registry,
    copy_capture,
    copy_dataset,
    edit_json,
    edit_npz,
    flip_byte,
    subprocess_env,
    tree_digest,
    truncate,
)

TRUNCATED_BVH = """HIERARCHY
ROOT Hips
{
 OFFSET 0 0 0
 CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
 End Site
 {
  OFFSET 0 1 0
 }
}
MOTION
Frames: 3
Frame Time: 0.0083333
0 0 0 0 0 0
"""
"""Declares 3 frames, holds 1 (a file cut short while being copied)."""
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
    "--steps",
    "2",
    "--max-steps-this-run",
    "1",
    "--checkpoint-every",
    "1",
]
"""One step per invocation: the first call trains step 1, the same call again resumes and trains step 2."""
DRIVE_ARGS = ["--lpips", "off", "--image-scale", "0.25", "--count", "2"]
MAINS = {"avatar-prep": prep_main, "avatar-train": train_main, "avatar-drive": drive_main}


CASES: list[Case] = []
case = case_registry(CASES)


# --------------------------------------------------------------------------- avatar-prep
def prep_all(env: Env, mutate: Callable[[Path], object], *extra: str) -> tuple[list[str], list[Path]]:
    """``avatar-prep all`` of a corrupted capture into a dataset whose project-uv stage is still to run
    (the stage that reads every image): the stages already there must survive the failure."""
    cap = copy_capture(env.capture, env.tmp / "capture")
    ds = copy_dataset(env.dataset, env.tmp / "dataset", capture=cap, drop=("project-uv",))
    mutate(cap)
    return ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS, *extra], [cap, ds]


IMG = "images/full00/00000003.png"
MASK = "masks/full00/00000003.png"


@case("truncated image", "avatar-prep", IMG, "cannot decode image")
def _(env):
    return prep_all(env, lambda c: truncate(c / IMG, 100))


@case("empty image file", "avatar-prep", IMG, "cannot decode image")
def _(env):
    return prep_all(env, lambda c: (c / IMG).write_bytes(b""))


@case("non-image bytes in a .png", "avatar-prep", IMG, "cannot decode image")
def _(env):
    return prep_all(env, lambda c: (c / IMG).write_bytes(b"this is not a PNG\n" * 64))


@case("wrong image size", "avatar-prep", IMG, "size", "64x48", "128x128")
def _(env):
    return prep_all(env, lambda c: write_image(c / IMG, np.zeros((48, 64, 3))))


@case("missing mask", "avatar-prep", MASK, "not found")
def _(env):
    return prep_all(env, lambda c: (c / MASK).unlink())


@case("mask size mismatch", "avatar-prep", MASK, "size", "32x32")
def _(env):
    return prep_all(env, lambda c: write_image(c / MASK, np.ones((32, 32))))


@case("corrupt image read in a worker process", "avatar-prep", "images/full00/00000005.png", "cannot decode image")
def _(env):  # --workers 2: the SchemaError crosses a process boundary (was BrokenProcessPool)
    argv, protected = prep_all(env, lambda c: truncate(c / "images/full00/00000005.png", 100))
    return [*argv, "--workers", "2", "--shard-size", "4"], protected


@case("missing motion.npz", "avatar-prep", "motion.npz", "file not found")
def _(env):
    return prep_all(env, lambda c: (c / "motion.npz").unlink())


def _inf_translation(cap: Path) -> None:
    with np.load(cap / "motion.npz") as z:
        rt = z["root_translation"].copy()
    rt[5, 1] = np.inf
    edit_npz(cap / "motion.npz", root_translation=rt)


@case("Inf in the root translation", "avatar-prep", "motion.npz", "root_translation", "frame 5, column 1")
def _(env):
    return prep_all(env, _inf_translation)


def _pose_like(cap: Path, fn) -> None:
    with np.load(cap / "motion.npz") as z:
        pose = z["pose"]
    edit_npz(cap / "motion.npz", pose=fn(pose))


@case("pose array of strings (wrong dtype)", "avatar-prep", "motion.npz", "pose", "dtype")
def _(env):
    return prep_all(env, lambda c: _pose_like(c, lambda p: np.full(p.shape, "0.1")))


@case("pose array of wrong shape", "avatar-prep", "motion.npz", "pose", "expected shape")
def _(env):
    return prep_all(env, lambda c: _pose_like(c, lambda p: p[..., None]))


@case("truncated motion.npz", "avatar-prep", "motion.npz", "cannot read npz")
def _(env):
    return prep_all(env, lambda c: truncate(c / "motion.npz", 300))


@case("truncated skin_weights.npz", "avatar-prep", "skin_weights.npz", "cannot read npz")
def _(env):
    return prep_all(env, lambda c: truncate(c / "template/skin_weights.npz", 300))


def _turn_cameras_around(cap: Path) -> None:
    """Rotate every camera 180 degrees about its own y axis: still valid rotations, body behind all."""
    flip = np.diag([-1.0, 1.0, -1.0])

    def edit(cal: dict) -> None:
        for c in cal.values():
            c["R"] = (flip @ np.asarray(c["R"])).tolist()
            c["T"] = (flip @ np.ravel(c["T"])).tolist()

    edit_json(cap / "calibration.json", edit)


@case("cameras behind the body", "avatar-prep", "calibration.json", "R/T", "behind")
def _(env):
    return prep_all(env, _turn_cameras_around)


def _collapse_mesh(cap: Path) -> None:
    """All vertices on the x axis: every triangle has zero area."""
    p = cap / "template/mesh.obj"
    lines = [f"v {ln.split()[1]} 0 0" if ln.startswith("v ") else ln for ln in p.read_text().splitlines()]
    p.write_text("\n".join(lines) + "\n")


@case("degenerate triangles", "avatar-prep", "mesh.obj", "f:", "degenerate")
def _(env):
    return prep_all(env, _collapse_mesh)


@case("empty train split", "avatar-prep", "splits.json", "train.frames", "empty")
def _(env):
    return prep_all(env, lambda c: edit_json(c / "splits.json", lambda o: o["train"].update(frames=[])))


@case("unknown camera id in a split", "avatar-prep", "splits.json", "train.cameras", "cam_x")
def _(env):
    return prep_all(env, lambda c: edit_json(c / "splits.json", lambda o: o["train"]["cameras"].append("cam_x")))


@case("binary bytes in calibration.json", "avatar-prep", "calibration.json", "UTF-8")
def _(env):
    return prep_all(env, lambda c: (c / "calibration.json").write_bytes(b"\xff\xfe\x00\x01" * 32))


@case("dataset of another format version", "avatar-prep", "dataset.json", "version", "unsupported")
def _(env):
    ds = copy_dataset(env.dataset, env.tmp / "dataset", drop=("project-uv",))
    edit_json(ds / "dataset.json", lambda o: o.update(version=2))
    # another shard size: a stage that ran before the refusal would rewrite the pose-template shards
    return ["all", "--capture", str(env.capture), "--out", str(ds), *PREP_ARGS, "--shard-size", "4"], [ds]


@case("output dir that is a file", "avatar-prep", "dataset", "a file is in the way")
def _(env):
    out = env.tmp / "dataset"
    out.write_text("not a directory")
    return ["all", "--capture", str(env.capture), "--out", str(out), *PREP_ARGS], [out]


# --------------------------------------------------------------------------- avatar-train
def train_fresh(env: Env, mutate: Callable[[Path], object], *extra: str) -> tuple[list[str], list[Path]]:
    ds = copy_dataset(env.dataset, env.tmp / "dataset")
    mutate(ds)
    return ["avatar", "--dataset", str(ds), "--out", str(env.tmp / "run"), *TRAIN_ARGS, *extra], [ds]


def train_resume(env: Env, mutate: Callable[[Path, Path, Path], object], *extra: str) -> tuple[list[str], list[Path]]:
    """Train one step, damage (capture, dataset, run), then resume with the same command (+ ``extra``):
    the run's checkpoint, config and log, and the inputs, must survive."""
    cap = copy_capture(env.capture, env.tmp / "capture")
    ds = copy_dataset(env.dataset, env.tmp / "dataset", capture=cap)
    run = env.tmp / "run"
    argv = ["avatar", "--dataset", str(ds), "--out", str(run), *TRAIN_ARGS]
    assert train_main(argv) == 0 and (run / "checkpoints" / "latest.pt").exists()
    mutate(cap, ds, run)
    return [*argv, *extra], [cap, ds, run]


@case("dataset stage missing", "avatar-train", "dataset.json", "stages.localize", "avatar-prep localize")
def _(env):
    return train_fresh(env, lambda d: edit_json(d / "dataset.json", lambda o: o["stages"].pop("localize")))


@case("dataset of another format version", "avatar-train", "dataset.json", "version", "unsupported")
def _(env):
    return train_fresh(env, lambda d: edit_json(d / "dataset.json", lambda o: o.update(version=7)))


@case("not a prepared dataset", "avatar-train", "dataset.json", "not a prepared dataset")
def _(env):
    return train_fresh(env, lambda d: (d / "dataset.json").unlink())


@case("stage output changed after prep", "avatar-train", "hierarchy.npz", "sha256", "checksum mismatch")
def _(env):
    return train_fresh(env, lambda d: truncate(d / "sample_points/hierarchy.npz", 1000))


@case(
    "dataset shard with a wrong checksum", "avatar-train", "project_uv/shard-00000.npz", "sha256", "checksum mismatch"
)
def _(env):
    return train_resume(env, lambda c, d, r: flip_byte(d / "project_uv/shard-00000.npz"))


def _escape(ds: Path) -> None:
    edit_json(ds / "project_uv/manifest.json", lambda o: o["shards"][0].update(file="../../capture/motion.npz"))


@case(
    "manifest path escaping the dataset root",
    "avatar-train",
    "manifest.json",
    "shards[0].file",
    "escapes the dataset root",
)
def _(env):
    return train_resume(env, lambda c, d, r: _escape(d))


def _truncate_train_images(cap: Path) -> None:
    for p in (cap / "images").rglob("*.png"):
        truncate(p, 100)


@case("truncated training images", "avatar-train", "capture/images/", ".png", "cannot decode image")
def _(env):
    return train_resume(env, lambda c, d, r: _truncate_train_images(c))


@case(
    "checkpoint from another config",
    "avatar-train",
    "latest.pt",
    "config.train.schedule.batch_size",
    "another configuration",
)
def _(env):
    return train_resume(env, lambda c, d, r: None, "--batch-size", "4")


@case("truncated checkpoint", "avatar-train", "latest.pt", "cannot load checkpoint")
def _(env):
    return train_resume(env, lambda c, d, r: truncate(r / "checkpoints/latest.pt", 4096))


@case("negative steps", "avatar-train", "schedule.steps", ">= 1", "-3")
def _(env):
    return train_fresh(env, lambda d: None, "--steps=-3")


@case("zero log interval", "avatar-train", "log_every", ">= 1")
def _(env):
    return train_fresh(env, lambda d: None, "--log-every", "0")


@case("output dir that is a file", "avatar-train", "run", "a file is in the way")
def _(env):
    argv, protected = train_fresh(env, lambda d: None)
    (env.tmp / "run").write_text("not a directory")
    return argv, [*protected, env.tmp / "run"]


# --------------------------------------------------------------------------- avatar-drive
def drive(env: Env, motion: Path, *extra: str, run: Path | None = None) -> tuple[list[str], list[Path]]:
    """Drive into a copy of earlier drive results (which must survive) with the given motion."""
    out = env.tmp / "out"
    shutil.copytree(env.drive_out, out)
    run = run or env.run
    return ["--run", str(run), "--motion", str(motion), "--out", str(out), *DRIVE_ARGS, *extra], [run, out, motion]


def _npz(env: Env, name: str = "walk.npz", **changes) -> Path:
    from gsavatar.data_schema import load_capture

    P = load_capture(env.capture).rig.pose_dim
    arrays = {
        "pose": np.zeros((3, P), np.float32),
        "root_rotation": np.zeros((3, 3), np.float32),
        "root_translation": np.zeros((3, 3), np.float32),
        "fps": np.float32(15.0),
        **changes,
    }
    np.savez(env.tmp / name, **arrays)
    return env.tmp / name


@case("garbage BVH", "avatar-drive", "walk.bvh", "MOTION")
def _(env):
    (env.tmp / "walk.bvh").write_bytes(bytes(range(256)) * 8)
    return drive(env, env.tmp / "walk.bvh")


@case("truncated BVH", "avatar-drive", "walk.bvh", "line", "truncated")
def _(env):
    (env.tmp / "walk.bvh").write_text(TRUNCATED_BVH)
    return drive(env, env.tmp / "walk.bvh")


@case("motion npz that is not a zip", "avatar-drive", "walk.npz", "cannot read npz")
def _(env):
    (env.tmp / "walk.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 64)
    return drive(env, env.tmp / "walk.npz")


@case("motion pose of wrong dtype", "avatar-drive", "walk.npz", "pose", "dtype")
def _(env):
    return drive(env, _npz(env, pose=np.full((3, 4), "a")))


@case("motion arrays of different lengths", "avatar-drive", "walk.npz", "root_rotation", "4 frames")
def _(env):
    return drive(env, _npz(env, root_rotation=np.zeros((4, 3), np.float32)))


def _inf_motion(env: Env) -> Path:
    rt = np.zeros((3, 3), np.float32)
    rt[2, 0] = -np.inf
    return _npz(env, root_translation=rt)


@case("Inf in a driving motion", "avatar-drive", "walk.npz", "root_translation", "frame 2")
def _(env):
    return drive(env, _inf_motion(env))


@case("non-positive motion fps", "avatar-drive", "walk.npz", "fps", "-30", "outside the plausible range")
def _(env):
    return drive(env, _npz(env, fps=np.float32(-30.0)))


@case("capture motion with a rig of another pose dim", "avatar-drive", "rig.json", "pose_params", "slots")
def _(env):
    from minimal_capture import make_minimal_capture

    return drive(env, make_minimal_capture(env.tmp / "other_capture"))


@case("unknown camera id", "avatar-drive", "capture_cameras", "nope")
def _(env):
    return drive(env, env.capture, "--capture-cameras", "nope")


@case("missing ground-truth mask", "avatar-drive", "masks/full01/00000001.png", "missing")
def _(env):
    cap = copy_capture(env.capture, env.tmp / "capture")
    (cap / "masks/full01/00000001.png").unlink()
    return drive(env, cap)


@case("start frame past the motion", "avatar-drive", "start", "[0, 12)")
def _(env):
    return drive(env, env.capture, "--start", "40")


@case("truncated run checkpoint", "avatar-drive", "latest.pt", "cannot load checkpoint")
def _(env):
    run = env.tmp / "run"
    shutil.copytree(env.run, run)
    truncate(run / "checkpoints/latest.pt", 4096)
    return drive(env, env.capture, run=run)


@case("output path below a file", "avatar-drive", "results/out", "not a directory", "a file is in the way")
def _(env):
    results = env.tmp / "results"
    results.write_text("not a directory")
    return ["--run", str(env.run), "--motion", str(env.capture), "--out", str(results / "out"), *DRIVE_ARGS], [
        env.run,
        results,
    ]


# --------------------------------------------------------------------------- tests
@pytest.fixture
def env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output) -> Env:
    return Env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output)


def run_cli(cli: str, argv: list[str]) -> int | str | None:
    try:
        return MAINS[cli](argv)
    except SystemExit as e:  # tyro's parse errors and `verify` exit through SystemExit
        return e.code


@pytest.mark.parametrize("case", CASES, ids=[f"{c.cli}: {c.kind}" for c in CASES])
def test_bad_input_is_refused_clearly_and_nothing_is_lost(case: Case, env: Env, capsys):
    """New files may appear (e.g. shards a worker finished before another failed: the re-run keeps
    them), but every file that was there before must be byte-identical afterwards."""
    argv, protected = case.setup(env)
    before = tree_digest(*protected)
    capsys.readouterr()
    rc = run_cli(case.cli, argv)
    err = capsys.readouterr().err
    assert rc not in (0, None), f"exit code {rc!r}; stderr:\n{err}"
    assert "Traceback" not in err, err
    missing = [f for f in case.expect if f not in err]
    assert not missing, f"message lacks {missing}:\n{err}"
    after = tree_digest(*protected)
    changed = [p for p, digest in before.items() if after.get(p) != digest]
    assert not changed, f"files that existed before the failing command were changed or removed: {changed}"


def test_suite_covers_enough_kinds():
    kinds = {(c.cli, c.kind) for c in CASES}
    assert len(kinds) == len(CASES) >= 20
    assert {c.cli for c in CASES} == set(MAINS)


@pytest.mark.parametrize("cli", sorted(MAINS))
def test_console_scripts_exit_2_with_one_line_and_no_traceback(cli, env):
    """The installed entry points (not just ``main``) turn bad input into exit code 2."""
    missing = str(env.tmp / "missing")
    argv = {
        "avatar-prep": ["all", "--capture", missing, "--out", str(env.tmp / "ds")],
        "avatar-train": ["avatar", "--dataset", missing, "--out", str(env.tmp / "run")],
        "avatar-drive": ["--run", str(env.run), "--motion", missing, "--out", str(env.tmp / "out")],
    }[cli]
    exe = Path(sys.executable).with_name(cli)
    cmd = (
        [str(exe)]
        if exe.exists()
        else [
            sys.executable,
            "-m",
            {
                "avatar-prep": "gsavatar.prep.cli",
                "avatar-train": "gsavatar.train.cli",
                "avatar-drive": "gsavatar.drive.cli",
            }[cli],
        ]
    )
    r = subprocess.run([*cmd, *argv], capture_output=True, text=True, env=subprocess_env(), timeout=300)
    assert r.returncode == 2, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert errors and "missing" in errors[0] and "Traceback" not in r.stderr, r.stderr
    assert not (env.tmp / "ds").exists() and not (env.tmp / "run").exists() and not (env.tmp / "out").exists()
