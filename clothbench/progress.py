"""What a command is busy with, on a terminal only, once it takes a moment: a progress bar for
counted work (LazyProgress) and a spinner naming a wait that cannot be counted (`waiting`: a
backend's probe, its JIT compile, a tuning's measurement, a report's figures).

Nothing is drawn where stderr is not a terminal (piped, redirected, CI): the output is then
what it would be without either. Nor in a worker process: a sweep's rows run in children that
share the parent's terminal, where the sweep's bar is already drawn. One display is on the
terminal at a time: a wait met while a bar is drawn is said in the bar's description, and a
bar does not start drawing during a wait.

Layer 0 (tests/test_layout.py): the commands, the harness and a backend's tuning all draw it.
"""

from __future__ import annotations

import multiprocessing
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterator

from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

SHOW_AFTER_S = 0.5  # a bar or a wait is drawn once it has run this long: a quick one never flickers


def on_terminal() -> bool:
    """Whether this process may draw: stderr is a terminal and this is not a worker process."""
    return sys.stderr.isatty() and multiprocessing.parent_process() is None


class LazyProgress:
    """Counts work done; draws a rich bar on stderr once the work has run SHOW_AFTER_S."""

    def __init__(self, total: int, description: str, enabled: bool | None = None):
        self.total = total
        self.description = description
        self.enabled = on_terminal() if enabled is None else enabled
        self.started = time.perf_counter()
        self._progress: Progress | None = None
        self._task = None

    def update(self, done: int, description: str | None = None) -> None:
        global _bar
        if description:
            self.description = description
        if not self.enabled:
            return
        if self._progress is None:
            if time.perf_counter() - self.started < SHOW_AFTER_S or _waits.pending():
                return
            self._progress = Progress(
                TextColumn("{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                transient=True,
                auto_refresh=False,  # drawn at each update (between timed chunks), never by a thread meanwhile
            )
            self._progress.start()
            self._task = self._progress.add_task(escape(self.description), total=self.total)
            _bar = self
        self._progress.update(self._task, completed=done, description=escape(self.description), refresh=True)

    def say(self, description: str) -> None:
        """Show `description` in place of the bar's own until the next update (a wait meanwhile)."""
        if self._progress is not None:
            self._progress.update(self._task, description=escape(description))
            self._progress.refresh()

    def close(self) -> None:
        global _bar
        if self._progress is not None:
            self._progress.stop()
            self._progress = None
        if _bar is self:
            _bar = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_bar: LazyProgress | None = None  # the bar drawn on the terminal now, if any


@contextmanager
def waiting(what: str, timed: bool = False) -> Iterator[Callable[[str], None]]:
    """Say on the terminal that `what` is being waited for (`probing backends`, `warming up
    torch`), with a spinner and the time so far, from SHOW_AFTER_S into the wait to its end;
    the line is cleared afterwards. A wait inside another says itself in the outer one's place
    until it ends. Yields `say(text)`, which replaces the text and redraws it at once.

    The spinner redraws itself REDRAW_S apart from a thread, except while a `timed` wait is
    under way (a tuning's measurement): then it is drawn only by `say`, which the caller calls
    between the timed parts, so that nothing is drawn while a clock runs."""
    if not on_terminal():
        yield lambda text: None
        return
    bar = _bar
    if bar is not None:  # a bar is drawn (the sweep's): the wait is said in its description
        bar.say(f"{bar.description}: {what}")
        try:
            yield lambda text: bar.say(f"{bar.description}: {text}")
        finally:
            bar.say(bar.description)
        return
    level = _waits.push(what, timed)
    try:
        yield lambda text: _waits.say(level, text)
    finally:
        _waits.pop()


REDRAW_S = 0.1  # the spinner's frame, and how soon after SHOW_AFTER_S it appears


class _Waits:
    """The waits under way in this process, innermost last, and the one spinner saying the
    innermost: drawn once the outermost has run SHOW_AFTER_S, by the caller's thread at a
    wait's start, end or `say`, or by a redrawing thread while no timed wait is under way;
    cleared when the outermost ends."""

    def __init__(self):
        self._lock = threading.Lock()
        self._what: list[tuple[str, bool]] = []  # (text, timed)
        self._begun = 0.0
        self._stop: threading.Event | None = None
        self._redrawing: threading.Thread | None = None
        self._spinner: Progress | None = None
        self._task = None

    def pending(self) -> bool:
        return bool(self._what)

    def push(self, what: str, timed: bool) -> int:
        with self._lock:
            self._what.append((what, timed))
            if len(self._what) == 1:
                self._begun = time.monotonic()
                self._stop = threading.Event()
                self._redrawing = threading.Thread(target=self._redraw_until, args=(self._stop,), daemon=True)
                self._redrawing.start()
            self._draw()
            return len(self._what) - 1

    def say(self, level: int, text: str) -> None:
        with self._lock:
            if level < len(self._what):
                self._what[level] = (text, self._what[level][1])
                self._draw()

    def pop(self) -> None:
        redrawing = None
        with self._lock:
            self._what.pop()
            if self._what:
                self._draw()
                return
            self._stop.set()
            redrawing, self._redrawing = self._redrawing, None
            if self._spinner is not None:
                self._spinner.stop()
                self._spinner = None
        redrawing.join()  # outside the lock: the thread may be waiting for it, to see the stop

    def _redraw_until(self, stop: threading.Event) -> None:
        while not stop.wait(REDRAW_S):
            with self._lock:
                if not stop.is_set() and not any(timed for _, timed in self._what):
                    self._draw()

    def _draw(self) -> None:
        """Draw the innermost wait, where the outermost has run SHOW_AFTER_S (the lock held)."""
        text = escape(self._what[-1][0])
        if self._spinner is not None:
            self._spinner.update(self._task, description=text, refresh=True)
        elif time.monotonic() - self._begun >= SHOW_AFTER_S:
            self._spinner = Progress(
                SpinnerColumn(),
                TextColumn("{task.description}"),
                TimeElapsedColumn(),
                console=Console(stderr=True),
                transient=True,
                auto_refresh=False,  # redrawn by _redraw_until, which a timed wait pauses
            )
            self._task = self._spinner.add_task(text, total=None)
            self._spinner.start()


_waits = _Waits()
