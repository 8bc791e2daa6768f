"""Fingerprints of the capture files a prep stage reads, so a changed input makes the stage re-run.

A fingerprint is a flat ``{name: token}`` dict, recorded with the stage (``dataset.json``
``stages.<stage>.inputs``) and, for per-frame files, in each shard's sidecar:

- small metadata files (capture.json, calibration.json, splits.json, motion.npz, every file under
  ``template/``): ``sha256:<hex>`` of the bytes;
- per-frame images and masks: ``stat:<size>:<mtime_ns>``. Hashing every image on every run would
  cost minutes on a real capture; an edit that keeps both size and mtime is not detected (copying a
  capture without keeping mtimes, e.g. ``cp -r`` without ``-p``, re-projects it once);
- an upstream stage ``stage:<name>``: :func:`gsavatar.data_schema.dataset.stage_identity` (its
  version, config and inputs), so a stage downstream of a recomputed one re-runs as well.

Names are relative to the capture root: moving or copying a capture (with its mtimes) keeps them.
"""

from __future__ import annotations

from pathlib import Path

from gsavatar.data_schema import Capture
from gsavatar.data_schema.dataset import stage_identity
from gsavatar.utils.io import sha256_file

MISSING = "missing"


def content_token(path: Path) -> str:
    """``sha256:<hex>`` of a small file, ``missing`` if there is none."""
    return f"sha256:{sha256_file(path)}" if path.is_file() else MISSING


def stat_token(path: Path) -> str:
    """``stat:<size>:<mtime_ns>`` of a large per-frame file, ``missing`` if there is none."""
    try:
        st = path.stat()
    except OSError:
        return MISSING
    return f"stat:{st.st_size}:{st.st_mtime_ns}"


def metadata_inputs(capture_root: Path, names: tuple[str, ...]) -> dict[str, str]:
    """Content tokens of capture files ``names``; a name ending in ``/`` stands for every file below it."""
    root = Path(capture_root)
    out: dict[str, str] = {}
    for name in names:
        if name.endswith("/"):
            d = root / name
            for p in sorted(d.rglob("*")) if d.is_dir() else []:
                if p.is_file():
                    out[p.relative_to(root).as_posix()] = content_token(p)
        else:
            out[name] = content_token(root / name)
    return out


def upstream_inputs(dataset: Path, stages: tuple[str, ...]) -> dict[str, str]:
    """``{"stage:<name>": identity}`` of the stages whose outputs a stage reads (``missing`` if not run)."""
    return {f"stage:{s}": stage_identity(Path(dataset), s) or MISSING for s in stages}


def frame_inputs(cap: Capture, frames: list[int], cams: list[str]) -> dict[str, str]:
    """Stat tokens of the images and masks of ``frames`` seen by ``cams`` (names relative to the capture)."""
    out: dict[str, str] = {}
    for f in frames:
        for c in cams:
            for p in (cap.image_path(c, f), cap.mask_path(c, f)):
                out[p.relative_to(cap.root).as_posix()] = stat_token(p)
    return out
