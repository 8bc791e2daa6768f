"""Output folders a command may write into: empty, new, or already one of ours of the same kind.

Every command that takes ``--out DIR`` calls :func:`claim_output_dir` before it writes anything.
A folder it creates or claims gets a marker, ``DIR/gsavatar-output.json``
(``{"format": "gsavatar-output", "kind": ...}``; no timestamp, so an interrupted and re-run command
ends with the same bytes as an uninterrupted one), so a later run recognises it and
resumes into it. A non-empty folder without the marker is refused (a user's ``config.json`` or
``localize/hierarchy.png`` would be overwritten) unless the command's force flag is given; outputs
of gsavatar versions from before the marker are recognised by their own files (:data:`LEGACY`). A
folder holding another kind of gsavatar output (a dataset given as a run's ``--out``) is refused
even with the force flag: two outputs in one folder would break both.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from typing import Literal

from gsavatar.utils.errors import SchemaError
from gsavatar.utils.io import atomic_write_json, sha256_file
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.paths import add_output_root

OutputKind = Literal["capture", "dataset", "run", "predictor", "drive", "report"]
MARKER = "gsavatar-output.json"
MARKER_FORMAT = "gsavatar-output"
_DRIVE_FRAME = re.compile(r"\d{6}\.png")
_MARKER_TEMP = re.compile(re.escape(f".{MARKER}.") + r".+" + re.escape(Path(MARKER).suffix))
"""Temp file of a marker being written (:func:`gsavatar.utils.io.atomic_path`'s name): another process
(a torchrun rank claiming the same folder) is mid-write, or one was killed between creating and renaming it."""


def _entries(d: Path) -> list[Path]:
    """What a folder holds, less marker temp files (they do not make a folder foreign)."""
    return [p for p in d.iterdir() if not _MARKER_TEMP.fullmatch(p.name)]


def _json_dict(path: Path) -> dict | None:
    """The JSON object in ``path``, or None when it is missing, unreadable or not an object."""
    if not path.is_file():
        return None
    try:
        obj = read_json(path)
    except SchemaError:
        return None
    return obj if isinstance(obj, dict) else None


def _legacy_capture(d: Path) -> bool:
    return (_json_dict(d / "capture.json") or {}).get("format") == "gsavatar-capture"


def _legacy_dataset(d: Path) -> bool:
    return (_json_dict(d / "dataset.json") or {}).get("format") == "gsavatar-dataset"


def _legacy_run(d: Path) -> bool:
    cfg = _json_dict(d / "config.json") or {}
    return isinstance(cfg.get("train"), dict) and "dataset" in cfg["train"] and isinstance(cfg.get("model"), dict)


def _legacy_predictor(d: Path) -> bool:
    return (d / "targets.npz").is_file()


def _legacy_drive(d: Path) -> bool:
    info = _json_dict(d / "drive.json") or {}
    if "run" in info and "mode" in info:
        return True
    frames = d / "frames"
    files = [p for p in frames.rglob("*") if p.is_file()] if frames.is_dir() else []
    return bool(files) and all(p.parent.parent == frames and _DRIVE_FRAME.fullmatch(p.name) for p in files)


def _legacy_report(d: Path) -> bool:
    return _json_dict(d / "report.json") is not None


LEGACY: dict[str, Callable[[Path], bool]] = {
    "capture": _legacy_capture,
    "dataset": _legacy_dataset,
    "run": _legacy_run,
    "predictor": _legacy_predictor,
    "drive": _legacy_drive,
    "report": _legacy_report,
}
"""How each kind's folder was recognised before the marker existed (its defining file)."""


def output_kind(path: str | Path) -> str | None:
    """Kind of gsavatar output a folder holds (marker first, then :data:`LEGACY`), or None.

    Raises SchemaError naming the marker when it exists but is not one of ours (a marker is
    written atomically, so a damaged one was not written by gsavatar)."""
    d = Path(path)
    marker = d / MARKER
    if marker.exists():
        obj = read_json(marker)
        if not isinstance(obj, dict) or obj.get("format") != MARKER_FORMAT or obj.get("kind") not in LEGACY:
            raise SchemaError(
                marker,
                "kind",
                f"not a gsavatar output marker (expected format {MARKER_FORMAT!r} and a kind of {sorted(LEGACY)})",
            )
        return obj["kind"]
    for kind, is_kind in LEGACY.items():
        if is_kind(d):
            return kind
    return None


def claim_output_dir(
    path: str | Path, kind: OutputKind, force: bool = False, force_flag: str = "--force", register: bool = False
) -> Path:
    """Make ``path`` this command's output folder of ``kind``; returns it.

    Creates it (and its parents) if missing; an existing folder must be empty, or hold gsavatar output
    of the same ``kind``, or ``force`` must be set. Writes the marker unless it is already there (an
    existing marker is never rewritten: re-runs leave every byte of a finished output unchanged).
    ``force_flag`` is the flag named in the refusal. ``register``: also make it an output root of the
    running command (:func:`gsavatar.utils.paths.add_output_root`: writes that resolve outside every
    root are refused until the command ends); only from code that runs inside a CLI command
    (:func:`gsavatar.utils.cli.run_reporting_errors` clears the roots), never from library functions
    that scripts call directly, and not for commands that also write elsewhere (``synth``: the anny cache).

    Raises SchemaError(path, "", ...) for a non-empty foreign folder (unless ``force``) and for another
    kind of gsavatar output (always); FileExistsError/NotADirectoryError when a file is in the way.
    """
    d = Path(path)
    if kind not in LEGACY:
        raise ValueError(f"kind must be one of {sorted(LEGACY)}, got {kind!r}")
    if d.is_dir() and _entries(d):
        found = output_kind(d)
        if found is not None and found != kind:
            raise SchemaError(
                d,
                "",
                f"holds a gsavatar {found} output, not a {kind}: choose another folder "
                f"(two outputs in one folder would overwrite each other)",
            )
        if found is None and not force:
            raise SchemaError(
                d,
                "",
                f"not empty and not a gsavatar {kind} output; choose an empty or new folder, "
                f"or pass {force_flag} to write into it anyway",
            )
    d.mkdir(parents=True, exist_ok=True)  # a file in the way: FileExistsError / NotADirectoryError (exit 2)
    if register:
        add_output_root(d)
    marker = d / MARKER
    if not marker.exists():
        atomic_write_json(marker, {"format": MARKER_FORMAT, "kind": kind})
    return d


# --------------------------------------------------------------------------- single-file outputs
FileKind = Literal["ply", "video", "figure"]
FILE_SUFFIXES: dict[str, tuple[str, ...]] = {"ply": (".ply",), "video": (".mp4",), "figure": (".png",)}
"""The extensions each kind of single-file output may have (the writer picks the format from it)."""
PLY_COMMENT = "comment gsavatar-output 3dgs"
"""Header line of every PLY gsavatar writes: how an existing .ply is recognised as ours."""
FILE_RECORD_FORMAT = "gsavatar-output-file"


def file_record_path(path: str | Path) -> Path:
    """The sidecar record of a single-file output (hidden, beside it): ``DIR/.NAME.gsavatar.json``."""
    p = Path(path)
    return p.with_name(f".{p.name}.gsavatar.json")


def _ply_is_ours(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    end = head.find(b"end_header")
    return head.startswith(b"ply\n") and end > 0 and PLY_COMMENT.encode() in head[:end].split(b"\n")


def is_our_file(path: str | Path, kind: FileKind) -> bool:
    """Whether ``path`` is a single-file gsavatar output of ``kind`` that nobody has replaced since.

    PLY: the header line :data:`PLY_COMMENT`. Other kinds: the sidecar record (:func:`record_output_file`) names
    the kind and the file's current SHA-256, so a user's file saved over ours is not taken for ours.
    """
    p = Path(path)
    if not p.is_file():
        return False
    if kind == "ply" and _ply_is_ours(p):
        return True
    rec = _json_dict(file_record_path(p)) or {}
    if rec.get("format") != FILE_RECORD_FORMAT or rec.get("kind") != kind:
        return False
    return rec.get("sha256") == sha256_file(p)


def claim_output_file(
    path: str | Path,
    kind: FileKind,
    force: bool = False,
    force_flag: str = "--force",
    companions: tuple[str | Path, ...] = (),
) -> Path:
    """Check that a command may write its single-file output ``path`` of ``kind``; returns it. Writes nothing.

    The extension must fit the kind (:data:`FILE_SUFFIXES`). An existing path must be a regular file that is a
    gsavatar output of this kind (:func:`is_our_file`: it is replaced, as a re-run would), or ``force`` must be
    set. ``companions``: files written with it (a JSON of its numbers); an existing one is replaced only when
    ``path`` is ours or ``force`` is set. Raises SchemaError(path, "", ...) naming the file and the flag;
    IsADirectoryError for a folder.
    The writer's temporary file lives beside the target (:func:`gsavatar.utils.io.atomic_path`).
    """
    p = Path(path)
    if kind not in FILE_SUFFIXES:
        raise ValueError(f"kind must be one of {sorted(FILE_SUFFIXES)}, got {kind!r}")
    if p.suffix.lower() not in FILE_SUFFIXES[kind]:
        raise SchemaError(
            p, "", f"a {kind} output must end in {' or '.join(FILE_SUFFIXES[kind])}, got {p.suffix or 'no extension'!r}"
        )
    if p.is_dir():
        raise IsADirectoryError(f"{p}: is a directory; name the {kind} file to write")
    ours = False
    if p.exists() or p.is_symlink():
        if not p.is_file() or p.is_symlink():
            raise SchemaError(p, "", "exists and is not a regular file (a link, FIFO or device); choose another name")
        ours = is_our_file(p, kind)  # hashes the file once
        if not force and not ours:
            raise SchemaError(
                p,
                "",
                f"exists and is not a gsavatar {kind} output; choose another name, or pass {force_flag} to replace it",
            )
    for c in map(Path, companions):
        if c.is_symlink() or c.is_dir() or (c.exists() and not (force or ours)):
            raise SchemaError(
                c,
                "",
                f"exists and was not written with {p.name} by gsavatar; choose another name for "
                f"{p.name}, or pass {force_flag} to replace both",
            )
    return p


def record_output_file(path: str | Path, kind: FileKind) -> None:
    """Write the sidecar record of a finished single-file output (its kind and SHA-256), atomically."""
    p = Path(path)
    if kind != "ply":  # a PLY carries its mark in its header
        atomic_write_json(file_record_path(p), {"format": FILE_RECORD_FORMAT, "kind": kind, "sha256": sha256_file(p)})
