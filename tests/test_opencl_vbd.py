"""The OpenCL VBD solver beyond the contract (tests/contract/test_vbd_contract.py): strict is
the NumPy float32 reference bit for bit with meshes, moving colliders and pins attached to a
body (either mesh search, one collider table per substep across an upload of them) and on every
runtime here that compiles; fast stays within a few times NumPy float32's own error; a scene
compiles only the parts it has."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import device
from clothbench.backends.opencl.bodies import STEPS_PER_UPLOAD
from clothbench.harness import position_error, reference, simulate
from clothbench.model.scene import load_setup
from clothbench.model.solver import Vbd
from conftest import assert_bit_exact, every_collider_scene, require

N = 16  # as tests/test_pbd_meshes.py: the spacing still drapes over the torus's tube
# substeps: 5 at 60 steps is 300 tables, more than one upload holds; the torus is touched
# from about 0.14 s, the paddle sweeps 90 degrees in 1 s, the bar carries the sheet 9 cm in 1 s
SUBSTEPS = 5
STEPS = {"torus": 30, "sweep": 60, "carried": 60}
ALGORITHMS = ("naive", "accelerated")


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


@functools.lru_cache(maxsize=None)
def setup(name: str):
    return scene_of(name), Vbd(dt=1 / 60, substeps=SUBSTEPS, chebyshev_rho=0.9)


def scene_of(name: str):
    """Built-in scene `name` at N, or a skip where it has meshes and trimesh is missing."""
    scene = load_setup(name).scene.replace(grid=N)
    if scene.meshes:
        pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")
    return scene


# the quick tier runs the moving mesh with the default search (it crosses an upload of the
# collider tables, the case the others add to); every scene and search in the full tier
BODY_CASES = [
    pytest.param(name, algorithm, marks=() if (name, algorithm) == ("sweep", ALGORITHMS[0]) else pytest.mark.full)
    for name in STEPS  # a mesh; a moving mesh; pins on a moving bar
    for algorithm in ALGORITHMS
]


@pytest.mark.parametrize("name, algorithm", BODY_CASES)
def test_strict_vbd_with_bodies_matches_numpy_f32_bit_for_bit(name, algorithm):
    scene, solver = setup(name)
    if scene.has_motion:
        assert STEPS[name] * SUBSTEPS > STEPS_PER_UPLOAD, "the run crosses an upload of tables"
    ref_pos, ref_prev = reference(scene, solver, STEPS[name], "f32")
    pos, prev = simulate("opencl", scene, solver, STEPS[name], BackendOptions(strict=True, mesh_collision=algorithm))
    assert_bit_exact(pos, ref_pos, f"pos, {name} {algorithm}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} {algorithm}")
    if scene.meshes:  # and the mesh was touched: without it the sheet ends elsewhere
        free = simulate("opencl", scene.replace(meshes=()), solver, STEPS[name], BackendOptions(strict=True))[0]
        assert not np.array_equal(free, pos), f"{name}: the cloth never reached the mesh"


@pytest.mark.parametrize("name", ["all kinds", "torus", "carried"])
def test_fast_vbd_error_is_of_the_order_of_numpy_f32s_own(name):
    # Fast contracts FMAs and takes one rsqrt per spring: O(float32 epsilon) per operation, as
    # the reference's own roundings. Measured (PoCL 3.1, 16^2, 60 steps at 60 Hz, 10 sweeps):
    # fast's max error from f64 is 1.3-4.4x NumPy f32's (2-8 um). The bound, 8x with a 2 um
    # floor, still catches a slip in the step: 1% on k alone puts NumPy f32 0.3-2 mm off, 10%
    # on b 0.9-22 mm. Not with Chebyshev or the curtain: contact there turns one particle
    # pushed a substep earlier into millimetres.
    scene = every_collider_scene(N) if name == "all kinds" else scene_of(name)
    solver = Vbd(dt=1 / 60)
    ref64 = reference(scene, solver, 60, "f64")[0]
    _, f32_max = position_error(reference(scene, solver, 60, "f32")[0], ref64)
    _, fast_max = position_error(simulate("opencl", scene, solver, 60, BackendOptions())[0], ref64)
    assert fast_max <= 8 * f32_max + 2e-6, f"{name}: fast {fast_max:.3g} m, NumPy f32 {f32_max:.3g} m"


def test_strict_vbd_is_bit_exact_on_every_runtime_here_that_compiles():
    # the Intel CPU runtime as well as PoCL: no runtime may contract or reorder a strict build
    scene, solver = load_setup("curtain").scene.replace(grid=24), Vbd(dt=1 / 60, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, 100, "f32")
    compiling = [(spec, kind) for spec, dev, kind in device.ordered_devices() if device.compile_error(dev) is None]
    assert compiling, "no OpenCL device here compiles"
    for spec, kind in compiling:
        pos, prev = simulate("opencl", scene, solver, 100, BackendOptions(strict=True, device=spec))
        assert_bit_exact(pos, ref_pos, f"pos, {kind} ({spec})")
        assert_bit_exact(prev, ref_prev, f"prev, {kind} ({spec})")


def test_a_scene_compiles_only_the_parts_it_has():
    cases = {
        "drape": (),
        "torus": ("-DCLOTH_MESHES=1", "-DCLOTH_MESH_BVH"),
        "carried": ("-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED_PINS"),
    }
    parts = ("CLOTH_MESHES", "CLOTH_MESH_BVH", "CLOTH_PER_STEP", "CLOTH_ATTACHED_PINS")
    for name, expected in cases.items():
        scene, solver = scene_of(name), Vbd(dt=1 / 60)
        with create_backend("opencl", scene, solver, BackendOptions(strict=True)) as b:
            built = b.build_options()
            has_mesh_code = "closest_point" in b.source
        found = {o.split("=")[0] for o in built if any(o.startswith(f"-D{p}") for p in parts)}
        assert found == {o.split("=")[0] for o in expected}, f"{name}: {built}"
        assert has_mesh_code == bool(scene.meshes), f"{name}: mesh code in the source"
