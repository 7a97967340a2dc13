"""`view --from FILE.usd`: an exported run played back in the window. Not a backend: a source
of frames that answers what the session asks of one (advance, read, read_normals, upload for a
reset), stepping through the file's frames instead of simulating."""

from __future__ import annotations

import bisect

import numpy as np


class Playback:
    """The frames of an exported USD (reports/export.py's Exported), shown as the session's
    step passes each one's step; the last stays once passed, and R plays it again."""

    name = "usd"  # what the overlay and the log call the source

    def __init__(self, exported):
        self.exported = exported
        info = exported.info
        self.mode = f"playback of {exported.frames} frames, every {info.every} steps"
        self.device = f"{exported.path.name}: {info.backend} {info.mode}"
        self.steps = [exported.step(f) for f in range(exported.frames)]
        self.step = 0
        start, _ = exported.scene.initial_state(np.float32)
        self._w = start[:, 3:]  # the inverse masses, beside the file's points as a state has them

    @property
    def frame(self) -> int:
        """The last frame whose step has been reached."""
        return bisect.bisect_right(self.steps, self.step) - 1

    @property
    def time(self) -> float:
        """Seconds simulated at the frame shown: where its colliders are."""
        return self.exported.time(self.frame)

    def initial_state(self) -> tuple[np.ndarray, np.ndarray]:
        state = np.hstack([self.exported.points[0], self._w])
        return state, state

    def upload(self, pos, prev) -> None:  # the session uploads only to start again (R)
        self.step = 0

    def advance(self, steps: int) -> None:
        self.step += steps

    def synchronize(self) -> None:
        pass

    def device_elapsed_ms(self) -> None:
        return None

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        state = np.hstack([self.exported.points[self.frame], self._w])
        return state, state

    def read_normals(self) -> np.ndarray:
        return self.exported.normals[self.frame]

    def close(self) -> None:
        pass
