"""`--strict` on a driver that flushes subnormal floats to zero.

A strict run is bit-exact with NumPy float32 wherever the arithmetic keeps subnormal values,
as IEEE 754 and NumPy do. A driver that flushes them to zero (llvmpipe's fragment shaders)
cannot be told not to, so once a value of a run falls below float32's smallest normal
(1.2e-38) strict cannot hold there (docs/semantics.md, "Subnormal floats"). Such a backend
says so (`flushes_subnormals`); on it, a timed strict run steps a NumPy float32 run beside
it, compares the bits after every chunk (outside the timed region) and names the first step
where the two part, then compares no more.

The twin run is the `c` backend's strict float32 where it gives NumPy's bits
(simulate.with_numpy_bits: the same operations in the same order, subnormals kept), else
NumPy's own: at 2048^2 NumPy takes 0.6 s a step and `c` 12 ms (AMD EPYC Zen 4, 2 cores); the
default sweep's four strict llvmpipe and Taichi rows at 1024^2 and 2048^2 took 540 s with the
NumPy twin and 104 s with c's (docs/timing.md).
"""

from __future__ import annotations

import numpy as np

from clothbench.backends import create_backend
from clothbench.harness.simulate import with_numpy_bits

AXES = "xyzw"
STATE = ("pos", "prev")


def needs_watch(backend) -> bool:
    """A strict run on a backend whose driver flushes subnormals."""
    return backend.options.strict and backend.flushes_subnormals


def twin(scene, solver):
    """A backend whose strict float32 run of `scene` is NumPy float32's, bit for bit: `c` where
    it gives NumPy's bits (and builds here), else NumPy."""
    return with_numpy_bits(scene, solver, "f32", lambda name, options: create_backend(name, scene, solver, options))


def _bits(state) -> tuple[np.ndarray, ...]:
    return tuple(np.ascontiguousarray(a, dtype=np.float32).view(np.uint32) for a in state)


def _same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(_bits(a), _bits(b)))


class StrictWatch:
    """A NumPy float32 run in lockstep with a strict `backend` started from (pos, prev)."""

    def __init__(self, backend, pos: np.ndarray, prev: np.ndarray):
        self.backend = backend
        self.shadow = twin(backend.scene, backend.solver)
        self.shadow.upload(pos, prev)
        self.start = (pos, prev)  # the state both runs held when the current chunk began
        self.parted = False

    def check(self, done: int, chunk: int, pos: np.ndarray, prev: np.ndarray) -> str | None:
        """After the backend advanced `chunk` steps from step `done` to (pos, prev): one line
        naming the first step where the runs part, in the chunk where they do; else None
        (and always None after that chunk: there is nothing more to compare)."""
        if self.parted:
            return None
        self.shadow.advance(chunk)
        expected = self.shadow.read()
        if _same((pos, prev), expected):
            self.start = (pos, prev)
            return None
        self.parted = True
        return self._pinpoint(done, chunk) or _describe(done + chunk, (pos, prev), expected, self.backend)

    def _pinpoint(self, done: int, chunk: int) -> str | None:
        """Replay the chunk one step at a time on both runs; the backend ends where it was."""
        backend, shadow = self.backend, self.shadow
        backend.upload(*self.start)
        shadow.upload(*self.start)
        for s in range(1, chunk + 1):
            backend.advance(1)
            shadow.advance(1)
            got, expected = backend.read(), shadow.read()
            if not _same(got, expected):
                backend.advance(chunk - s)
                return _describe(done + s, got, expected, backend)
        return None  # not reproduced step by step: the caller names the chunk's end

    def close(self) -> None:
        self.shadow.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _describe(step: int, got, expected, backend) -> str:
    """The first value where two different states differ, and why."""
    g, e = np.stack(_bits(got)), np.stack(_bits(expected))
    which, i, axis = np.argwhere(g != e)[0]
    have, want = (a.view(np.float32)[which, i, axis] for a in (g, e))
    return (
        f"--strict parts from NumPy float32 at step {step}: particle {i} {STATE[which]}.{AXES[axis]} "
        f"is {have!s}, NumPy's {want!s}; {backend.name} on {backend.device} flushes subnormal floats "
        "to zero, NumPy keeps them"
    )
