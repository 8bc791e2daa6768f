"""Hostile inputs (issue 11): names that become paths, masks in other encodings, JSON that is not what it
seems, absurd numbers, a full disk and Ctrl-C, through the real CLI entry points.

Same contract as test_bad_inputs.py (non-zero exit, one line naming the file and field, no traceback,
every pre-existing file byte-identical) plus: nothing is ever written outside the output folder, and
inputs that are unusual but unambiguous (0/1 masks, red masks, alpha masks) give the same dataset as
the plain encoding. docs/reliability.md lists the kinds.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from gsavatar.data_schema import SchemaError
from gsavatar.utils.io import atomic_write_bytes, decode_mask
from gsavatar.utils.paths import check_name, output_path, output_roots
from reliability.helpers import PREP_ARGS, copy_capture, copy_dataset, edit_json, subprocess_env, tree_digest
from reliability.helpers import Env
from reliability.test_bad_inputs import TRAIN_ARGS, run_cli

OUTSIDE = "outside"
"""Folder beside every test's inputs that a traversal would write into; must stay absent."""


@pytest.fixture
def env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output) -> Env:
    return Env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output)


def check_refused(
    cli: str, argv: list[str], protected: list[Path], expect: tuple[str, ...], capsys, env: Env, code: int = 2
) -> str:
    before = tree_digest(*protected)
    capsys.readouterr()
    rc = run_cli(cli, argv)
    err = capsys.readouterr().err
    assert rc == code, f"exit code {rc!r} (expected {code}); stderr:\n{err}"
    assert "Traceback" not in err, err
    missing = [f for f in expect if f not in err]
    assert not missing, f"message lacks {missing}:\n{err}"
    after = tree_digest(*protected)
    assert not [p for p, d in before.items() if after.get(p) != d], "pre-existing files changed"
    assert not (env.tmp / OUTSIDE).exists(), (
        f"written outside the output folder: {list((env.tmp / OUTSIDE).rglob('*'))}"
    )
    return err


def prep(env: Env, mutate: Callable[[Path], object]) -> tuple[list[str], list[Path]]:
    """``avatar-prep all`` of a changed capture copy into a dataset copy still missing project-uv."""
    cap = copy_capture(env.capture, env.tmp / "capture")
    ds = copy_dataset(env.dataset, env.tmp / "dataset", capture=cap, drop=("project-uv",))
    mutate(cap)
    return ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS], [cap, ds]


def rename_camera(cap: Path, old: str, new: str) -> None:
    edit_json(cap / "calibration.json", lambda c: c.__setitem__(new, c.pop(old)))
    edit_json(
        cap / "splits.json",
        lambda s: [sp.__setitem__("cameras", [new if x == old else x for x in sp["cameras"]]) for sp in s.values()],
    )


# --------------------------------------------------------------------------- security: names become paths
def test_camera_name_climbing_out_is_refused_by_prep(env, capsys):
    bad = "../../../../" + OUTSIDE + "/PWNED_cam"
    argv, protected = prep(env, lambda c: rename_camera(c, "full00", bad))
    check_refused("avatar-prep", argv, protected, ("calibration.json", "camera name", "not a plain name"), capsys, env)


def test_camera_name_climbing_out_is_refused_by_drive(env, capsys):
    """avatar-drive used to write frames/{cam}/{t}.png outside its --out."""
    cap = copy_capture(env.capture, env.tmp / "capture")
    rename_camera(cap, "full01", "../../" + OUTSIDE + "/PWNED_cam")
    out = env.tmp / "drive"
    argv = [
        "--run",
        str(env.run),
        "--motion",
        str(cap),
        "--out",
        str(out),
        "--lpips",
        "off",
        "--image-scale",
        "0.25",
        "--count",
        "2",
    ]
    check_refused(
        "avatar-drive", argv, [cap, env.run], ("calibration.json", "PWNED_cam", "not a plain name"), capsys, env
    )


