"""A test-only fault switch: CLOTHBENCH_FAULT="BACKEND:KIND[,BACKEND:KIND...]" makes the named
backend's rows fail the way real drivers do, inside the worker process that runs them:
abort (SIGABRT), segv (SIGSEGV), kill (SIGKILL, as the out-of-memory killer sends), hang
(sleeps for ever), memory (raises MemoryError), slow (sleeps 2 s, then runs as usual). Nothing happens unless the variable is set.

So that a test can act at a known moment instead of after a guessed sleep, CLOTHBENCH_FAULT_READY
names a file to which each armed row appends one line ("BACKEND PID") as it starts, before any
fault; CLOTHBENCH_FAULT_AFTER=N then spares the first N rows so marked (they run as usual) and
applies the fault from the next one on: "the second row is running" is then a line count.
"""

from __future__ import annotations

import os
import signal
import time

FAULT_ENV = "CLOTHBENCH_FAULT"
READY_ENV = "CLOTHBENCH_FAULT_READY"
AFTER_ENV = "CLOTHBENCH_FAULT_AFTER"
KINDS = ("abort", "segv", "kill", "hang", "memory", "slow")
SLOW_S = 2.0
_armed = False  # only inside a worker process: a fault never takes the parent down


def arm() -> None:
    global _armed
    _armed = True


def faults() -> dict[str, str]:
    out = {}
    for part in os.environ.get(FAULT_ENV, "").split(","):
        name, _, kind = part.strip().partition(":")
        if name and kind in KINDS:
            out[name] = kind
    return out


def inject(backend: str) -> None:
    """Fail now, as $CLOTHBENCH_FAULT says for `backend` (in a worker process only)."""
    if not _armed:
        return
    kind = faults().get(backend)
    place = _mark_started(backend)  # 0: no READY file, nothing spared
    if place and place <= int(os.environ.get(AFTER_ENV, "0") or 0):
        return
    if kind == "abort":
        os.abort()
    elif kind == "segv":
        os.kill(os.getpid(), signal.SIGSEGV)
    elif kind == "kill":
        os.kill(os.getpid(), signal.SIGKILL)
    elif kind == "hang":
        while True:
            time.sleep(60)
    elif kind == "slow":
        time.sleep(SLOW_S)
    elif kind == "memory":
        raise MemoryError(f"{FAULT_ENV}: {backend} out of memory")


def _mark_started(backend: str) -> int:
    """Append this row's start to $CLOTHBENCH_FAULT_READY and return its place in the file, from 1
    (0 where the variable is unset). One short O_APPEND write: rows in parallel workers do not tear it."""
    path = os.environ.get(READY_ENV)
    if not path:
        return 0
    line = f"{backend} {os.getpid()}"
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, f"{line}\n".encode())
    finally:
        os.close(fd)
    with open(path) as f:
        return f.read().splitlines().index(line) + 1
