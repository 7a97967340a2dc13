"""The backend contract for [self_collision] (docs/semantics.md, "Self-collision"), over every
registry entry and every solver: a backend whose capabilities declare it for a solver runs a
folded sheet strict and matches the NumPy float32 reference bit for bit, with the pass seen to
act; one that does not declare it refuses the scene in one line before any work. CUDA, whose
registry entry runs only on a GPU, runs here through its CPU build as well (tests/test_cuda.py's
stand-in cupy)."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import backend_class, create_backend
from clothbench.errors import ClothbenchError
from clothbench.model import solver as solvers

from conftest import VERLET, assert_bit_exact
from folded_sheet import folded
from registry_variants import backend_params, options, usable
from test_cuda import cuda_on_cpu, shim_library  # noqa: F401  (fixtures: CudaBackend on its CPU build)

# every solver the model knows, each with its defaults at the Verlet contract's dt
SOLVERS = {name: solvers.solver_for_spec(name, VERLET) for name in solvers.SOLVERS}
# 1.5 spacings across a fold whose layers lie 0.5 apart: at the start every particle has one to
# nine pairs, seven most often (its partner across the fold and that partner's grid neighbours),
# so a sum taken in any order but ascending j shows in the bits; at the fold's own 0.8 each has
# one pair, and a reversed sum passes. Still a 16^2 sheet and at most 20 steps: every backend
# runs this.
THICKNESS = 1.5


def sheet():
    return folded(thickness=THICKNESS)


def run(name: str, scene, solver, pos, steps: int, **values) -> np.ndarray:
    with create_backend(name, scene, solver, options(name, solver.name, **values)) as b:
        b.upload(pos, pos)
        b.advance(steps)
        return b.read()[0]


def params() -> list:
    return [
        pytest.param(p.values[0], solver, id=f"{p.id}-{solver}") for solver in SOLVERS for p in backend_params(solver)
    ]


@pytest.mark.parametrize("steps", [1, 20])
@pytest.mark.parametrize("param, solver_name", params())
def test_strict_self_collision_matches_numpy_f32_bit_for_bit(param, solver_name, steps):
    name, _ = usable(param)
    solver = SOLVERS[solver_name]
    if solver_name not in backend_class(name, solver_name).capabilities.self_collision:
        pytest.skip(f"{name} {solver_name} does not declare self_collision")
    scene, pos = sheet()
    got = run(name, scene, solver, pos, steps, strict=True)
    assert_matches_numpy(got, scene, solver, pos, steps, f"{name} {solver_name}")


def assert_matches_numpy(got, scene, solver, pos, steps: int, what: str) -> None:
    expected = run("numpy", scene, solver, pos, steps)
    assert_bit_exact(got, expected, f"{what} folded sheet, {steps} steps")
    without = run("numpy", scene.replace(self_collision=None), solver, pos, steps)
    assert not np.array_equal(expected, without), "the pass pushed no pair: the test shows nothing"


@pytest.mark.parametrize("steps", [1, 20])
@pytest.mark.parametrize("solver_name", ["verlet", "vbd"])  # the CUDA classes that declare it
def test_cuda_strict_self_collision_on_its_cpu_build_matches_numpy_f32_bit_for_bit(cuda_on_cpu, solver_name, steps):  # noqa: F811
    cuda_on_cpu.install()
    solver = SOLVERS[solver_name]
    assert solver_name in backend_class("cuda", solver_name).capabilities.self_collision
    scene, pos = sheet()
    got = run("cuda", scene, solver, pos, steps, strict=True)
    assert_matches_numpy(got, scene, solver, pos, steps, f"cuda (CPU build) {solver_name}")


@pytest.mark.parametrize("param, solver_name", params())
def test_a_backend_without_self_collision_refuses_it_in_one_line_before_any_work(param, solver_name):
    name, _ = usable(param)
    if solver_name in backend_class(name, solver_name).capabilities.self_collision:
        pytest.skip(f"{name} {solver_name} declares self_collision")
    scene, _ = sheet()
    with pytest.raises(ClothbenchError) as e:
        create_backend(name, scene, SOLVERS[solver_name], options(name, solver_name))
    message = str(e.value)
    assert "[self_collision]" in message and "(numpy" in message and "\n" not in message  # who takes it
