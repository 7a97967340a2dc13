"""Errors meant for people: the CLI prints them as one line and exits with their code."""

import signal

# what a Ctrl-C (or a SIGTERM, taken as one) ends a command with
INTERRUPTED_LINE = "clothbench: interrupted"
INTERRUPTED_EXIT = 130


class ClothbenchError(Exception):
    """Bad input or an unusable backend: one line on stderr, exit code 2."""

    exit_code = 2


class SceneError(ClothbenchError):
    """A scene value or scene file that cannot be simulated."""


class BackendUnavailable(ClothbenchError):
    """A backend that cannot run on this machine; the message says why."""

    def __init__(self, backend: str, reason: str):
        super().__init__(f"{backend} unavailable: {reason}")
        self.backend = backend
        self.reason = reason


class BlowUp(ClothbenchError):
    """The simulation stopped being finite or ran away; exit code 3."""

    exit_code = 3

    def __init__(self, step: int, what: str):
        super().__init__(f"simulation blew up at step {step}: {what}")
        self.step = step
        self.what = what


def signal_name(number: int) -> str:
    """A signal's name (SIGABRT) for a message about a process that died of it."""
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"
