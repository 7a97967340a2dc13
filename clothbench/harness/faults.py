"""A test-only fault switch: CLOTHBENCH_FAULT="BACKEND:KIND[,BACKEND:KIND...]" makes the named
backend's rows fail the way real drivers do, inside the worker process that runs them:
abort (SIGABRT), segv (SIGSEGV), kill (SIGKILL, as the out-of-memory killer sends), hang
(sleeps for ever), memory (raises MemoryError), slow (sleeps 2 s, then runs as usual). Nothing happens unless the variable is set.
"""

from __future__ import annotations

import os
import signal
import time

FAULT_ENV = "CLOTHBENCH_FAULT"
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
