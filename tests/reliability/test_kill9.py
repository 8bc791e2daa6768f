"""kill -9 at seeded random points of ``avatar-prep all`` and of training, then re-run / resume:
the result must equal an uninterrupted run's (arrays, manifests, records, parameters, loss curve).

Kill points of prep are the commit points of an uninterrupted reference run (every file it
writes, in the order it wrote them): scenario ``i`` waits until a seeded random one of them
appears in the interrupted run, sleeps a seeded random 0-50 ms, and SIGKILLs the whole process
group (the spawned workers too). The killed dataset must already verify (no recorded file is
half-written), and the re-run must only complete it.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from gsavatar.data_schema.dataset import verify_dataset
from gsavatar.prep.cli import main as prep_main
from gsavatar.train.cli import main as train_main
from reliability.helpers import copy_dataset, flip_byte, npz_arrays, subprocess_env

PREP = ["--workers", "1", "--shard-size", "3", "--project.tex-size", "128", "--no-figures"]
"""3 frames per shard: 4 shards per per-frame stage, so there are many commit points to hit."""
TRAIN = [
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
    "6",
    "--checkpoint-every",
    "2",
]


def kill_group(p: subprocess.Popen) -> None:
    """SIGKILL the process and its children (started with ``start_new_session=True``), then reap it."""
    try:
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    p.wait()


def prep_argv(capture: Path, out: Path, *extra: str) -> list[str]:
    return ["all", "--capture", str(capture), "--out", str(out), *PREP, *extra]


def visible_files(root: Path) -> list[str]:
    """Files of a dataset, relative; hidden temp files (orphans of a killed atomic write) excluded."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and not p.name.startswith("."))


@pytest.fixture(scope="module")
def reference(tiny_capture, tmp_path_factory) -> tuple[Path, list[str]]:
    """An uninterrupted run, and its files in the order they were committed (the kill points)."""
    ds = tmp_path_factory.mktemp("kill_ref") / "dataset"
    assert prep_main(prep_argv(tiny_capture, ds)) == 0
    order = sorted(visible_files(ds), key=lambda rel: (ds / rel).stat().st_mtime_ns)
    # dataset.json is rewritten after every stage and the last two files are written in the
    # final ~0.1 s: a kill there could arrive after the process has already finished.
    points = [rel for rel in order if rel != "dataset.json"][:-2]
    return ds, points


def strip_sha(obj):
    """JSON without sha256 fields (npz bytes hold zip timestamps; the arrays are compared instead)."""
    if isinstance(obj, dict):
        return {k: strip_sha(v) for k, v in obj.items() if k != "sha256"}
    if isinstance(obj, list):
        return [strip_sha(v) for v in obj]
    return obj


def assert_same_dataset(ref: Path, got: Path) -> None:
    assert visible_files(got) == visible_files(ref)
    a, b = json.loads((ref / "dataset.json").read_text()), json.loads((got / "dataset.json").read_text())
    assert a["capture"] == b["capture"] and sorted(a["stages"]) == sorted(b["stages"])
    for stage, rec in a["stages"].items():
        other = b["stages"][stage]
        key = lambda r: (r["version"], r["config"], sorted(r["files"]))  # noqa: E731 - not timings or checksums
        assert key(rec) == key(other), stage
    for rel in visible_files(ref):
        if rel.endswith(".npz"):
            x, y = npz_arrays(ref / rel), npz_arrays(got / rel)
            assert sorted(x) == sorted(y), rel
            for k in x:
                assert x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k], equal_nan=x[k].dtype.kind == "f"), (
                    f"{rel}:{k}"
                )
        elif rel.endswith(".json") and rel != "dataset.json":
            assert strip_sha(json.loads((ref / rel).read_text())) == strip_sha(json.loads((got / rel).read_text())), rel
    assert verify_dataset(got) == []


def start_prep(capture: Path, out: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "gsavatar.prep.cli", *prep_argv(capture, out, *extra)],
        env=subprocess_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )


def kill_when(p: subprocess.Popen, ds: Path, point: str, delay: float, timeout: float = 240.0) -> None:
    """SIGKILL ``p``'s process group ``delay`` seconds after ``ds / point`` appears."""
    path = ds / point
    deadline = time.monotonic() + timeout
    while not path.exists():
        if p.poll() is not None:
            pytest.fail(
                f"prep exited ({p.returncode}) before {path.name} appeared:\n{p.stderr.read().decode()[-2000:]}"
            )
        if time.monotonic() > deadline:
            break
        time.sleep(0.002)
    time.sleep(delay)
    kill_group(p)
    p.stderr.close()
    assert p.returncode == -signal.SIGKILL, f"prep finished (exit {p.returncode}) before the kill at {path.name}"
    orphans = [q.name for q in ds.rglob(".*") if q.is_file()]
    print(f"killed {delay * 1e3:.0f} ms after {point} appeared; orphan temp files: {orphans}")
    # nothing half-written is ever recorded: what the killed run committed already verifies
    if (ds / "dataset.json").exists():
        assert verify_dataset(ds) == [], f"killed after {point}: a recorded file does not verify"


