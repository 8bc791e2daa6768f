"""Shared behaviour of the command-line tools."""

from __future__ import annotations

import sys
from collections.abc import Callable


def run_reporting_errors(fn: Callable[[], object]) -> int:
    """Run ``fn``; bad input (SchemaError/ValueError, missing or existing files) becomes
    ``error: <file>: <field>: <message>`` on stderr and exit code 2, never a traceback."""
    try:
        fn()
    except (ValueError, FileNotFoundError, FileExistsError) as e:  # SchemaError is a ValueError
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0
