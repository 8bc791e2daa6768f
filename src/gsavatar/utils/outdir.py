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
from gsavatar.utils.io import atomic_write_json
from gsavatar.utils.jsonio import read_json
from gsavatar.utils.paths import add_output_root

OutputKind = Literal["capture", "dataset", "run", "predictor", "drive", "report"]
MARKER = "gsavatar-output.json"
MARKER_FORMAT = "gsavatar-output"
_DRIVE_FRAME = re.compile(r"\d{6}\.png")


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
            raise SchemaError(marker, "kind", f"not a gsavatar output marker (expected format {MARKER_FORMAT!r} "
                                              f"and a kind of {sorted(LEGACY)})")
        return obj["kind"]
    for kind, is_kind in LEGACY.items():
        if is_kind(d):
            return kind
    return None


def claim_output_dir(path: str | Path, kind: OutputKind, force: bool = False, force_flag: str = "--force",
                     register: bool = False) -> Path:
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
    if d.is_dir() and any(d.iterdir()):
        found = output_kind(d)
        if found is not None and found != kind:
            raise SchemaError(d, "", f"holds a gsavatar {found} output, not a {kind}: choose another folder "
                                     f"(two outputs in one folder would overwrite each other)")
        if found is None and not force:
            raise SchemaError(d, "", f"not empty and not a gsavatar {kind} output; choose an empty or new folder, "
                                     f"or pass {force_flag} to write into it anyway")
    d.mkdir(parents=True, exist_ok=True)  # a file in the way: FileExistsError / NotADirectoryError (exit 2)
    if register:
        add_output_root(d)
    marker = d / MARKER
    if not marker.exists():
        atomic_write_json(marker, {"format": MARKER_FORMAT, "kind": kind})
    return d