def pick(points: list[str], rng: random.Random, segment: int, segments: int) -> str:
    """A seeded random kill point from the ``segment``-th part of the run (spreads the scenarios)."""
    lo = len(points) * segment // segments
    hi = max(len(points) * (segment + 1) // segments, lo + 1)
    return points[rng.randrange(lo, hi)]


SINGLE_KILLS = 4


@pytest.mark.parametrize("scenario", range(SINGLE_KILLS))
def test_prep_killed_at_a_random_point_then_rerun_equals_uninterrupted(scenario, reference, tiny_capture, tmp_path):
    ref, points = reference
    rng = random.Random(1000 + scenario)
    point, delay = pick(points, rng, scenario, SINGLE_KILLS), rng.uniform(0.0, 0.05)
    ds = tmp_path / "dataset"
    kill_when(start_prep(tiny_capture, ds), ds, point, delay)
    assert prep_main(prep_argv(tiny_capture, ds)) == 0
    assert_same_dataset(ref, ds)


def test_prep_killed_twice_then_rerun_equals_uninterrupted(reference, tiny_capture, tmp_path):
    ref, points = reference
    rng = random.Random(2000)
    ds = tmp_path / "dataset"
    first = points[rng.randrange(0, len(points) // 2)]
    kill_when(start_prep(tiny_capture, ds), ds, first, rng.uniform(0.0, 0.05))
    later = [rel for rel in points if not (ds / rel).exists()]
    second = later[rng.randrange(0, len(later))]
    kill_when(start_prep(tiny_capture, ds), ds, second, rng.uniform(0.0, 0.05))
    assert prep_main(prep_argv(tiny_capture, ds)) == 0
    assert_same_dataset(ref, ds)


def test_prep_with_worker_processes_killed_then_rerun_equals_uninterrupted(reference, tiny_capture, tmp_path):
    """--workers 2: the kill takes the spawned workers down too (process group, like a batch scheduler)."""
    ref, points = reference
    rng = random.Random(3000)
    ds = tmp_path / "dataset"
    shards = [rel for rel in points if rel.startswith("project_uv/shard-") and rel.endswith(".json")][:-1]
    kill_when(start_prep(tiny_capture, ds, "--workers", "2"), ds, rng.choice(shards), rng.uniform(0.0, 0.05))
    assert prep_main(prep_argv(tiny_capture, ds)) == 0
    assert_same_dataset(ref, ds)


def test_prep_rerun_repairs_a_corrupt_and_a_lost_shard(reference, tiny_capture, tmp_path):
    ref, _ = reference
    ds = copy_dataset(ref, tmp_path / "dataset")
    flip_byte(ds / "project_uv/shard-00001.npz")
    (ds / "pose_template/shard-00002.npz").unlink()
    assert len(verify_dataset(ds)) == 4  # each recorded twice: in dataset.json and in its manifest
    assert prep_main(prep_argv(tiny_capture, ds)) == 0
    assert_same_dataset(ref, ds)


# --------------------------------------------------------------------------- training
def curve(run: Path) -> dict[int, float]:
    """Loss per step (a step logged again after a resume keeps its last value)."""
    return {r["step"]: r["total"] for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())}


def params(run: Path) -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["modules"]["net"]


@pytest.fixture(scope="module")
def train_reference(tiny_dataset, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("kill_train") / "ref"
    assert train_main(["avatar", "--dataset", str(tiny_dataset), "--out", str(run), *TRAIN]) == 0
    return run


@pytest.mark.parametrize("seed", [0, 1])
def test_training_killed_at_a_random_step_then_resumed_equals_uninterrupted(
    seed, train_reference, tiny_dataset, tmp_path
):
    """Seeded random step (1-4 of 6) and delay (0-0.3 s, so sometimes mid-step or mid-checkpoint-write)."""
    rng = random.Random(seed)
    step, delay = rng.randint(1, 4), rng.uniform(0.0, 0.3)
    run = tmp_path / "run"
    argv = ["avatar", "--dataset", str(tiny_dataset), "--out", str(run), *TRAIN]
    p = subprocess.Popen(
        [sys.executable, "-m", "gsavatar.train.cli", *argv],
        env=subprocess_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 240
    while p.poll() is None and time.monotonic() < deadline:
        if (run / "metrics.jsonl").exists() and max(curve(run), default=0) >= step:
            break
        time.sleep(0.01)
    time.sleep(delay)
    kill_group(p)
    assert p.returncode == -signal.SIGKILL, f"training finished (exit {p.returncode}) before the kill at step {step}"
    print(
        f"killed {delay * 1e3:.0f} ms after step {step} was logged; "
        f"checkpoint: {(run / 'checkpoints/latest.pt').exists()}"
    )
    assert train_main(argv) == 0  # resumes from the last complete checkpoint (or from scratch)
    assert curve(run) == curve(train_reference)
    a, b = params(train_reference), params(run)
    assert sorted(a) == sorted(b) and all(torch.equal(a[k], b[k]) for k in a)
