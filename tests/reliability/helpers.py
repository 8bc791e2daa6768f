"""Shared helpers of the reliability suite: file-tree digests, corrupted copies, CLI runners."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
PREP_ARGS = ["--workers", "1", "--project.tex-size", "128", "--no-figures"]
"""Settings of the session's ``tiny_dataset`` (tests/conftest.py): stages re-run with them are skipped."""


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
