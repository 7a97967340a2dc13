"""--strict on any valid scene, also one whose values pass through float32's subnormal range
(docs/semantics.md, "Subnormal floats"): a backend whose arithmetic keeps subnormals, as
NumPy does, is bit-exact there too; one that flushes them to zero (llvmpipe's fragment
shaders, Taichi's threads) cannot be, and its timed run says at which step it parts from
NumPy, with every state before that step still bit-exact."""

from __future__ import annotations

import re

import numpy as np
import pytest

from clothbench.backends import create_backend
from clothbench.harness import reference, run_timed, simulate, strict_watch
from clothbench.model.scene import Scene, load_scene
from clothbench.model.solver import Pbd

from conftest import VERLET, assert_bit_exact, require
from registry_variants import backend_params, options, usable

FLOAT32_TINY = np.finfo(np.float32).tiny  # the smallest normal float32, 1.2e-38
WEIGHTLESS_STEPS = 300


def weightless_scene() -> Scene:
    """A user scene whose coordinates pass through float32's subnormal range: a 16 x 16 sheet
    in zero gravity. It is at rest only up to the float32 rounding of its rest lengths, so the
    springs nudge its edges, and coordinates that start at exactly 0 (the first row's z, the
    first column's x) grow from 0 up through the subnormal range from step 5 on."""
    return Scene(name="weightless", grid=16, gravity=(0.0, 0.0, 0.0))


def test_the_weightless_scene_reaches_subnormals():
    pos, _ = reference(weightless_scene(), VERLET, 5, "f32")
    subnormal = (pos[:, :3] != 0) & (np.abs(pos[:, :3]) < FLOAT32_TINY)
    assert subnormal.any(), "the case no longer reaches the subnormal range"


@pytest.mark.parametrize(
    "chunk",
    [pytest.param(None, marks=pytest.mark.full), 3, pytest.param(1, marks=pytest.mark.full)],
    ids=["chunk30", "chunk3", "chunk1"],
)  # the quick tier: one chunking
@pytest.mark.parametrize("param", backend_params())
def test_strict_on_subnormals_is_exact_or_the_run_says_where_it_parts(param, chunk):
    name, _ = usable(param)
    scene, strict = weightless_scene(), options(name, strict=True)
    with create_backend(name, scene, VERLET, strict) as b:
        result = run_timed(b, WEIGHTLESS_STEPS, chunk=chunk)
        flushes, device = b.flushes_subnormals, b.device
    want = reference(scene, VERLET, WEIGHTLESS_STEPS, "f32")
    if not flushes:
        assert result.strict_divergence is None, result.strict_divergence
        assert_bit_exact(result.pos, want[0], f"{name} --strict through subnormals: pos")
        assert_bit_exact(result.prev, want[1], f"{name} --strict through subnormals: prev")
        return
    # a driver that flushes subnormals cannot give the reference's subnormal values
    line = result.strict_divergence
    assert line is not None, f"{name} flushes subnormals but its strict run reported nothing"
    assert line in result.warnings and "\n" not in line
    assert f"{name} on {device} flushes subnormal floats to zero" in line
    found = re.search(r"at step (\d+): particle (\d+) (pos|prev)\.([xyzw])", line)
    step, particle = int(found[1]), int(found[2])
    state, axis = ("pos", "prev").index(found[3]), "xyzw".index(found[4])
    # every state before that step is the reference's bit for bit; the one at it is not, there
    before, want = simulate(name, scene, VERLET, step - 1, strict), reference(scene, VERLET, step - 1, "f32")
    assert_bit_exact(before[0], want[0], f"{name} --strict before step {step}: pos")
    assert_bit_exact(before[1], want[1], f"{name} --strict before step {step}: prev")
    at = simulate(name, scene, VERLET, step, strict)[state]
    assert at[particle, axis] != reference(scene, VERLET, step, "f32")[state][particle, axis]
    # the timed run carried on from the backend's own state
    alone = simulate(name, scene, VERLET, WEIGHTLESS_STEPS, strict)[0]
    assert_bit_exact(result.pos, alone, f"{name}: the run after parting")


def test_the_watch_steps_its_float32_twin_on_c_where_c_gives_numpys_bits():
    # the twin stepped beside a flushing backend's strict run is c's strict float32 (the
    # contract holds it to NumPy's bits, and above it must give the step NumPy's would), a
    # fiftieth of NumPy's time at 2048^2; NumPy's own where c refuses the scene (a mesh) or the
    # solver (PBD)
    require("c")
    with strict_watch.twin(weightless_scene(), VERLET) as twin:
        assert (twin.name, twin.options.strict, twin.options.precision) == ("c", True, "f32")
    for scene, solver in ((load_scene("torus").replace(grid=8), VERLET), (weightless_scene(), Pbd())):
        with strict_watch.twin(scene, solver) as twin:
            assert twin.name == "numpy", (scene.name, solver.name)


@pytest.mark.parametrize("param", backend_params())
def test_only_strict_runs_are_compared(param):
    name, _ = usable(param)
    with create_backend(name, weightless_scene(), VERLET, options(name)) as b:
        assert run_timed(b, 30).strict_divergence is None
