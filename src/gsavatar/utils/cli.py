"""Shared behaviour of the command-line tools: one line per failure, never a traceback.

Exit codes: 0 success, 2 bad input (a file or option the user can fix; the message names it),
1 the environment failed (disk full), 130 interrupted (Ctrl-C). In every case the files already
written stay intact (atomic writes), and a resumable command says how to resume.
"""

from __future__ import annotations

import errno
import os
import shutil
import sys
from collections.abc import Callable

from gsavatar.utils.io import NO_SPACE_ERRNOS
from gsavatar.utils.paths import clear_output_roots

PATH_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)
"""OS errors that mean a bad path on the command line (or in a file it names), not a bug."""

EXIT_BAD_INPUT, EXIT_FAULT, EXIT_INTERRUPTED = 2, 1, 130

_RESUME_HINT: list[str | Callable[[], str]] = []
"""What the running command says about resuming after a fault or Ctrl-C (set by resumable commands)."""


def set_resume_hint(text: str | Callable[[], str]) -> None:
    """Replace the running command's resume hint, e.g. ``"re-run the same command to resume from step 400"``, or a
    function that words it when it is needed (while a checkpoint is being written, whether it exists yet is only
    known then)."""
    _RESUME_HINT[:] = [text]


def describe_path_error(e: OSError) -> str:
    """``<path>: <reason>`` for an OS error about a path; a file where a directory belongs gets a hint."""
    if e.filename is None:
        return str(e)
    where = f"{e.filename} -> {e.filename2}" if e.filename2 else str(e.filename)
    msg = f"{where}: {(e.strerror or type(e).__name__).lower()}"
    if isinstance(e, NotADirectoryError) or (isinstance(e, FileExistsError) and not os.path.isdir(e.filename)):
        msg += " (a directory is needed there, but a file is in the way)"
    return msg


def describe_no_space(e: OSError) -> str:
    """``no space left on <path> (<free> MiB free there)`` for ENOSPC / EDQUOT / EFBIG."""
    path = str(e.filename) if e.filename else "the output device"
    free = ""
    if e.filename:
        d = os.path.dirname(os.path.abspath(path))
        while d and not os.path.isdir(d):
            d = os.path.dirname(d)
        try:
            free = f" ({shutil.disk_usage(d).free / 2**20:.0f} MiB free there)"
        except OSError:
            pass
    what = {errno.EFBIG: "file size limit reached", errno.EDQUOT: "disk quota exceeded"}.get(e.errno, "no space left")
    return f"{what} on {path}{free}"


def _hint() -> str:
    if not _RESUME_HINT:
        return ""
    h = _RESUME_HINT[0]
    return f"; {h() if callable(h) else h}"


def run_reporting_errors(fn: Callable[[], object]) -> int:
    """Run ``fn`` and turn failures into one line on stderr and an exit code (module docstring).

    Bad input (SchemaError/ValueError, missing or existing files, a file where a directory belongs):
    ``error: <file>: <field>: <message>``, exit 2. Disk full: ``error: no space left on <path>``, exit 1.
    Ctrl-C: ``interrupted``, exit 130. The output-root registry of :mod:`gsavatar.utils.paths` and the
    resume hint are reset before and after, so one command never inherits another's.
    """
    clear_output_roots()
    _RESUME_HINT.clear()
    try:
        fn()
    except KeyboardInterrupt:
        print(f"\ninterrupted: nothing half-written was left behind{_hint()}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except PATH_ERRORS as e:
        print(f"error: {describe_path_error(e)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as e:
        if e.errno not in NO_SPACE_ERRNOS:
            raise
        print(f"error: {describe_no_space(e)}: finished outputs are intact{_hint()}", file=sys.stderr)
        return EXIT_FAULT
    except ValueError as e:  # SchemaError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    finally:
        clear_output_roots()
        _RESUME_HINT.clear()
    return 0


def parse_args(parse: Callable[[], object], exit_codes: bool = False) -> object | int:
    """``parse()`` (a ``tyro.cli`` call), or 2 with ``error: ...`` on stderr when a nested config refuses a value
    (its ``__post_init__``; tyro reports only the top-level class's checks itself), e.g.
    ``--model.init-opacity 2``. ``exit_codes``: tyro's own exits (``--help``, parse errors) are returned as
    codes too instead of raising SystemExit."""
    try:
        return parse()
    except SystemExit as e:
        if not exit_codes:
            raise
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
    except (ValueError, TypeError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
