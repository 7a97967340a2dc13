"""[self_collision] on the CUDA backend's Verlet step (kernels/self_collision.cuh, docs/cuda.md
"Self-collision"), proved without a GPU:

1. nvcc -ptx compiles the pass into the module, strict and fast, specialised and generic, with
   normals, meshes and motion, without a warning; strict PTX has no FMA and no approximation;
   a scene without the table compiles none of it. The same of the VBD kernel (vbd_cloth.cu).
2. The CPU build (shim/) run by PingPong: strict is the NumPy float32 reference bit for bit
   where each particle has several pairs (so the order of its sum shows), in both builds, both
   transfers, with normals, a block that divides neither the grid nor the sort, pad slots,
   cells of 1 and 2.5 thicknesses, clamped keys, and with colliders, a mesh, motion and an
   attached pin acting after the pass; fast within float32's own error.
3. CudaBackend over the stand-in cupy (tests/test_cuda.py): every shape it offers, bit for bit;
   the multi-step shapes are not offered, and naming one is refused in one line.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.cuda import cpu, launch
from clothbench.backends.cuda import vbd
from clothbench.backends.cuda import verlet as cuda
from clothbench.backends.cuda.cpu import ShimRuntime
from clothbench.backends.cuda.launch import PingPong
from clothbench.backends.cuda.self_contact import KERNELS
from clothbench.backends.numpy.self_collision import SelfCollisionPass
from clothbench.errors import ClothbenchError
from clothbench.harness import position_error
from clothbench.model.kernel_inputs import SelfCollisionConstants
from clothbench.model.scene import SelfCollision
from clothbench.model.solver import solver_for_spec

from conftest import VERLET, assert_bit_exact, every_kind
from folded_sheet import folded, on_bodies
from test_cuda import BUILDS, MODES, ONE_NVCC_WORKER, entry_body, nvcc_build
from test_cuda import cuda_on_cpu, shim_library  # noqa: F401  (fixtures: the stand-in cupy)
from test_cuda_vbd import launches_on_cpu
from test_cuda_vbd import nvcc_ptx as vbd_ptx

STEPS = 20  # every pair of the fold pushed, several times
# 1.5 spacings, the fold's layers 0.5 apart: each particle has several pairs across the fold, so
# the order of its sum shows in the bits (at the contract's 0.8 it has one)
THICK = 1.5


def sheet(n: int = 16):
    return folded(n, thickness=THICK)


def numpy_run(scene, pos, steps: int, **options):
    with create_backend("numpy", scene, VERLET, BackendOptions(**options)) as b:
        b.upload(pos, pos)
        b.advance(steps)
        return b.read()


def cpu_run(scene, pos, steps: int, strict=True, generic=False, normals=False, mesh_collision=None, **options):
    """(pos, prev) after `steps` steps of the CPU build through PingPong, and the PingPong."""
    if cpu.gxx() is None:
        pytest.skip("g++ not found: cannot build the CPU shim of the CUDA kernel")
    transfer = options.get("transfer", "swap")  # the build's, as the backend's
    lib = cpu.build(strict, cuda.kernel_defines(scene, VERLET, normals, generic, mesh_collision, transfer))
    contact = tuple(ShimRuntime(lib, name) for name in KERNELS)
    pp = PingPong(ShimRuntime(lib), scene, VERLET, generic=generic, normals=normals, self_collision=contact, **options)
    pp.upload(pos, pos)
    pp.advance(steps)
    return pp.read(), pp


def assert_matches_numpy(scene, pos, what: str, steps: int = STEPS, **build):
    (got, got_prev), pp = cpu_run(scene, pos, steps, **build)
    expected, expected_prev = numpy_run(scene, pos, steps)
    assert_bit_exact(got, expected, f"pos, {what}")
    assert_bit_exact(got_prev, expected_prev, f"prev, {what}")
    without = numpy_run(scene.replace(self_collision=None), pos, steps)[0]
    assert not np.array_equal(expected, without), f"{what}: the pass pushed no pair, the test shows nothing"
    c = pp.contact
    launches = [k.launches for k in (c.keys_kernel, c.sort_kernel, c.pass_kernel)]
    assert launches == [steps, steps * len(pp.contact.stages), steps], f"{what}: the pass's launches"
    return pp


def test_each_particle_has_several_pairs_so_the_sum_order_shows():
    # the premise of the bit-exact tests below: a particle summing in another order than
    # ascending j would round differently
    scene, pos = sheet()
    i = SelfCollisionPass(scene, np.float32).pairs(pos[:, :3])[0]
    assert np.bincount(i).max() >= 4, np.bincount(i).max()


@pytest.mark.parametrize(
    "n, build",
    [
        (16, {}),
        (16, {"generic": True}),
        (16, {"transfer": "copy"}),
        (16, {"normals": True, "block": 24}),  # 256 particles and slots in blocks of 24: padded launches
        (16, {"generic": True, "block": 24}),
        (12, {"block": 64}),  # 144 particles, 256 slots: pad slots sort last
    ],
    ids=str,
)
def test_strict_matches_numpy_f32_bit_for_bit_in_every_build(n, build):
    scene, pos = sheet(n)
    assert_matches_numpy(scene, pos, f"n={n} {build}", **build)


@pytest.mark.parametrize("cell", [1.0, 2.5])
def test_strict_matches_numpy_f32_with_cells_larger_than_the_thickness(cell):
    # 2.5 thicknesses: every cell holds several particles of both layers, so the runs merged
    # hold candidates past the thickness that the distance test rejects
    scene, pos = sheet()
    t = scene.self_collision.thickness
    scene = scene.replace(self_collision=SelfCollision(thickness=t, cell=cell * t))
    assert_matches_numpy(scene, pos, f"cell {cell}")


def test_strict_matches_numpy_f32_where_the_cell_keys_are_clamped():
    # 200 km out along every axis the keys pass 2^20 cells and clamp: the whole sheet is in one
    # cell, whose 27 neighbours are that cell again; each candidate is met once
    scene, pos = sheet()
    pos[:, :3] += np.float32(2e5)
    assert float(pos[:, :3].min()) * float(SelfCollisionConstants.of(scene).inv_cell) > 2**20, "keys clamp"
    assert_matches_numpy(scene, pos, "clamped", steps=5)


def bodies_scene():
    return on_bodies(sheet(16))


@pytest.mark.parametrize("build", [{}, {"generic": True}, {"mesh_collision": "naive"}], ids=str)
def test_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit(build):
    scene, pos = bodies_scene()
    assert_matches_numpy(scene, pos, f"bodies {build}", steps=40, **build)


def test_vbd_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit():
    # VbdLaunches on the CPU build: the pass's rows are the substep's, as vbd_collide's were
    scene, pos = bodies_scene()
    solver = solver_for_spec("vbd", VERLET)
    state = launches_on_cpu(scene, solver)
    state.upload(pos, pos)
    state.advance(STEPS)
    expected = {}
    for table in (scene.self_collision, None):
        with create_backend("numpy", scene.replace(self_collision=table), solver, BackendOptions()) as b:
            b.upload(pos, pos)
            b.advance(STEPS)
            expected[table] = b.read()[0]
    assert_bit_exact(state.read()[0], expected[scene.self_collision], f"vbd bodies, {STEPS} steps")
    assert not np.array_equal(expected[scene.self_collision], expected[None]), "the pass pushed no pair"


def test_fixed_colliders_act_after_the_pass_bit_for_bit():
    # the specialised build with the colliders compiled in (no motion), every kind
    scene, pos = sheet(16)
    kinds = every_kind(16)
    scene = scene.replace(spheres=kinds.spheres, cylinders=kinds.cylinders, planes=kinds.planes)
    for generic in (False, True):
        assert_matches_numpy(scene, pos, f"fixed colliders, generic={generic}", generic=generic)


@pytest.mark.parametrize("generic", [False, True])
def test_fast_error_is_of_the_order_of_strict_float32s(generic):
    # Fast mode uses rsqrt in the springs and an approximate sqrt and '/' in the pass: O(float32
    # epsilon) per operation. Held to strict's own distance from float64 (NumPy f64), 3x with a
    # 1 nm floor, as OpenCL's pass is; a slip in the pass (a sign, a share) moves a pair by up to
    # the thickness, centimetres.
    scene, pos = sheet()
    ref64 = numpy_run(scene, pos.astype(np.float64), STEPS, precision="f64")[0]
    _, strict_max = position_error(numpy_run(scene, pos, STEPS)[0], ref64)
    (fast, _), _ = cpu_run(scene, pos, STEPS, strict=False, generic=generic)
    _, fast_max = position_error(fast, ref64)
    assert fast_max <= 3 * strict_max + 1e-9, f"fast {fast_max:.3g} m, NumPy f32 {strict_max:.3g} m"


def test_pingpong_refuses_a_self_colliding_scene_without_the_pass_or_in_verlet_steps():
    scene, _ = sheet()
    lib = cpu.build(True, cuda.kernel_defines(scene, VERLET))
    contact = tuple(ShimRuntime(lib, name) for name in KERNELS)
    with pytest.raises(ValueError, match="self_collision"):
        PingPong(ShimRuntime(lib), scene, VERLET)
    with pytest.raises(ValueError, match="self_collision"):
        PingPong(ShimRuntime(lib, launch.STEPS_KERNEL), scene, VERLET, steps_per_launch=16, self_collision=contact)


# --- 1. what is compiled ---------------------------------------------------------------


@pytest.mark.parametrize("generic", [False, True])
def test_a_scene_without_self_collision_compiles_none_of_it(generic):
    scene, _ = sheet()
    assert "-DCLOTH_SELF_COLLISION" in cuda.kernel_defines(scene, VERLET, generic=generic)
    plain = cuda.kernel_defines(scene.replace(self_collision=None), VERLET, generic=generic)
    assert not any("SELF" in d for d in plain)
    with_pass = cpu.build(True, cuda.kernel_defines(scene, VERLET, generic=generic))
    without = cpu.build(True, plain)
    assert hasattr(with_pass, "self_collision_launch") and not hasattr(without, "self_collision_launch")


def test_a_vbd_scene_without_self_collision_compiles_none_of_it():
    # the -D switches are the key of the build: without the table they are those of before the pass
    scene, _ = sheet()
    plain = scene.replace(self_collision=None)
    assert vbd.vbd_defines(scene) == (vbd.vbd_defines(plain)[0], "-DCLOTH_SELF_COLLISION", *vbd.vbd_defines(plain)[1:])
    assert vbd.kernels_of(plain) == vbd.KERNELS
    with_pass = cpu.build(True, vbd.vbd_defines(scene), vbd.KERNEL_FILE)
    without = cpu.build(True, vbd.vbd_defines(plain), vbd.KERNEL_FILE)
    assert hasattr(with_pass, "self_collision_launch") and not hasattr(without, "self_collision_launch")


NVCC_SCENES = {"fold": lambda: sheet()[0], "bodies": lambda: bodies_scene()[0]}


@pytest.fixture(scope="module")
def self_ptx(tmp_path_factory):
    """(scene, mode, build, normals) -> (nvcc's process, PTX) of the self-colliding builds."""
    if shutil.which("nvcc") is None:
        pytest.skip("nvcc not found on PATH (CUDA toolkit not installed)")
    folder = tmp_path_factory.mktemp("nvcc-self")
    variants = [(s, m, b, normals) for s in NVCC_SCENES for m in MODES for b in BUILDS for normals in (False, True)]
    return {
        (s, m, b, normals): nvcc_build(
            NVCC_SCENES[s](), MODES[m], BUILDS[b], normals, folder / f"{s}-{m}-{b}-{normals}.ptx"
        )
        for s, m, b, normals in variants
    }


@pytest.mark.full  # nvcc builds: test_cuda.py's PTX tests are the quick tier's; these in --full and CI
@ONE_NVCC_WORKER
def test_the_pass_compiles_for_sm80_without_errors_or_warnings(self_ptx):
    for variant, (done, ptx) in self_ptx.items():
        assert done.returncode == 0 and not (done.stdout + done.stderr).strip(), f"nvcc {variant}: {done.stderr}"
        for kernel in (launch.STEP_KERNEL, *KERNELS):
            assert f".entry {kernel}(" in ptx, f"{variant}: no {kernel}"


@pytest.mark.full  # nvcc builds: test_cuda.py's PTX tests are the quick tier's; these in --full and CI
@ONE_NVCC_WORKER
def test_strict_ptx_of_the_pass_rounds_every_operation_on_its_own(self_ptx):
    for (name, mode, build, normals), (_, ptx) in self_ptx.items():
        if mode != "strict":
            continue
        body = entry_body(ptx, "self_collision")
        assert "fma." not in ptx and ".approx" not in ptx and ".ftz" not in ptx, (name, build, normals)
        assert "sqrt.rn.f32" in body and "div.rn.f32" in body, (name, build, normals)


@pytest.mark.full  # nvcc builds: test_cuda.py's PTX tests are the quick tier's; these in --full and CI
@ONE_NVCC_WORKER
@pytest.mark.parametrize("scene_name", NVCC_SCENES)
@pytest.mark.parametrize("mode", MODES)
def test_the_pass_compiles_into_the_vbd_kernel_strict_rounding_every_operation(tmp_path, mode, scene_name):
    ptx = vbd_ptx(NVCC_SCENES[scene_name](), MODES[mode], "sm_80", tmp_path)  # no warning, or it fails
    for kernel in (*vbd.KERNELS, *KERNELS):
        assert f".entry {kernel}(" in ptx, f"vbd {mode} {scene_name}: no {kernel}"
    if MODES[mode]:
        assert "fma." not in ptx and ".approx" not in ptx and ".ftz" not in ptx, scene_name
        body = entry_body(ptx, "self_collision")
        assert "sqrt.rn.f32" in body and "div.rn.f32" in body, scene_name


# --- 3. CudaBackend over the stand-in cupy -----------------------------------------------


def test_cuda_backend_runs_the_pass_in_every_shape_it_offers_bit_for_bit(cuda_on_cpu):  # noqa: F811
    scene, pos = sheet()
    expected = numpy_run(scene, pos, STEPS)
    shapes = cuda.CudaBackend.kernel_shapes(scene, BackendOptions(strict=True))
    assert shapes and all(launch.parse_shape(s, scene.particles)[0] is None for s in shapes), shapes
    for generic in (False, True):
        for shape in shapes:
            backend, _ = cuda_on_cpu(scene, strict=True, generic=generic, shape=shape)
            with backend:
                assert backend.shape == shape
                backend.upload(pos, pos)
                backend.advance(STEPS)
                got = backend.read()
            assert_bit_exact(got[0], expected[0], f"pos, {shape}, generic={generic}")
            assert_bit_exact(got[1], expected[1], f"prev, {shape}, generic={generic}")


def test_the_multi_step_kernel_is_not_offered_with_the_pass_and_naming_it_is_refused(cuda_on_cpu):  # noqa: F811
    scene, _ = sheet()
    options = BackendOptions(strict=True)
    plain = cuda.CudaBackend.kernel_shapes(scene.replace(self_collision=None), options)
    assert "steps/launch=16" in plain, "the test needs a grid the multi-step kernel takes"
    assert cuda.CudaBackend.kernel_shapes(scene, options) == tuple(s for s in plain if s.startswith("block="))
    with pytest.raises(ClothbenchError) as e:
        cuda_on_cpu(scene, strict=True, shape="steps/launch=16")
    assert "steps/launch=16" in str(e.value) and "\n" not in str(e.value)
