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

    def run(name: str, options: BackendOptions) -> None:
        _states(name, scene, solver, counts, options, on_state)

    if precision == "f64":
        with_numpy_bits(scene, solver, precision, run)
    else:
        run("numpy", BackendOptions(precision=precision))
    return keep


def with_numpy_bits(scene: Scene, solver: Solver, precision: str, use: Callable):
    """use(name, options) with the backend whose strict run of `scene` in `precision` is
    NumPy's, bit for bit, at a fraction of NumPy's time: `c` where its class takes the scene and
    solver (the contract and tests/test_c_backend.py, tests/test_c_vbd.py hold its bits to
    NumPy's, float32 and float64) and it builds here, else NumPy itself. For the float64
    references and the strict watch's float32 twin (strict_watch.py)."""
    if solver.name in C_REFERENCE_SOLVERS and availability("c").usable and c_takes(scene, solver):
        try:
            return use("c", BackendOptions(precision=precision, strict=True))
        except ClothbenchError:  # a compiler that cannot build it: NumPy gives the same bits
            pass
    return use("numpy", BackendOptions(precision=precision))


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
