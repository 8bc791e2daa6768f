"""Hostile files through the real entry points: inputs that used to hang (a FIFO for an image),
allocate without bound (a BVH ``Frame Time`` of 1e9, an fps of 1e-7, an npz bomb) or end in a
traceback or a message without a file name (npy bytes as .npz, NaN in EXR pixels or OBJ lines,
a BVH without frames, a garbage run config.json).

Each must give exit code 2, one ``error:`` line naming the file and the field, no traceback, and
leave every file that was already there byte-identical. Inputs are copies under ``tmp_path``.
docs/reliability.md lists the kinds ("resource bounds", "faults").
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from gsavatar.utils.errors import SchemaError
from gsavatar.data_schema.limits import MAX_RESAMPLED_FRAMES
from gsavatar.drive.cli import main as drive_main
from gsavatar.prep.cli import main as prep_main
from gsavatar.train.cli import main as train_main
from gsavatar.utils.io import read_image, read_npz, write_image
from reliability.helpers import (
    PREP_ARGS,
    Case,
    Env,
    case_registry,
    copy_capture,
    copy_dataset,
    subprocess_env,
    tree_digest,
)

DRIVE_ARGS = ["--lpips", "off", "--image-scale", "0.25"]
MAINS = {"avatar-prep": prep_main, "avatar-train": train_main, "avatar-drive": drive_main}


CASES: list[Case] = []
case = case_registry(CASES)


# --------------------------------------------------------------------------- builders
def bvh_text(frames: str = "2", frame_time: str = "0.0333333", rows: int = 2, hierarchy: str | None = None) -> str:
    """A one-joint BVH (6 channels) with the given ``Frames:``/``Frame Time:`` values and ``rows`` rows."""
    hierarchy = hierarchy or (
        "ROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation "
        "Yrotation Xrotation\n End Site\n {\n  OFFSET 0 1 0\n }\n}\n"
    )
    return f"HIERARCHY\n{hierarchy}MOTION\nFrames: {frames}\nFrame Time: {frame_time}\n" + "0 0 0 0 0 0\n" * rows


def nested_hierarchy(depth: int) -> str:
    """``depth`` joints each inside the previous one (a recursive parser overflows the stack)."""
    opening = "".join(f"JOINT j{i}\n{{\n OFFSET 0 1 0\n CHANNELS 0\n" for i in range(depth))
    return (
        "ROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation\n"
        + opening
        + "}\n" * depth
        + "}\n"
    )


def pose_dim(env: Env) -> int:
    from gsavatar.data_schema import load_capture

    return load_capture(env.capture).rig.pose_dim


def motion_arrays(env: Env, frames: int = 3, **changes) -> dict[str, np.ndarray]:
    return {
        "pose": np.zeros((frames, pose_dim(env)), np.float32),
        "root_rotation": np.zeros((frames, 3), np.float32),
        "root_translation": np.zeros((frames, 3), np.float32),
        "fps": np.float32(15.0),
        **changes,
    }


def npz(env: Env, name: str = "walk.npz", compressed: bool = False, **arrays) -> Path:
    (np.savez_compressed if compressed else np.savez)(env.tmp / name, **arrays)
    return env.tmp / name


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def declare_uncompressed_size(path: Path, member: str, size: int) -> None:
    """Rewrite the uncompressed size that the zip central directory declares for ``member`` (what an
    npz bomb looks like before decompression, without writing GBs in the test)."""
    data = bytearray(path.read_bytes())
    i = 0
    while (i := data.find(b"PK\x01\x02", i)) >= 0:
        n = int.from_bytes(data[i + 28 : i + 30], "little")
        if data[i + 46 : i + 46 + n] == member.encode():
            data[i + 24 : i + 28] = size.to_bytes(4, "little")
            path.write_bytes(bytes(data))
            return
        i += 4
    raise AssertionError(f"{member} not in {path}")


def lying_header_npz(path: Path, key: str, shape: tuple[int, ...], others: dict[str, np.ndarray]) -> Path:
    """An npz whose ``key`` member has an .npy header declaring ``shape`` (float64) and 64 bytes of data."""
    np.savez(path, **others)
    hdr = io.BytesIO()
    np.lib.format.write_array_header_1_0(hdr, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "a") as z:
        z.writestr(f"{key}.npy", hdr.getvalue() + bytes(64))
    return path


@contextlib.contextmanager
def fifo_guard(path: Path, after_s: float = 20.0) -> Iterator[list[bool]]:
    """If a reader still blocks opening the FIFO ``path`` after ``after_s``, open its write end so the reader
    sees EOF: a regression fails the test (yielded flag set) instead of hanging the suite."""
    stop, unblocked = threading.Event(), [False]

    def unblock() -> None:
        deadline = time.monotonic() + after_s
        while not stop.wait(0.2):
            if time.monotonic() < deadline:
                continue
            try:
                fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)  # ENXIO while nobody reads: nothing blocks
            except OSError:
                continue
            os.close(fd)
            unblocked[0] = True

    t = threading.Thread(target=unblock, daemon=True)
    t.start()
    try:
        yield unblocked
    finally:
        stop.set()
        t.join()


# --------------------------------------------------------------------------- avatar-drive
def drive(env: Env, motion: Path, *extra: str, run: Path | None = None) -> tuple[list[str], list[Path]]:
    """Drive into a copy of earlier drive results (which must survive) with the given motion."""
    out = env.tmp / "out"
    shutil.copytree(env.drive_out, out)
    run = run or env.run
    return ["--run", str(run), "--motion", str(motion), "--out", str(out), *DRIVE_ARGS, *extra], [run, out, motion]


def bvh(env: Env, text: str) -> Path:
    (env.tmp / "walk.bvh").write_text(text)
    return env.tmp / "walk.bvh"


@case("BVH Frame Time of 1e9 s", "avatar-drive", "walk.bvh", "line 13", "Frame Time", "1e9", "outside")
def _(env):
    return drive(env, bvh(env, bvh_text(frame_time="1e9")), "--count", "2")


@case("BVH Frame Time of 1e-9 s", "avatar-drive", "walk.bvh", "line 13", "Frame Time", "1e-9", "outside")
def _(env):
    return drive(env, bvh(env, bvh_text(frame_time="1e-9")), "--count", "2")


@case("BVH without frames", "avatar-drive", "walk.bvh", "line 12", "Frames: no motion frames")
def _(env):
    return drive(env, bvh(env, bvh_text(frames="0", rows=0)))


@case("BVH declaring 10^12 frames", "avatar-drive", "walk.bvh", "MOTION truncated", "1000000000000", "only 2")
def _(env):  # the [F, C] array was allocated from the declared count before the rows were read
    return drive(env, bvh(env, bvh_text(frames="1000000000000")))


@case("BVH with a negative frame count", "avatar-drive", "walk.bvh", "line 12", "Frames:", "-5")
def _(env):
    return drive(env, bvh(env, bvh_text(frames="-5")))


@case("BVH joints nested 2000 deep", "avatar-drive", "walk.bvh", "line", "nested deeper than")
def _(env):  # was a RecursionError traceback
    return drive(env, bvh(env, bvh_text(hierarchy=nested_hierarchy(2000))))


@case("BVH channel count above its names", "avatar-drive", "walk.bvh", "line 6", "CHANNELS", "unknown channel 'End'")
def _(env):  # 6 declared, 5 named: the parser takes 'End' (of End Site) for the 6th
    return drive(env, bvh(env, bvh_text().replace(" Xrotation\n End Site", "\n End Site")))


@case(
    "BVH whose resampling makes too many frames",
    "avatar-drive",
    "walk.bvh",
    "MOTION",
    f"more than the {MAX_RESAMPLED_FRAMES}",
)
def _(env):  # 1 fps x 14000 frames -> 15 fps: 209986 output frames
    return drive(env, bvh(env, bvh_text(frames="14000", frame_time="1", rows=14000)))


@case("motion fps of 1e-7 (npz key)", "avatar-drive", "walk.npz", "fps", "1e-07", "outside the plausible range")
def _(env):
    return drive(env, npz(env, **motion_arrays(env, fps=np.float64(1e-7))))


@case("motion fps of 1e-7 (sidecar json)", "avatar-drive", "walk.json", "fps", "1e-07", "outside the plausible range")
def _(env):
    arrays = motion_arrays(env)
    del arrays["fps"]
    (env.tmp / "walk.json").write_text(json.dumps({"fps": 1e-7}))
    return drive(env, npz(env, **arrays))


@case("sidecar json with the fps twice", "avatar-drive", "walk.json", "fps", "key given twice")
def _(env):
    arrays = motion_arrays(env)
    del arrays["fps"]
    (env.tmp / "walk.json").write_text('{"fps": 15, "fps": 1e-7}')
    return drive(env, npz(env, **arrays))


@case("--motion-fps of 1e-7", "avatar-drive", "fps", "walk.npz", "1e-07", "outside the plausible range")
def _(env):
    return drive(env, npz(env, **motion_arrays(env)), "--motion-fps", "1e-7")


@case(
    "npz motion whose resampling makes too many frames",
    "avatar-drive",
    "walk.npz",
    "fps",
    f"more than the {MAX_RESAMPLED_FRAMES}",
)
def _(env):  # 1 fps x 14000 frames -> 15 fps
    return drive(env, npz(env, **motion_arrays(env, frames=14000, fps=np.float32(1.0))))


@case("npy bytes saved as .npz", "avatar-drive", "walk.npz", "not an npz archive")
def _(env):
    (env.tmp / "walk.npz").write_bytes(npy_bytes(np.zeros((3, 4), np.float32)))
    return drive(env, env.tmp / "walk.npz")


@case("npz array declaring 3 GiB uncompressed", "avatar-drive", "walk.npz", "pose", "bytes uncompressed", "more than")
def _(env):
    path = npz(env, compressed=True, **motion_arrays(env))
    declare_uncompressed_size(path, "pose.npy", 3 << 30)
    return drive(env, path)


@case("npy header declaring 8 TB in a small member", "avatar-drive", "walk.npz", "pose", "header declares shape")
def _(env):
    others = {k: v for k, v in motion_arrays(env).items() if k != "pose"}
    return drive(env, lying_header_npz(env.tmp / "walk.npz", "pose", (10**6, 10**6), others))


@case("FIFO as BVH", "avatar-drive", "walk.bvh", "not a regular file")
def _(env):
    os.mkfifo(env.tmp / "walk.bvh")
    return drive(env, env.tmp / "walk.bvh")


@case("FIFO as motion npz", "avatar-drive", "walk.npz", "not a regular file")
def _(env):
    os.mkfifo(env.tmp / "walk.npz")
    return drive(env, env.tmp / "walk.npz")


def run_copy(env: Env, text: str | None = None, edit: Callable[[dict], object] | None = None) -> Path:
    """A copy of the session run with its config.json replaced by ``text`` or edited by ``edit``."""
    run = env.tmp / "run"
    shutil.copytree(env.run, run)
    cfg = run / "config.json"
    if edit is not None:
        obj = json.loads(cfg.read_text())
        edit(obj)
        text = json.dumps(obj)
    cfg.write_text(text)
    return run


RUN_CONFIGS: dict[str, tuple[Callable[[Env], Path], tuple[str, ...]]] = {
    "run config.json that is not JSON": (lambda e: run_copy(e, '{"train": [1, 2'), ("config.json", "invalid JSON")),
    "run config.json that is a list": (lambda e: run_copy(e, "[]"), ("config.json", "train", "missing")),
    "run config.json with a string step count": (
        lambda e: run_copy(e, edit=lambda o: o["train"]["schedule"].update(steps="many")),
        ("config.json", "train.schedule.steps", "'many'"),
    ),
    "run config.json of the old flat layout with a string step count": (
        lambda e: run_copy(e, edit=lambda o: o["train"].update(steps="many")),
        ("config.json", "train.schedule.steps", "'many'"),
    ),
    "run config.json with a boolean preset": (
        lambda e: run_copy(e, edit=lambda o: o["train"].update(preset=True)),
        ("config.json", "train.preset", "True"),
    ),
    "run config.json without the dataset": (
        lambda e: run_copy(e, edit=lambda o: o["train"].pop("dataset")),
        ("config.json", "train.dataset", "missing"),
    ),
    "run config.json with negative eval frames": (
        lambda e: run_copy(e, edit=lambda o: o["train"].update(eval_frames=-3)),
        ("config.json", "eval_frames", "-3"),
    ),
    "run config.json with a duplicate key": (
        lambda e: run_copy(e, '{"train": {}, "train": {}}'),
        ("config.json", "train", "key given twice"),
    ),
}
for _kind, (_make, _expect) in RUN_CONFIGS.items():

    def _drive_setup(env, make=_make):
        return drive(env, env.capture, "--count", "2", run=make(env))

    def _eval_setup(env, make=_make):
        run = make(env)
        return ["eval", "--run", str(run)], [run, env.dataset]

    case(_kind, "avatar-drive", *_expect)(_drive_setup)
    case(_kind, "avatar-train", *_expect)(_eval_setup)


# --------------------------------------------------------------------------- avatar-prep
def prep_all(env: Env, mutate: Callable[[Path], object]) -> tuple[list[str], list[Path]]:
    """``avatar-prep all`` of a damaged capture copy into a dataset whose project-uv stage (the one that
    reads every image) is still to run: the stages already there must survive the failure."""
    cap = copy_capture(env.capture, env.tmp / "capture")
    ds = copy_dataset(env.dataset, env.tmp / "dataset", capture=cap, drop=("project-uv",))
    mutate(cap)
    return ["all", "--capture", str(cap), "--out", str(ds), *PREP_ARGS], [cap, ds]


def first_line(path: Path, prefix: str) -> int:
    """1-based number of the first line of ``path`` starting with ``prefix``."""
    return next(i for i, ln in enumerate(path.read_text().splitlines(), 1) if ln.startswith(prefix))


def replace_line(path: Path, lineno: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[lineno - 1] = text
    path.write_text("\n".join(lines) + "\n")


MESH = "template/mesh.obj"
OBJ_LINES = {"vt": "vt nan 0.5", "v": "v 0.1 inf 0.2", "f": "f 1 2 99999999"}
"""A bad line replacing the first line of each kind in the capture's mesh.obj."""


