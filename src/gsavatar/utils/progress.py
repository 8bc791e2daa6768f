"""Rich progress bars that stay quiet when output is not a terminal (CI logs)."""

from __future__ import annotations

import contextlib
import sys
import time
from collections.abc import Iterator


class _Bar:
    def __init__(self, progress, task) -> None:
        self._p, self._t = progress, task

    def advance(self, n: float = 1) -> None:
        if self._p is not None:
            self._p.advance(self._t, n)


@contextlib.contextmanager
def progress_bar(description: str, total: float | None) -> Iterator[_Bar]:
    """A rich progress bar on a TTY; a single start/finish line otherwise."""
    if sys.stderr.isatty():
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            transient=False,
        ) as p:
            yield _Bar(p, p.add_task(description, total=total))
    else:
        t0 = time.perf_counter()
        yield _Bar(None, None)
        print(f"{description}: done in {time.perf_counter() - t0:.1f}s", file=sys.stderr)
