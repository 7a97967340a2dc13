"""A progress bar that appears only on a terminal and only once work takes a moment."""

from __future__ import annotations

import sys
import time

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

SHOW_AFTER_S = 0.5


class LazyProgress:
    """Counts work done; draws a rich bar on stderr once the work has run SHOW_AFTER_S."""

    def __init__(self, total: int, description: str, enabled: bool | None = None):
        self.total = total
        self.description = description
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self.started = time.perf_counter()
        self._progress: Progress | None = None
        self._task = None

    def update(self, done: int, description: str | None = None) -> None:
        if description:
            self.description = description
        if not self.enabled:
            return
        if self._progress is None:
            if time.perf_counter() - self.started < SHOW_AFTER_S:
                return
            self._progress = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
            )
            self._progress.start()
            self._task = self._progress.add_task(self.description, total=self.total)
        self._progress.update(self._task, completed=done, description=self.description)

    def close(self) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