def _obj_case(kind: str, bad: str) -> None:
    def setup(env):
        n = first_line(env.capture / MESH, kind + " ")
        argv, protected = prep_all(env, lambda c: replace_line(c / MESH, n, bad))
        return argv, protected

    expect = ("mesh.obj", "line", f"{kind}:", "non-finite" if kind != "f" else "out of range")
    case(f"OBJ {kind} line {bad!r}", "avatar-prep", *expect)(setup)


for _kind, _bad in OBJ_LINES.items():
    _obj_case(_kind, _bad)


def _nan_normal(cap: Path) -> None:
    p = cap / MESH
    lines = p.read_text().splitlines()
    lines.insert(first_line(p, "v "), "vn nan 0 1")  # after the first vertex: line first_v + 1
    p.write_text("\n".join(lines) + "\n")


@case("OBJ vn line with NaN", "avatar-prep", "mesh.obj", "line", "vn:", "non-finite")
def _(env):
    return prep_all(env, _nan_normal)


@case("npy bytes saved as skin_weights.npz", "avatar-prep", "skin_weights.npz", "not an npz archive")
def _(env):
    return prep_all(env, lambda c: (c / "template/skin_weights.npz").write_bytes(npy_bytes(np.zeros((8, 2)))))


def _exr_camera(cap: Path, poison: Callable[[np.ndarray], object]) -> None:
    """Store camera full00's images as EXR; ``poison`` edits frame 3's pixels in place."""
    for png in sorted((cap / "images/full00").glob("*.png")):
        img = read_image(png)
        if png.stem == "00000003":
            poison(img)
        write_image(png.with_suffix(".exr"), img)
        png.unlink()


