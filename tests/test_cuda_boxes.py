"""The oriented box in the CUDA kernels (kernels/verlet_cloth.cu, collide_box), proved without a
GPU the way tests/test_cuda.py proves the other colliders: nvcc -ptx compiles the box builds
without warnings and, strict, without a fused multiply-add; the CPU build of the unmodified
kernel (clothbench/backends/cuda/cpu.py) is the NumPy float32 reference bit for bit on the
contract's box scene (tests/data/boxes.toml: a fixed rotated box and a moving one), fixed and
moving, specialised and generic, in both kernels and through CudaBackend itself; every branch
of docs/semantics.md's box response on hand-placed particles; a build whose scene has no box
holds no box code. On a device the contract test (tests/contract/test_box_contract.py) runs it.
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from clothbench.backends import BackendOptions, backend_class, create_backend
from clothbench.backends.cuda import cpu, launch
from clothbench.backends.cuda import verlet as cuda
from clothbench.backends.cuda.launch import PingPong
from clothbench.harness import reference
from clothbench.harness.plan import without_motion
from clothbench.kernel_source import kernel_path
from clothbench.model.scene import Box, Scene, load_setup

from conftest import BOX_SCENE, BOX_STEPS, VERLET, assert_bit_exact, sphere
from test_cuda import cuda_on_cpu, entry_body, shim_library  # noqa: F401  (fixtures: the stand-in cupy)

KERNEL = kernel_path(cuda.KERNEL_FILE)
# the contract's length: the sheet reaches both boxes, moving or stopped, well within it
# (tests/contract/test_box_contract.py checks)
BUILDS = {"specialised": False, "generic": True}


def box_scene(moving: bool = True) -> tuple[Scene, object]:
    """(scene, solver) of the contract's box scene; not moving: its motion stopped, so that the
    specialised build compiles the box rows in as constants."""
    setup = load_setup(str(BOX_SCENE))
    return (setup.scene if moving else without_motion(setup.scene)), setup.solver


def pingpong(scene, solver, strict=True, generic=False, steps_per_launch=None) -> PingPong:
    """A PingPong on the CPU build of this scene: verlet_step, or verlet_steps in one block."""
    if cpu.gxx() is None:
        pytest.skip("g++ not found: cannot build the CPU shim of the CUDA kernel")
    lib = cpu.build(strict, cuda.kernel_defines(scene, solver, False, generic))
    if steps_per_launch is None:
        return PingPong(cpu.ShimRuntime(lib), scene, solver, generic=generic)
    return PingPong(
        cpu.ShimRuntime(lib, launch.STEPS_KERNEL),
        scene,
        solver,
        generic=generic,
        block=launch.multistep_threads(scene.particles),
        steps_per_launch=steps_per_launch,
    )


def assert_equals_reference(pos, prev, scene, solver, steps, what):
    ref_pos, ref_prev = reference(scene, solver, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos after {steps} steps, {what}")
    assert_bit_exact(prev, ref_prev, f"prev after {steps} steps, {what}")


# --- nvcc --------------------------------------------------------------------------------

NVCC_VARIANTS = [
    (moving, strict, generic) for moving in (False, True) for strict in (True, False) for generic in (False, True)
]


def nvcc_id(variant) -> str:
    moving, strict, generic = variant
    return "-".join(
        ["moving" if moving else "fixed", "strict" if strict else "fast", "generic" if generic else "specialised"]
    )


@pytest.mark.parametrize("variant", NVCC_VARIANTS, ids=nvcc_id)
def test_box_kernels_compile_for_sm80_without_warnings(tmp_path, variant):
    if shutil.which("nvcc") is None:
        pytest.skip("nvcc not found on PATH (CUDA toolkit not installed)")
    moving, strict, generic = variant
    scene, solver = box_scene(moving)
    defines = [cuda._nvcc_escaped(d) for d in cuda.kernel_defines(scene, solver, False, generic)]
    out = tmp_path / "boxes.ptx"
    cmd = ["nvcc", "-ptx", "-arch=sm_80", *cuda.compile_options(strict), *defines,
           "-Werror", "all-warnings", "-o", str(out), str(KERNEL)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and not (done.stdout + done.stderr).strip(), done.stdout + done.stderr
    ptx = out.read_text()
    assert ".entry verlet_step(" in ptx and ".entry verlet_steps(" in ptx
    if not moving and not generic:  # the boxes' rows compiled in: a step loads only positions
        assert entry_body(ptx, "verlet_step").count("ld.global") == 2 + 12
    if strict:
        assert "fma." not in ptx and ".approx" not in ptx and ".ftz" not in ptx


def preprocessed(scene: Scene, generic: bool) -> str:
    """The kernel after the preprocessor, with the scene's -D switches (g++ -E runs the same #if)."""
    if shutil.which("g++") is None:
        pytest.skip("g++ not found")
    cmd = ["g++", "-E", "-P", "-x", "c++", *cuda.kernel_defines(scene, VERLET, False, generic), str(KERNEL)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_only_a_scene_with_boxes_builds_box_code():
    assert "collide_box" not in preprocessed(sphere(16), generic=False)
    assert "collide_box" in preprocessed(box_scene(False)[0], generic=False)
    assert "collide_box" in preprocessed(sphere(16), generic=True)  # generic: every kind
    defines = " ".join(cuda.kernel_defines(sphere(16), VERLET))
    assert "-DCLOTH_BOX_COUNT=0" in defines and "CLOTH_BOXES" not in defines


# --- the CPU build: bit for bit with NumPy float32 ----------------------------------------


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("moving", [False, True], ids=["fixed", "moving"])
def test_strict_boxes_on_the_cpu_build_equal_numpy_f32(build, moving):
    scene, solver = box_scene(moving)
    pp = pingpong(scene, solver, generic=BUILDS[build])
    pp.upload(*solver.initial_state(scene, np.float32))
    pp.advance(BOX_STEPS)
    assert_equals_reference(*pp.read(), scene, solver, BOX_STEPS, f"{build}, {'moving' if moving else 'fixed'}")


@pytest.mark.parametrize("build", BUILDS)
def test_strict_boxes_in_the_multistep_kernel_equal_numpy_f32(build):
    # verlet_steps reads step s's rows of the moving box at motion + s * rows: 37 is not a
    # multiple of 16, so a launch of the remainder is checked too
    scene, solver = box_scene(moving=True)
    pp = pingpong(scene, solver, generic=BUILDS[build], steps_per_launch=16)
    pp.upload(*solver.initial_state(scene, np.float32))
    pp.advance(37)
    assert_equals_reference(*pp.read(), scene, solver, 37, f"{build}, verlet_steps")
    pp.advance(BOX_STEPS - 37)
    assert_equals_reference(*pp.read(), scene, solver, BOX_STEPS, f"{build}, verlet_steps")


def test_strict_boxes_through_cuda_backend_equal_numpy_f32(cuda_on_cpu):  # noqa: F811
    # the contract's strict run (tests/contract/test_box_contract.py), through CudaBackend's own
    # host code over the stand-in cupy whose kernel is the CPU build it asked for
    scene, solver = box_scene(moving=True)
    assert solver == VERLET  # the stand-in backend runs with tests/conftest.py's VERLET
    backend, _ = cuda_on_cpu(scene, strict=True)
    with backend:
        assert "-DCLOTH_BOX_COUNT=2" in backend.defines
        backend.upload(*solver.initial_state(scene, np.float32))
        backend.advance(BOX_STEPS)
        backend.synchronize()
        pos, prev = backend.read()
    assert_equals_reference(pos, prev, scene, solver, BOX_STEPS, "CudaBackend")


# Hand-placed particles, one in each branch of the response, in a box rotated about all three
# axes: no springs, gravity or damping, so each particle stays where it is until collided.
ROTATED = Box(center=(0.2, -0.1, 0.4), half_extents=(0.3, 0.15, 0.2), rotation=(25.0, -40.0, 70.0))
CUBE = Box(center=(2.0, 0.0, 0.0), half_extents=(0.25, 0.25, 0.25))  # ties: equal depths


def every_branch() -> tuple[Scene, np.ndarray]:
    rot = ROTATED.pose_at(0.0)[0]
    local = [
        (0.29, 0.0, 0.0), (-0.29, 0.01, 0.0),  # nearest the + and - faces of axis 0
        (0.0, 0.14, 0.02), (0.05, -0.14, 0.0),  # axis 1, both faces
        (0.01, 0.0, 0.19), (0.0, 0.02, -0.19),  # axis 2, both faces
        (0.0, 0.0, 0.0),  # the centre: least depth on axis 1, its + face (l = 0)
        (0.31, 0.0, 0.0), (0.0, 0.16, 0.0),  # outside
        (0.1, 0.12, 0.0),  # inside, pinned: never collided
    ]  # fmt: skip
    points = [np.array(ROTATED.center) + rot @ np.array(p) for p in local]
    points += [(2.0, 0.0, 0.0), (2.125, 0.125, 0.0), (2.0, -0.125, 0.125)]  # the cube: exact ties, to the lower axis
    points += [(2.25, 0.0, 0.0), (2.0, 0.3, 0.0)]  # on the cube's face (not strictly inside), outside it
    n = 4
    state = np.zeros((n * n, 4), np.float32)
    state[:, :3] = (5.0, 5.0, 5.0)  # the rest of the grid, far from both boxes
    state[:, 3] = 100.0
    state[: len(points), :3] = np.array(points, np.float64)
    state[9, 3] = 0.0
    scene = Scene(grid=n, stiffness=0.0, damping=0.0, gravity=(0, 0, 0), boxes=(ROTATED, CUBE))
    return scene, state


@pytest.mark.parametrize("build", BUILDS)
def test_every_branch_of_the_box_equals_numpy_f32(build):
    scene, state = every_branch()
    pp = pingpong(scene, VERLET, generic=BUILDS[build])
    pp.upload(state, state)
    pp.step()
    got = pp.read()[0]
    assert_bit_exact(got, reference_one_step(scene, state), f"one step, every branch, {build}")
    moved = (got[:, :3] != state[:, :3]).any(axis=1)
    assert moved.tolist() == [True] * 7 + [False] * 3 + [True] * 3 + [False] * (len(state) - 13)
    np.testing.assert_allclose(got[10:13, :3], [(2.25, 0.0, 0.0), (2.25, 0.125, 0.0), (2.0, -0.25, 0.125)], atol=1e-7)
    # a moved particle of the rotated box lies on the face its local coordinate names
    local = (got[:7, :3].astype(np.float64) - ROTATED.center) @ ROTATED.pose_at(0.0)[0]
    faces = [(0, 0.3), (0, -0.3), (1, 0.15), (1, -0.15), (2, 0.2), (2, -0.2), (1, 0.15)]
    for i, (axis, face) in enumerate(faces):
        assert abs(local[i, axis] - face) < 1e-6, f"particle {i}: {local[i]}"


def reference_one_step(scene: Scene, state: np.ndarray) -> np.ndarray:
    with create_backend("numpy", scene, VERLET, BackendOptions(precision="f32")) as b:
        b.upload(state, state)
        b.advance(1)
        return b.read()[0]


def test_the_cuda_backend_declares_boxes():
    caps = backend_class("cuda").capabilities
    assert "verlet" in caps.boxes
    assert caps.scene_refusal("cuda", box_scene(moving=True)[0]) is None
