"""Shared helpers of the reliability suite: file-tree digests, corrupted copies, CLI runners."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

REPO = Path(__file__).resolve().parents[2]
PREP_ARGS = ["--workers", "1", "--project.tex-size", "128", "--no-figures"]
"""Settings of the session's ``tiny_dataset`` (tests/conftest.py): stages re-run with them are skipped."""


class Env(NamedTuple):
    """What a bad-input case builds on (copies under ``tmp``, never the fixtures themselves)."""

    tmp: Path
    capture: Path
    """Pristine session capture (copied, never modified)."""
    dataset: Path
    """Pristine session dataset (``avatar-prep all`` of ``capture``)."""
    run: Path
    """Session pose-only run for avatar-drive (protected: drive must not write into it)."""
    drive_out: Path
    """Outputs of an earlier successful drive (copied as the pre-existing --out)."""


Setup = Callable[[Env], tuple[list[str], list[Path]]]
"""Builds the bad input; returns (argv, paths whose files must be byte-identical afterwards)."""


@dataclass(frozen=True)
class Case:
    kind: str
    cli: str
    setup: Setup
    expect: tuple[str, ...]
    """Fragments that must all appear in stderr (file and/or field, reason)."""


def case_registry(cases: list[Case]) -> Callable[..., Callable[[Setup], Setup]]:
    """``case = case_registry(CASES)``; then ``@case(kind, cli, *expect)`` on a setup function appends a Case."""

    def case(kind: str, cli: str, *expect: str) -> Callable[[Setup], Setup]:
        def register(fn: Setup) -> Setup:
            cases.append(Case(kind, cli, fn, expect))
            return fn

        return register

    return case


def tree_digest(*roots: Path) -> dict[str, str]:
    """sha256 of every file under ``roots`` (a root may be a single file), keyed by path."""
    out = {}
    for root in roots:
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for p in files:
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def subprocess_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO / "src"), "OMP_NUM_THREADS": "1"}


def copy_capture(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def copy_dataset(src: Path, dst: Path, capture: Path | None = None, drop: tuple[str, ...] = ()) -> Path:
    """Copy a prepared dataset; optionally point it at another capture and forget stages ``drop``."""
    shutil.copytree(src, dst)
    meta = json.loads((dst / "dataset.json").read_text())
    if capture is not None:
        meta["capture"] = str(capture)
    for stage in drop:
        del meta["stages"][stage]
        shutil.rmtree(dst / stage.replace("-", "_"))
    (dst / "dataset.json").write_text(json.dumps(meta, indent=1))
    return dst


def edit_json(path: Path, fn) -> None:
    obj = json.loads(path.read_text())
    fn(obj)
    path.write_text(json.dumps(obj))


def edit_npz(path: Path, **changes) -> None:
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d.update(changes)
    np.savez(path, **d)


def truncate(path: Path, keep: int) -> None:
    path.write_bytes(path.read_bytes()[:keep])


def flip_byte(path: Path, at: float = 0.5) -> None:
    data = bytearray(path.read_bytes())
    data[int(len(data) * at)] ^= 0xFF
    path.write_bytes(bytes(data))


def npz_arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
