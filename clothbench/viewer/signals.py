"""Ctrl-C and SIGTERM in the viewer, and the X server that goes with them.

A terminal's Ctrl-C reaches every process of its foreground group, and under `xvfb-run` the
X server is one of them (xvfb-run starts Xvfb in the background of a shell without job
control, so it stays in the group): Xvfb exits at once, the viewer's next X request finds the
connection closed, and Xlib calls its IO error handler from inside that request. The default
handler prints `XIO: fatal IO error ...` with X's request counts and calls exit(1). Hence:

- a signal only records itself, and the frame loop stops between frames (`raise_if_stopped`).
  Python's own SIGINT handler raises KeyboardInterrupt wherever the main thread is, Xlib's
  callback included, where ctypes prints the exception and drops it;
- the IO error handler is this module's (`on_lost_display`): after a signal it says what the
  CLI says for one and exits 130; without one it says that the display went, and exits 1.

Xlib's IO error handler is process-wide and outlives the window (pyglet's display is closed at
exit), so what it reads, the signal that came, is kept here for the process.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
from contextlib import contextmanager

from clothbench.errors import INTERRUPTED_EXIT, INTERRUPTED_LINE

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)  # SIGTERM as a Ctrl-C, as every command takes it

_received: list[int] = []  # the signals that came while the viewer ran
_handler = None  # the installed XIOErrorHandler: ctypes calls it only while it is referenced


def _record(signum, frame) -> None:
    _received.append(signum)


def raise_if_stopped() -> None:
    """A recorded Ctrl-C or SIGTERM as the KeyboardInterrupt the CLI exits 130 for."""
    if _received:
        raise KeyboardInterrupt


@contextmanager
def stop_between_frames():
    """Ctrl-C and SIGTERM recorded, not raised, while the viewer runs; the handlers it had after."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signals are the main thread's: a viewer elsewhere has none to take
        return
    _received.clear()
    saved = {sig: signal.signal(sig, _record) for sig in STOP_SIGNALS}
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)


def _lost_display(display) -> int:
    try:
        ctypes.pythonapi.PyErr_CheckSignals()  # a signal whose Python handler has not run yet: recorded now
    except KeyboardInterrupt:  # one after stop_between_frames gave the handlers back
        _received.append(signal.SIGINT)
    if _received:
        print(INTERRUPTED_LINE, file=sys.stderr)
        code = INTERRUPTED_EXIT
    else:
        where = os.environ.get("DISPLAY", "")
        print(f"clothbench: error: lost the display {where}: its X server closed the connection", file=sys.stderr)
        code = 1
    sys.stderr.flush()
    sys.stdout.flush()
    os._exit(code)  # Xlib calls exit(1) if this returns: the connection cannot be used again


def on_lost_display() -> None:
    """This module's handler as Xlib's IO error handler (for a window on an X display)."""
    global _handler
    if _handler is None:
        from pyglet.libs.x11 import xlib

        _handler = xlib.XIOErrorHandler(_lost_display)
        xlib.XSetIOErrorHandler(_handler)