def test_parameter_name_climbing_out_is_refused(env, capsys):
    """localize used to write influence_{param}.png outside the dataset."""

    def mutate(cap: Path) -> None:
        def ren(r):
            old = r["pose_params"][3]["name"]
            new = "x/../../../../" + OUTSIDE + "/PWNED_param"
            r["pose_params"][3]["name"] = new
            for g in r["groups"].values():
                g[:] = [new if n == old else n for n in g]

        edit_json(cap / "template/rig.json", ren)

    argv, protected = prep(env, mutate)
    check_refused("avatar-prep", argv, protected, ("rig.json", "pose_params[3].name", "not a plain name"), capsys, env)


def test_joint_and_split_names_are_checked(env, capsys):
    argv, protected = prep(
        env, lambda c: edit_json(c / "template/rig.json", lambda r: r["joints"][-1].__setitem__("name", "a\\b/.."))
    )
    check_refused("avatar-prep", argv, protected, ("rig.json", "joints[", ".name", "not a plain name"), capsys, env)
    shutil.rmtree(env.tmp / "capture"), shutil.rmtree(env.tmp / "dataset")
    argv, protected = prep(
        env, lambda c: edit_json(c / "splits.json", lambda s: s.__setitem__("../test", s.pop("test")))
    )
    check_refused("avatar-prep", argv, protected, ("splits.json", "../test", "split name"), capsys, env)


@pytest.mark.parametrize(
    "name,ok",
    [
        ("full00", True),
        ("Neck.ry", True),
        ("mixamorig:Hips", True),
        ("l_hand+1", True),
        ("..", False),
        (".hidden", False),
        ("-rf", False),
        ("a/b", False),
        ("a\\b", False),
        ("", False),
        ("x" * 129, False),
        ("nul\0", False),
        ("sp ace", False),
        (3, False),
    ],
)
def test_check_name(name, ok):
    if ok:
        assert check_name(name, "f.json", "fld") == name
    else:
        with pytest.raises(SchemaError, match="f.json: fld"):
            check_name(name, "f.json", "fld")


def test_every_atomic_write_stays_in_the_output_roots(tmp_path):
    """The guard under every writer: inside the roots fine; '..', absolute paths and symlinks out refused."""
    out, elsewhere = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir(), elsewhere.mkdir()
    (out / "link").symlink_to(elsewhere, target_is_directory=True)
    with output_roots(out):
        atomic_write_bytes(out / "a" / "ok.bin", b"1")
        for bad in (out / ".." / "elsewhere" / "x.bin", elsewhere / "x.bin", out / "link" / "x.bin"):
            with pytest.raises(SchemaError, match="outside the output folder"):
                atomic_write_bytes(bad, b"1")
    atomic_write_bytes(elsewhere / "free.bin", b"1")  # no roots registered: library use is unrestricted
    assert sorted(p.name for p in elsewhere.iterdir()) == ["free.bin"]
    assert output_path(out, "frames", "cam", "1.png") == out / "frames" / "cam" / "1.png"
    for parts in (("..", "x"), ("/etc", "x"), ("link", "x")):
        with pytest.raises(SchemaError, match="outside the output folder"):
            output_path(out, *parts)


# --------------------------------------------------------------------------- masks
def _recode_masks(cap: Path, fn: Callable[[np.ndarray], np.ndarray]) -> None:
    for p in sorted((cap / "masks").rglob("*.png")):
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(p), fn(m))


ENCODINGS = {
    "0/1": lambda m: (m > 127).astype(np.uint8),
    "red RGB": lambda m: np.dstack([np.zeros_like(m), np.zeros_like(m), m]),  # OpenCV order: B, G, R
    "grey RGB": lambda m: np.dstack([m, m, m]),
    "RGBA alpha": lambda m: np.dstack([np.full_like(m, 90), np.full_like(m, 90), np.full_like(m, 90), m]),
    "16-bit": lambda m: m.astype(np.uint16) * 257,
}


@pytest.mark.parametrize("encoding", list(ENCODINGS))
def test_common_mask_encodings_give_the_plain_masks_values(encoding, tiny_capture):
    """Each encoding decodes to the same [0, 1] mask as the 0..255 grey PNG it was made from."""
    for p in sorted((tiny_capture / "masks").rglob("*.png"))[:6]:
        m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        want = decode_mask(m)
        got = decode_mask(ENCODINGS[encoding](m))
        tol = 0 if encoding != "0/1" else 1.0  # 0/1 is binary: soft edges become hard
        assert np.abs(got - want).max() <= tol and np.array_equal(got > 0.5, want > 0.5)


