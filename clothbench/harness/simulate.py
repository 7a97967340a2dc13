"""Untimed runs: the state after some steps, for comparisons and error measurements."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..backends import BackendOptions, create_backend
from ..scene import Scene


def simulate(
    backend: str, scene: Scene, steps: int, options: BackendOptions | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(pos, prev) after `steps` steps of `scene` from its initial state on `backend`."""
    options = options or BackendOptions()
    with create_backend(backend, scene, options) as b:
        b.upload(*scene.initial_state(options.dtype))
        b.advance(steps)
        return b.read()


@lru_cache(maxsize=32)
def reference(scene: Scene, steps: int, precision: str = "f64") -> tuple[np.ndarray, np.ndarray]:
    """The NumPy reference state, cached: many comparisons share one reference run."""
    pos, prev = simulate("numpy", scene, steps, BackendOptions(precision=precision))
    pos.setflags(write=False)
    prev.setflags(write=False)
    return pos, prev


def position_error(pos: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(RMS, max) of the per-particle position distance to the reference, in metres."""
    d = np.sqrt(((pos[:, :3].astype(np.float64) - ref[:, :3].astype(np.float64)) ** 2).sum(axis=1))
    return float(np.sqrt((d * d).mean())), float(d.max())
