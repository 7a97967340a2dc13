"""The oriented box on OpenCL (kernels/collide.cl collide_box, kernels/verlet_cloth.cl
collide_box_v): every branch of docs/semantics.md's "Box" exact in strict mode in both
Verlet builds, every Verlet kernel shape and every PBD shape bit for bit with the NumPy
float32 reference on the box scene (tests/contract/test_box_contract.py runs the default
shape of each), and a scene without a box compiles no box code."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import device, verlet as opencl
from clothbench.backends.opencl.pbd import OpenCLPbdBackend
from clothbench.backends.opencl.verlet_shapes import tuning_key
from clothbench.errors import ClothbenchError
from clothbench.harness import reference
from clothbench.kernel_source import read_kernel
from clothbench.model.scene import Box, Scene, load_setup
from clothbench.model.solver import Pbd
from conftest import BOX_SCENE, BOX_STEPS, VERLET, assert_bit_exact, require


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


def box_scene() -> Scene:
    return load_setup(str(BOX_SCENE)).scene


# Particles placed in every branch of the box (no springs, no gravity, no damping: only the
# colliders move them, in one step): an unrotated box and a rotated one that overlaps it, so a
# particle pushed out of the first can land in the second (the order within the kind).
CASES_SCENE = Scene(
    grid=20,
    stiffness=0.0,
    damping=0.0,
    gravity=(0.0, 0.0, 0.0),
    height=5.0,
    boxes=(
        Box(center=(0.5, 0.5, 0.5), half_extents=(0.1, 0.2, 0.3)),
        Box(center=(0.62, 0.5, 0.5), half_extents=(0.05, 0.1, 0.1), rotation=(20.0, -30.0, 45.0)),
        Box(center=(2.0, 0.0, 0.0), half_extents=(0.25, 0.25, 0.25)),
    ),
    pin_indices=(300,),
)
CASES = [
    (0.41, 0.5, 0.3),  # near the -x face
    (0.5, 0.32, 0.5),  # near the -y face
    (0.5, 0.61, 0.5),  # near the +y face
    (0.45, 0.5, 0.79),  # near the +z face
    (0.5, 0.5, 0.25),  # near the -z face
    (0.5, 0.5, 0.5),  # the centre: least depth on axis 0, its + face (l = 0), on into the next box
    (0.59, 0.5, 0.5),  # out through +x into the rotated box, and out of it
    (0.63, 0.52, 0.49),  # inside the rotated box only
    (2.0, 0.0, 0.0),  # the centre of a cube: ties to axis 0, its + face
    (2.125, 0.125, 0.0),  # an exact tie of axes 0 and 1 (0.125 deep): axis 0
    (0.8, 0.5, 0.5),  # outside every box: untouched
    (0.6, 0.3, 0.5),  # on a face of the first (not strictly inside): not moved there
    (0.5, 0.5, 0.55),  # the pinned particle (index 300), inside a box: never collided
]
CASE_INDEX = [0, 19, 21, 45, 50, 137, 155, 199, 222, 260, 246, 399, 300]  # border and interior


def one_step_of_cases(name: str, options: BackendOptions) -> np.ndarray:
    pos, prev = CASES_SCENE.initial_state(np.float32 if name == "opencl" else np.float64)
    pos[:, :3] = np.linspace(5, 6, pos.shape[0])[:, None]  # everyone else far from every box
    pos[CASE_INDEX, :3] = CASES
    prev[:, :3] = pos[:, :3]
    with create_backend(name, CASES_SCENE, VERLET, options) as b:
        b.upload(pos, prev)
        b.advance(1)
        return b.read()[0]


@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
def test_every_box_branch_is_exact_in_strict_and_within_ulps_in_fast(generic):
    expected = one_step_of_cases("numpy", BackendOptions(precision="f32"))
    moved = expected[CASE_INDEX, :3] != np.array(CASES, np.float32)
    assert moved[:10].any(axis=1).all(), "every case but the last three is pushed somewhere"
    assert not moved[10:].any(), "the last three stay"
    strict = one_step_of_cases("opencl", BackendOptions(strict=True, generic=generic))
    assert_bit_exact(strict, expected, "strict")
    # fast: the same formulas, contracted where the compiler likes; ~1 ulp of 2 m
    fast = one_step_of_cases("opencl", BackendOptions(generic=generic))
    np.testing.assert_allclose(fast, expected, rtol=0, atol=1e-6)


def test_every_verlet_shape_is_bit_exact_with_numpy_f32_on_boxes():
    # stepped 1 then 499 more: a step count that is not a multiple of the multi-step kernel's
    scene = box_scene()
    names = opencl.OpenCLBackend.kernel_shapes(scene, BackendOptions(strict=True))
    assert any(c.startswith("rows/") for c in names) and any(c.startswith("steps/") for c in names)
    for name in names:
        with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, shape=name)) as b:
            b.upload(*b.initial_state())
            done = 0
            for steps in (1, BOX_STEPS):
                b.advance(steps - done)
                done = steps
                pos, prev = b.read()
                ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
                assert_bit_exact(pos, ref_pos, f"pos, {name} after {steps} steps")
                assert_bit_exact(prev, ref_prev, f"prev, {name} after {steps} steps")


@pytest.mark.parametrize(
    "solver",
    [Pbd(dt=5e-4, iterations=4, substeps=2, method="jacobi")]
    + [pytest.param(Pbd(dt=5e-4, iterations=4, substeps=2, method="coloured"), marks=pytest.mark.full)]
    + [pytest.param(Pbd(dt=5e-4, iterations=4, substeps=2, chebyshev_rho=0.9), marks=pytest.mark.full)],
    ids=["jacobi", "coloured", "chebyshev"],  # the two others in the full tier: the same box code, other passes
)
def test_every_pbd_shape_is_bit_exact_with_numpy_f32_on_boxes(solver):
    scene = box_scene().replace(grid=24)  # the bands shapes' smallest grid, and quicker
    ref_pos, ref_prev = reference(scene, solver, BOX_STEPS, "f32")
    without = reference(scene.replace(boxes=()), solver, BOX_STEPS, "f32")[0]
    assert (ref_pos != without).any(), f"no particle touched a box in {BOX_STEPS} steps"
    for name in OpenCLPbdBackend.kernel_shapes(scene, BackendOptions(strict=True), solver):
        with create_backend("opencl", scene, solver, BackendOptions(strict=True, shape=name)) as b:
            b.upload(*b.initial_state())
            b.advance(BOX_STEPS)
            pos, prev = b.read()
        assert_bit_exact(pos, ref_pos, f"pos, pbd {solver.method} {name}")
        assert_bit_exact(prev, ref_prev, f"prev, pbd {solver.method} {name}")


def test_a_scene_without_a_box_compiles_no_box_code(monkeypatch):
    # Break the box of the specialised build: a scene without boxes still builds (its code
    # never reaches the compiler) and takes no CLOTH_BOXES; a box scene does not build.
    source = read_kernel(opencl.KERNEL_FILE)
    signature = "void collide_box_v("
    assert signature in source
    monkeypatch.setattr(device, "read_kernel", lambda name: source.replace(signature, "no_such_type collide_box_v("))
    without = box_scene().replace(boxes=())
    with create_backend("opencl", without, VERLET, BackendOptions(strict=True)) as b:
        options = " ".join(o for program_options in b.key for o in program_options)
        assert "-DCLOTH_SPHERES=1" in options and "BOXES" not in options, options
    with pytest.raises(ClothbenchError, match="no_such_type"):
        create_backend("opencl", box_scene(), VERLET, BackendOptions(strict=True))


def test_boxes_have_their_own_tuning_key_and_a_scene_without_keeps_its_old_one():
    scene, cpu = box_scene(), SimpleNamespace(name="cpu", platform=SimpleNamespace(version="1"), driver_version="1")
    with_boxes = tuning_key(cpu, scene, BackendOptions(), "")
    without = tuning_key(cpu, scene.replace(boxes=()), BackendOptions(), "")
    assert with_boxes["boxes"] == "2" and "boxes" not in without
    assert with_boxes["colliders"] == without["colliders"] == "1/0/1"  # spheres/cylinders/planes
