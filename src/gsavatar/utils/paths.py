"""Names from input files that become file names, and output paths that must stay in the output folder.

Two defences, both needed:

1. :func:`check_name` at the schema boundary: camera, joint, pose-parameter and split names come
   from user files (calibration.json, rig.json, splits.json) and end up in file names
   (``frames/{cam}/...``, ``eval_{frame}_{cam}.png``, ``influence_{param}.png``). They must be
   plain names: letters, digits and ``_ . - + :``, not starting with ``.`` or ``-``, at most
   :data:`MAX_NAME` characters.
2. :func:`output_path` for every writer that builds a path from parts, and the output roots of the
   running command (:func:`add_output_root`, called when a CLI claims its ``--out``; or the
   :func:`output_roots` context): while one is registered, every atomic write
   (:func:`gsavatar.utils.io.atomic_path`) checks that its resolved target, symlinks followed, lies
   inside one of the roots. A path that escapes is refused before anything is written.
"""

from __future__ import annotations

import contextlib
import re
import stat
from collections.abc import Iterator
from pathlib import Path

from gsavatar.utils.errors import SchemaError

MAX_NAME = 128
"""Longest name accepted (camera, joint, parameter, split)."""
_NAME = re.compile(r"[A-Za-z0-9_+:][A-Za-z0-9_.+:-]*")

_ROOTS: list[Path] = []
"""Output roots of the running command (resolved); empty = no check (library use)."""


def check_name(name, file: str | Path, fld: str, what: str = "name") -> str:
    """``name`` if it is a safe file-name component; else SchemaError naming ``file`` and ``fld``."""
    if not isinstance(name, str):
        raise SchemaError(file, fld, f"{what} must be a string, got {type(name).__name__} {name!r}")
    if not name or len(name) > MAX_NAME or not _NAME.fullmatch(name):
        shown = name if len(name) <= 80 else name[:77] + "..."
        raise SchemaError(
            file,
            fld,
            f"{what} {shown!r} is not a plain name (letters, digits and _ . - + : only, "
            f"not starting with . or -, 1-{MAX_NAME} characters): it becomes part of file names",
        )
    return name


def is_inside(path: str | Path, root: str | Path) -> bool:
    """Whether ``path`` (symlinks and ``..`` resolved, need not exist) lies in ``root``."""
    return Path(path).resolve().is_relative_to(Path(root).resolve())


def output_path(root: str | Path, *parts: str) -> Path:
    """``root / parts...``, refused (SchemaError) if the result resolves outside ``root``."""
    root = Path(root)
    p = root.joinpath(*parts)
    if any(Path(x).is_absolute() for x in parts) or not is_inside(p, root):
        raise SchemaError(p, "", f"would be written outside the output folder {root}")
    return p


@contextlib.contextmanager
def output_roots(*roots: str | Path) -> Iterator[None]:
    """While active, :func:`check_output` refuses writes outside ``roots`` (nestable)."""
    added = [Path(r).resolve() for r in roots]
    _ROOTS.extend(added)
    try:
        yield
    finally:
        for r in added:
            _ROOTS.remove(r)


def add_output_root(root: str | Path) -> None:
    """Register ``root`` for the rest of the command (:func:`gsavatar.utils.cli.run_reporting_errors`
    clears the registry when the command ends)."""
    _ROOTS.append(Path(root).resolve())


def clear_output_roots() -> None:
    _ROOTS.clear()


def check_output(path: str | Path) -> None:
    """Raise SchemaError if output roots are active and ``path`` resolves outside all of them."""
    if _ROOTS and not any(Path(path).resolve().is_relative_to(r) for r in _ROOTS):
        raise SchemaError(path, "", f"would be written outside the output folder ({', '.join(map(str, _ROOTS))})")


def check_regular_file(path: str | Path, what: str = "file", max_bytes: int | None = None) -> Path:
    """``path`` if it names a regular file (of at most ``max_bytes``). SchemaError naming it when it is missing,
    is a FIFO, device, socket or directory (opening a FIFO blocks forever: cv2.imread, OpenImageIO, np.load
    would hang), or is too large to be what it claims."""
    path = Path(path)
    try:
        st = path.stat()
    except FileNotFoundError:
        raise SchemaError(path, "", f"{what} not found") from None
    if not stat.S_ISREG(st.st_mode):
        raise SchemaError(path, "", "not a regular file" + ("" if what == "file" else f" ({what} expected)"))
    if max_bytes is not None and st.st_size > max_bytes:
        raise SchemaError(path, "", f"{st.st_size} bytes, more than the {max_bytes} a {what} may have here")
    return path
