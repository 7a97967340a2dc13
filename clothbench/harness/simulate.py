"""Untimed runs: the state after some steps, for comparisons and error measurements."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from clothbench.backends import BackendOptions, create_backend
from clothbench.scene import Scene
from clothbench.solver import Solver


def simulate(
    backend: str, scene: Scene, solver: Solver, steps: int, options: BackendOptions | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(pos, prev) after `steps` steps of `scene` stepped by `solver` from its start on `backend`."""
    options = options or BackendOptions()
    with create_backend(backend, scene, solver, options) as b:
        b.upload(*b.initial_state())
        b.advance(steps)
        return b.read()


@lru_cache(maxsize=32)
def reference(scene: Scene, solver: Solver, steps: int, precision: str = "f64") -> tuple[np.ndarray, np.ndarray]:
    """The NumPy reference state, cached: many comparisons share one reference run."""
    pos, prev = simulate("numpy", scene, solver, steps, BackendOptions(precision=precision))
    pos.setflags(write=False)
    prev.setflags(write=False)
    return pos, prev


def position_error(pos: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(RMS, max) of the per-particle position distance to the reference, in metres."""
    d = np.sqrt(((pos[:, :3].astype(np.float64) - ref[:, :3].astype(np.float64)) ** 2).sum(axis=1))
    return float(np.sqrt((d * d).mean())), float(d.max())