@case("NaN pixels in an EXR image", "avatar-prep", "images/full00/00000003.exr", "7 non-finite pixels")
def _(env):
    return prep_all(env, lambda c: _exr_camera(c, lambda img: img.__setitem__((slice(10, 17), 5, 1), np.nan)))


@case("Inf pixels in an EXR image", "avatar-prep", "images/full00/00000003.exr", "1 non-finite pixels")
def _(env):
    return prep_all(env, lambda c: _exr_camera(c, lambda img: img.__setitem__((0, 0), np.inf)))


# --------------------------------------------------------------------------- tests
@pytest.fixture
def env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output) -> Env:
    return Env(tmp_path, tiny_capture, tiny_dataset, pose_only_run, drive_output)


def run_cli(cli: str, argv: list[str]) -> int | str | None:
    try:
        return MAINS[cli](argv)
    except SystemExit as e:
        return e.code


def fifos(paths: list[Path]) -> list[Path]:
    out = []
    for p in paths:
        cands = [p] if not p.is_dir() else list(p.rglob("*"))
        out += [c for c in cands if c.exists() and not c.is_file() and not c.is_dir()]
    return out


@pytest.mark.parametrize("case", CASES, ids=[f"{c.cli}: {c.kind}" for c in CASES])
def test_hostile_file_is_refused_clearly_and_nothing_is_lost(case: Case, env: Env, capsys):
    argv, protected = case.setup(env)
    before = tree_digest(*protected)
    capsys.readouterr()
    with contextlib.ExitStack() as stack:
        guards = [stack.enter_context(fifo_guard(f)) for f in fifos(protected)]
        rc = run_cli(case.cli, argv)
    err = capsys.readouterr().err
    assert not any(g[0] for g in guards), f"a reader blocked on a FIFO; stderr:\n{err}"
    assert rc == 2, f"exit code {rc!r}; stderr:\n{err}"
    assert "Traceback" not in err, err
    errors = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1, err
    missing = [f for f in case.expect if f not in errors[0]]
    assert not missing, f"message lacks {missing}:\n{errors[0]}"
    after = tree_digest(*protected)
    changed = [p for p, digest in before.items() if after.get(p) != digest]
    assert not changed, f"files that existed before the failing command were changed or removed: {changed}"