def test_red_masks_prepare_the_same_textures(env, capsys):
    """End to end: a capture with red RGB masks gives the textures of the original capture."""
    argv, _ = prep(env, lambda c: _recode_masks(c, ENCODINGS["red RGB"]))
    assert run_cli("avatar-prep", argv) == 0, capsys.readouterr().err
    a = np.load(env.dataset / "project_uv/shard-00000.npz")["texture"]
    b = np.load(env.tmp / "dataset/project_uv/shard-00000.npz")["texture"]
    assert np.array_equal(a, b)


@pytest.mark.parametrize(
    "what,mutate,expect",
    [
        (
            "colour photo as mask",
            lambda c: _recode_masks(c, lambda m: np.random.default_rng(0).integers(0, 255, (*m.shape, 3), np.uint8)),
            ("masks/", "colour image, not a mask"),
        ),
        ("empty masks", lambda c: _recode_masks(c, lambda m: np.zeros_like(m)), ("masks", "empty or all foreground")),
        (
            "all-foreground masks",
            lambda c: _recode_masks(c, lambda m: np.full_like(m, 255)),
            ("masks", "empty or all foreground"),
        ),
        (
            "green-screen colours as mask",
            lambda c: _recode_masks(c, lambda m: np.dstack([m, np.maximum(m, 255 - m), m])),
            ("masks/", "colour image, not a mask"),
        ),
    ],
)
def test_masks_that_would_empty_the_dataset_are_refused(what, mutate, expect, env, capsys):
    argv, protected = prep(env, mutate)
    check_refused("avatar-prep", argv, protected, expect, capsys, env)


# --------------------------------------------------------------------------- strict JSON and plausible numbers
def _raw_edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def _dup_key(cap: Path) -> None:  # a second "full00" entry: json would keep the last silently
    cal = json.loads((cap / "calibration.json").read_text())
    body = ", ".join(f'"{k}": {json.dumps(v)}' for k, v in cal.items())
    (cap / "calibration.json").write_text("{" + body + f', "full00": {json.dumps(list(cal.values())[-1])}' + "}")


def _cal(fn):
    return lambda cap: edit_json(cap / "calibration.json", fn)


STRICT = [
    ("duplicate key", _dup_key, ("calibration.json", "full00", "key given twice")),
    ("NaN literal", lambda c: _raw_edit(c / "capture.json", '"fps": ', '"fps": NaN, "x": '), ("capture.json", "NaN")),
    (
        "boolean fps",
        lambda c: edit_json(c / "capture.json", lambda o: o.__setitem__("fps", True)),
        ("capture.json", "fps"),
    ),
    (
        "boolean num_frames",
        lambda c: edit_json(c / "capture.json", lambda o: o.__setitem__("num_frames", True)),
        ("capture.json", "num_frames"),
    ),
    ("boolean image size", _cal(lambda o: o["full00"].__setitem__("imgSize", [True, 128])), ("full00.imgSize",)),
    (
        "boolean frame index",
        lambda c: edit_json(c / "splits.json", lambda s: s["train"]["frames"].__setitem__(0, False)),
        ("splits.json", "train.frames", "not booleans"),
    ),
    ("boolean in K", _cal(lambda o: o["full00"]["K"][2].__setitem__(2, True)), ("calibration.json", "full00.K")),
    (
        "focal length 1e-300",
        _cal(lambda o: o["full00"]["K"][0].__setitem__(0, 1e-300)),
        ("full00.K", "fx", "implausible"),
    ),
    ("focal length 1e12", _cal(lambda o: o["full00"]["K"][1].__setitem__(1, 1e12)), ("full00.K", "fy", "implausible")),
    (
        "principal point far outside",
        _cal(lambda o: o["full00"]["K"][0].__setitem__(2, 1e6)),
        ("full00.K", "principal point"),
    ),
    (
        "distortion 1e30",
        _cal(lambda o: o["full00"].__setitem__("distCoeff", [1e30, 0, 0, 0, 0])),
        ("full00.distCoeff", "implausible"),
    ),
    ("translation in millimetres", _cal(lambda o: o["full00"].__setitem__("T", [0, 0, 3e4])), ("full00.T", "metres")),
    (
        "camera in train and test",
        lambda c: edit_json(c / "splits.json", lambda s: s["test"]["cameras"].append("full00")),
        ("splits.json", "test.cameras", "full00", "also in train"),
    ),
    (
        "frame in train and test",
        lambda c: edit_json(c / "splits.json", lambda s: s["test"]["frames"].append(0)),
        ("splits.json", "test.frames", "also in train"),
    ),
    (
        "frame listed twice",
        lambda c: edit_json(c / "splits.json", lambda s: s["train"]["frames"].append(s["train"]["frames"][0])),
        ("splits.json", "train.frames", "twice"),
    ),
    (
        "num_frames disagrees with motion",
        lambda c: edit_json(c / "capture.json", lambda o: o.__setitem__("num_frames", o["num_frames"] + 5)),
        ("capture.json", "num_frames", "motion.npz"),
    ),
    (
        "deeply nested JSON",
        lambda c: (c / "splits.json").write_text("[" * 100000 + "]" * 100000),
        ("splits.json", "nested"),
    ),
    (
        "rig parent not a name",
        lambda c: edit_json(c / "template/rig.json", lambda r: r["joints"][1].__setitem__("parent", [1])),
        ("rig.json", "joints[1].parent"),
    ),
    (
        "rig head of booleans",
        lambda c: edit_json(c / "template/rig.json", lambda r: r["joints"][1].__setitem__("head", [True, 0, 0])),
        ("rig.json", "joints[1].head"),
    ),
]


