"""Shared behaviour of the command-line tools."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable

PATH_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)
"""OS errors that mean a bad path on the command line (or in a file it names), not a bug."""


def describe_path_error(e: OSError) -> str:
    """``<path>: <reason>`` for an OS error about a path; a file where a directory belongs gets a hint."""
    if e.filename is None:
        return str(e)
    where = f"{e.filename} -> {e.filename2}" if e.filename2 else str(e.filename)
    msg = f"{where}: {(e.strerror or type(e).__name__).lower()}"
    if isinstance(e, NotADirectoryError) or (isinstance(e, FileExistsError) and not os.path.isdir(e.filename)):
        msg += " (a directory is needed there, but a file is in the way)"
    return msg


def run_reporting_errors(fn: Callable[[], object]) -> int:
    """Run ``fn``; bad input (SchemaError/ValueError, missing or existing files, a file where a
    directory belongs) becomes ``error: <file>: <field>: <message>`` on stderr and exit code 2,
    never a traceback."""
    try:
        fn()
    except PATH_ERRORS as e:
        print(f"error: {describe_path_error(e)}", file=sys.stderr)
        return 2
    except ValueError as e:  # SchemaError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