def test_fifo_image_fails_prep_instead_of_hanging(env):
    """A FIFO in place of an image blocked cv2.imread/OpenImageIO forever: `avatar-prep all` must exit 2
    naming it, well within the timeout (the real console entry point, in a subprocess)."""
    img = "images/full00/00000003.png"

    def mkfifo(cap: Path) -> None:
        (cap / img).unlink()
        os.mkfifo(cap / img)

    argv, protected = prep_all(env, mkfifo)
    before = tree_digest(*protected)
    exe = Path(sys.executable).with_name("avatar-prep")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "gsavatar.prep.cli"]
    try:
        r = subprocess.run([*cmd, *argv], capture_output=True, text=True, env=subprocess_env(), timeout=240)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"avatar-prep hung on a FIFO image:\n{e.stderr}")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr, r.stderr
    errors = [ln for ln in r.stderr.splitlines() if ln.startswith("error: ")]
    assert len(errors) == 1 and img in errors[0] and "not a regular file" in errors[0], r.stderr
    assert tree_digest(*protected) == before


# --------------------------------------------------------------------------- mechanisms, without a CLI
def test_read_npz_never_decompresses_keys_it_was_not_asked_for(tmp_path):
    """An unused member whose compressed bytes are garbage: reading it would fail, so a read that only
    asks for ``pose`` proves the member is skipped (a zero-filled 1.4 GB member costs nothing either)."""
    path = tmp_path / "m.npz"
    np.savez_compressed(path, pose=np.arange(6.0).reshape(2, 3), junk=np.arange(100_000))
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("junk.npy")
    data = bytearray(path.read_bytes())
    at = info.header_offset  # local header: 30 bytes, then the name and the extra field
    start = (
        at + 30 + int.from_bytes(data[at + 26 : at + 28], "little") + int.from_bytes(data[at + 28 : at + 30], "little")
    )
    data[start + 16 : start + info.compress_size - 16] = os.urandom(info.compress_size - 32)
    path.write_bytes(bytes(data))
    assert sorted(read_npz(path, keys=("pose", "absent"))) == ["pose"]
    with pytest.raises(SchemaError, match="cannot read npz"):
        read_npz(path)