@pytest.mark.parametrize("what,mutate,expect", STRICT, ids=[s[0] for s in STRICT])
def test_json_that_is_not_what_it_seems_is_refused(what, mutate, expect, env, capsys):
    argv, protected = prep(env, mutate)
    check_refused("avatar-prep", argv, protected, expect, capsys, env)


# --------------------------------------------------------------------------- faults: full disk, Ctrl-C
def test_disk_full_during_prep_names_the_file_and_keeps_the_dataset(env, capsys, monkeypatch):
    """ENOSPC from the first shard write: exit 1, 'no space left on <file>', nothing already there changed."""
    import gsavatar.utils.io as io_mod

    real = io_mod.np.savez

    def full(file, *a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(io_mod.np, "savez", full)
    argv, protected = prep(env, lambda c: None)
    err = check_refused(
        "avatar-prep", argv, protected, ("no space left on", "shard-00000.npz", "intact"), capsys, env, code=1
    )
    assert "re-run" in err
    monkeypatch.setattr(io_mod.np, "savez", real)
    assert run_cli("avatar-prep", argv) == 0  # the same command resumes once there is space


def test_file_size_limit_at_checkpoint_time_is_reported_and_resumable(env):
    """A real kernel refusal (RLIMIT_FSIZE -> EFBIG) while writing latest.pt, in a subprocess: exit 1 naming the
    checkpoint, the previous checkpoint intact, and the same command without the limit resumes."""
    import resource

    run = env.tmp / "run"
    cmd = [
        sys.executable,
        "-m",
        "gsavatar.train.cli",
        "avatar",
        "--dataset",
        str(env.dataset),
        "--out",
        str(run),
        *TRAIN_ARGS,
    ]
    first = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=600)
    assert first.returncode == 0, first.stderr
    ckpt = run / "checkpoints/latest.pt"
    before = tree_digest(run)
    limit = ckpt.stat().st_size // 2  # config/metrics lines fit, the checkpoint does not

    def small_files() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    r = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=600, preexec_fn=small_files)
    assert r.returncode == 1, r.stderr
    assert "Traceback" not in r.stderr
    assert "latest.pt" in r.stderr and "file size limit" in r.stderr, r.stderr
    assert tree_digest(ckpt) == {str(ckpt): before[str(ckpt)]}
    again = subprocess.run(cmd, capture_output=True, text=True, env=subprocess_env(), timeout=600)
    assert again.returncode == 0, again.stderr


