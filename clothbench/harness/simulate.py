"""Untimed runs: the state after some steps, for comparisons and error measurements."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from clothbench.backends import BackendOptions, availability, backend_class, create_backend
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver


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
    """The NumPy reference state, cached: many comparisons share one reference run.

    A float64 Verlet reference is stepped by the `c` backend in strict float64 where it can
    run: the same operations in the same order, so NumPy float64's bits (tests/test_c_backend.py
    holds it to that), at a fraction of NumPy's time on large grids (docs/c.md). Float32
    references stay NumPy's own: they are what every strict backend is compared against."""
    if precision == "f64" and solver.name == "verlet" and availability("c").usable and c_takes(scene):
        try:
            pos, prev = simulate("c", scene, solver, steps, BackendOptions(precision="f64", strict=True))
        except ClothbenchError:  # a compiler that cannot build it: NumPy gives the same bits
            pos, prev = simulate("numpy", scene, solver, steps, BackendOptions(precision=precision))
    else:
        pos, prev = simulate("numpy", scene, solver, steps, BackendOptions(precision=precision))
    pos.setflags(write=False)
    prev.setflags(write=False)
    return pos, prev


def c_takes(scene: Scene) -> bool:
    """Whether the c backend's Verlet takes `scene` (not one it refuses, as [self_collision] today)."""
    return backend_class("c").capabilities.scene_refusal("c", scene) is None


def position_error(pos: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(RMS, max) of the per-particle position distance to the reference, in metres."""
    d = np.sqrt(((pos[:, :3].astype(np.float64) - ref[:, :3].astype(np.float64)) ** 2).sum(axis=1))
    return float(np.sqrt((d * d).mean())), float(d.max())