def test_read_npz_checks_sizes_before_decompressing(tmp_path):
    path = tmp_path / "m.npz"
    np.savez_compressed(path, a=np.zeros(1000), b=np.zeros(10))
    with pytest.raises(SchemaError) as e:
        read_npz(path, max_bytes=4096)
    assert e.value.field == "a" and "8128 bytes uncompressed" in str(e.value)
    assert read_npz(path, keys=("b",), max_bytes=4096)["b"].shape == (10,)


def test_driving_motion_reads_only_its_arrays(tmp_path, tiny_capture):
    from gsavatar.data_schema import load_capture
    from gsavatar.drive.motion import load_driving_motion

    rig = load_capture(tiny_capture).rig
    path = lying_header_npz(
        tmp_path / "walk.npz",
        "unused",
        (10**6, 10**6),
        {
            "pose": np.zeros((4, rig.pose_dim)),
            "root_rotation": np.zeros((4, 3)),
            "root_translation": np.zeros((4, 3)),
            "fps": np.float64(15.0),
        },
    )
    assert load_driving_motion(path, rig, 15.0).num_frames == 4


def test_train_config_round_trips_through_json():
    from gsavatar.runs.config import Schedule, TrainConfig, from_json, resolve, to_json

    cfg = TrainConfig(
        dataset=Path("ds"), out=Path("run"), lpips_weights=Path("w.pth"), schedule=Schedule(image_scale=0.5)
    )
    cfg = resolve(cfg)
    assert from_json(json.loads(json.dumps(to_json(cfg))), "config.json", model=cfg.model.to_json()) == cfg
    with pytest.raises(SchemaError, match="train.deterministic"):
        from_json({**to_json(cfg), "deterministic": 1}, "config.json")


def test_resampling_is_bounded():
    from gsavatar.motion.resample import resample_times

    with pytest.raises(ValueError, match="more than"):
        resample_times(14_000, 1.0, 15.0)
    assert len(resample_times(14_000, 120.0, 30.0).i0) == 3500


def test_suite_covers_the_kinds():
    assert len({(c.cli, c.kind) for c in CASES}) == len(CASES) >= 30
    assert {c.cli for c in CASES} == set(MAINS)