def test_ctrl_c_during_training_exits_130_and_says_how_to_resume(env):
    run = env.tmp / "run"
    cmd = [
        sys.executable,
        "-m",
        "gsavatar.train.cli",
        "avatar",
        "--dataset",
        str(env.dataset),
        "--out",
        str(run),
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
        "100000",
        "--checkpoint-every",
        "1",
    ]
    # A test runner started in the background of a non-interactive shell (nohup ... &) ignores SIGINT, and
    # children inherit the ignore (Python then installs no handler): give the child the default disposition,
    # as a terminal's foreground process has.
    p = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=subprocess_env(),
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.time() + 300
    while not (run / "checkpoints/latest.pt").exists() and time.time() < deadline and p.poll() is None:
        time.sleep(0.2)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert "interrupted" in err and "resume" in err, err
    r = subprocess.run(
        [*cmd, "--max-steps-this-run", "1"], capture_output=True, text=True, env=subprocess_env(), timeout=600
    )
    assert r.returncode == 0, r.stderr


# --------------------------------------------------------------------------- EXIF orientation
def _write_jpeg(path: Path, rgb_u8: np.ndarray, orientation: int) -> None:
    import OpenImageIO as oiio

    spec = oiio.ImageSpec(rgb_u8.shape[1], rgb_u8.shape[0], 3, oiio.UINT8)
    spec.attribute("Orientation", orientation)
    spec.attribute("Compression", "jpeg:100")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(rgb_u8) and out.close()


def test_exif_orientation_of_jpeg_images_is_applied(env, capsys):
    """A camera whose JPEGs are stored sideways with EXIF orientation 6 (as phones do) gives the textures of
    the same camera stored upright: the orientation is applied, and the size check uses the upright size."""

    def to_jpeg(cap: Path, rotated: bool) -> None:
        for p in sorted((cap / "images/full00").glob("*.png")):
            rgb = cv2.imread(str(p))[..., ::-1]
            _write_jpeg(
                p.with_suffix(".jpg"),
                np.ascontiguousarray(rgb if rotated is False else np.rot90(rgb)),
                6 if rotated else 1,
            )
            p.unlink()

    textures = {}
    for rotated in (False, True, None):  # None: stored sideways, orientation tag stripped (what ignoring it reads)
        name = {False: "upright", True: "rot", None: "ignored"}[rotated]
        cap = copy_capture(env.capture, env.tmp / f"capture_{name}")
        to_jpeg(cap, rotated)
        ds = copy_dataset(env.dataset, env.tmp / f"dataset_{name}", capture=cap, drop=("project-uv",))
        assert run_cli("avatar-prep", ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS]) == 0, (
            capsys.readouterr().err
        )
        textures[name] = np.load(ds / "project_uv/shard-00000.npz")["texture"].astype(np.float32)
    err = {k: float(np.abs(textures[k] - textures["upright"]).mean()) for k in ("rot", "ignored")}
    assert err["rot"] < 0.1 * err["ignored"], err  # JPEG blocks differ once rotated: equal up to compression


def test_ctrl_c_while_a_checkpoint_is_written_words_the_hint_then(tmp_path, capsys):
    """save_checkpoint, replacing latest.pt, sets a hint that is worded when Ctrl-C comes: the first save interrupted
    before its file exists says "starts from step 0", one interrupted after says "resume" (the race the test above
    can hit)."""
    from gsavatar.runs.checkpoint import resume_hint
    from gsavatar.utils.cli import EXIT_INTERRUPTED, run_reporting_errors, set_resume_hint

    ckpt = tmp_path / "latest.pt"

    def interrupted(write: bool):
        def fn():
            set_resume_hint(lambda: resume_hint(ckpt, None))
            if write:
                ckpt.write_bytes(b"x")
            raise KeyboardInterrupt

        return fn

    assert run_reporting_errors(interrupted(False)) == EXIT_INTERRUPTED
    assert "starts from step 0" in capsys.readouterr().err
    assert run_reporting_errors(interrupted(True)) == EXIT_INTERRUPTED
    err = capsys.readouterr().err
    assert "resume from its last checkpoint" in err and str(ckpt) in err
