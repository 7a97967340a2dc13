"""Untimed runs: the state after some steps, for comparisons and error measurements."""

from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

from clothbench.backends import BackendOptions, availability, backend_class, check_name, create_backend
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver

# the solvers whose c strict float64 is NumPy float64 bit for bit (PBD has no c class)
C_REFERENCE_SOLVERS = ("verlet", "vbd")


def simulate(
    backend: str, scene: Scene, solver: Solver, steps: int, options: BackendOptions | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(pos, prev) after `steps` steps of `scene` stepped by `solver` from its start on `backend`."""
    found = []
    _states(backend, scene, solver, [steps], options or BackendOptions(), lambda _, *state: found.append(state))
    return found[0]


@lru_cache(maxsize=32)
def reference(scene: Scene, solver: Solver, steps: int, precision: str = "f64") -> tuple[np.ndarray, np.ndarray]:
    """The NumPy reference state, cached: many comparisons share one reference run.

    A float64 Verlet or VBD reference is stepped by the `c` backend in strict float64 where it
    takes the scene: the same operations in the same order, so NumPy float64's bits
    (tests/test_c_backend.py and tests/test_c_vbd.py hold it to that), at a fraction of NumPy's
    time (docs/c.md; NumPy's VBD is a Python loop over colours and sweeps). Float32 references
    stay NumPy's own: they are what every strict backend is compared against."""
    return reference_states(scene, solver, (steps,), precision)[steps]


def float64_state(scene: Scene, solver: Solver, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """reference()'s float64 (pos, prev) after `steps`, not cached: a converged reference's
    levels are each run once (and a 2048^2 state is 128 MiB)."""
    return reference_states(scene, solver, (steps,))[steps]


def float64_state_fork_safe(solver: Solver) -> bool:
    """Whether a forked child may run float64_state for `solver`: c may step it (its OpenMP is
    not fork-safe, by its registry entry), NumPy always is."""
    return solver.name not in C_REFERENCE_SOLVERS or check_name("c").fork_safe


def reference_states(
    scene: Scene, solver: Solver, counts, precision: str = "f64", on_state: Callable | None = None
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """reference()'s (pos, prev) after each of `counts` steps, from one run: the backend
    advances from one count to the next, which gives the bits of a separate run to each
    (tests/test_sweep_references.py holds it to that), for the cost of the largest alone. With
    `on_state`, each state goes to on_state(count, pos, prev) as it is reached instead, and
    none is kept (a 2048^2 float64 state is 128 MiB)."""
    counts = sorted(set(counts))
    keep: dict = {}
    if on_state is None:

        def on_state(count, pos, prev):
            pos.setflags(write=False)
            prev.setflags(write=False)
            keep[count] = (pos, prev)

    if precision == "f64" and c_gives_numpy_bits(scene, solver):
        try:
            _states("c", scene, solver, counts, BackendOptions(precision="f64", strict=True), on_state)
            return keep
        except ClothbenchError:  # a compiler that cannot build it: NumPy gives the same bits
            pass
    _states("numpy", scene, solver, counts, BackendOptions(precision=precision), on_state)
    return keep


def c_gives_numpy_bits(scene: Scene, solver: Solver) -> bool:
    """Whether the `c` backend's strict run of `scene` is NumPy's, bit for bit, in float32 and
    float64 (the contract and tests/test_c_backend.py, tests/test_c_vbd.py hold it to that), so
    that it may step a run whose bits are NumPy's at a fraction of NumPy's time: the float64
    references, the strict watch's float32 twin (strict_watch.py)."""
    return solver.name in C_REFERENCE_SOLVERS and availability("c").usable and c_takes(scene, solver)


def _states(backend: str, scene: Scene, solver: Solver, counts, options: BackendOptions, on_state) -> None:
    with create_backend(backend, scene, solver, options) as b:
        b.upload(*b.initial_state())
        done = 0
        for count in counts:
            b.advance(count - done)
            done = count
            pos, prev = b.read()
            on_state(count, pos.copy(), prev.copy())  # a backend may hand out views of its state


def c_takes(scene: Scene, solver: Solver) -> bool:
    """Whether the c backend's class for `solver` takes `scene` (not one it refuses, as a mesh today)."""
    name = solver.name
    return backend_class("c", name).capabilities.scene_refusal("c", scene, name) is None


def position_error(pos: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(RMS, max) of the per-particle position distance to the reference, in metres."""
    d = np.sqrt(((pos[:, :3].astype(np.float64) - ref[:, :3].astype(np.float64)) ** 2).sum(axis=1))
    return float(np.sqrt((d * d).mean())), float(d.max())
