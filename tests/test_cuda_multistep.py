"""verlet_steps (several steps a launch in one block) and the CUDA kernel shapes, without a GPU.

1. nvcc compiles the module that holds both kernels for sm_80, every build switch both ways;
   ptxas fits verlet_steps in 64 registers, so a block of 1024 threads can launch, with one
   barrier and no fused multiply-add in strict mode.
2. The CPU build runs verlet_steps with real barriers (shim.h: each thread a fiber): strict
   equals NumPy float32 bit for bit after 1, 37 and 500 steps, advance in pieces equals one
   call, and the result does not depend on the order the threads run in between barriers.
3. CudaBackend over the stand-in cupy of tests/test_cuda.py runs every kernel shape it offers
   bit for bit, tunes among them when tuning is on, and says which ran in its mode.
4. On a CUDA device (skipped here): the tuning with CUDA events (every shape bit for bit there
   is tests/contract/test_shapes_contract.py's).
"""

from __future__ import annotations

import ctypes
import json
import shutil
import subprocess

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.cuda import cpu, launch
from clothbench.backends.cuda import verlet as cuda
from clothbench.backends.cuda.launch import PingPong
from clothbench.errors import ClothbenchError
from clothbench.harness import reference, simulate
from clothbench.harness.normals import grid_normals
from clothbench.kernel_source import kernel_path
from clothbench.model.scene import load_scene

from conftest import VERLET, assert_bit_exact, every_collider_scene, require, sphere
from test_cuda import SPHERE_STEPS, assert_as_accurate_as_float32, scene_parameters
from test_cuda import ONE_NVCC_WORKER, cuda_on_cpu, shim_library  # noqa: F401  (fixtures: the stand-in cupy)

SCENES = {"sphere": sphere, "every-collider": every_collider_scene}
CHECKPOINTS = (1, 37, 500)  # steps: one, a remainder of both K, the run the brief asks for


def needs_gxx() -> None:
    if cpu.gxx() is None:
        pytest.skip("g++ not found: cannot build the CPU shim of the CUDA kernel")


def multistep(
    scene, steps_per_launch, strict=True, generic=False, normals=False, block=None, transfer="swap", **options
):
    """A PingPong on verlet_steps of the CPU build, one block of `block` threads (default: as
    the backend chooses)."""
    needs_gxx()
    defines = cuda.kernel_defines(scene, VERLET, normals, generic, transfer=transfer)
    runtime = cpu.ShimRuntime(cpu.build(strict, defines), "verlet_steps")
    threads = block or launch.multistep_threads(scene.particles)
    return PingPong(
        runtime,
        scene,
        VERLET,
        block=threads,
        generic=generic,
        normals=normals,
        steps_per_launch=steps_per_launch,
        transfer=transfer,
        **options,
    )


def start(pp: PingPong, scene) -> PingPong:
    pp.upload(*VERLET.initial_state(scene, np.float32))
    return pp


# --- 1. nvcc -------------------------------------------------------------------------

BUILD_VARIANTS = [
    (strict, generic, normals) for strict in (True, False) for generic in (False, True) for normals in (False, True)
]


def variant_id(v) -> str:
    return ("strict" if v[0] else "fast") + ("-generic" if v[1] else "-specialised") + ("-normals" if v[2] else "")


@pytest.fixture(scope="module")
def nvcc_builds(tmp_path_factory):
    """variant -> (ptxas resource report, PTX) of the every-collider scene at 64 x 64. The
    kernel shapes need no build of their own: block size, steps per launch and shared memory
    are launch parameters of the two kernels of this one module."""
    if shutil.which("nvcc") is None:
        pytest.skip("nvcc not found on PATH (CUDA toolkit not installed)")
    folder = tmp_path_factory.mktemp("nvcc_multistep")
    builds = {}
    for v in BUILD_VARIANTS:
        defines = [cuda._nvcc_escaped(d) for d in cuda.kernel_defines(every_collider_scene(64), VERLET, v[2], v[1])]
        base = ["nvcc", "-arch=sm_80", *cuda.compile_options(v[0]), *defines, "-Werror", "all-warnings"]
        ptx, cubin = folder / f"{variant_id(v)}.ptx", folder / f"{variant_id(v)}.cubin"
        done = subprocess.run(
            [*base, "-ptx", "-o", str(ptx), str(kernel_path(cuda.KERNEL_FILE))],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0 and not (done.stdout + done.stderr).strip(), done.stderr
        done = subprocess.run(
            [*base, "-cubin", "--resource-usage", "-o", str(cubin), str(kernel_path(cuda.KERNEL_FILE))],
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr
        builds[v] = (done.stdout + done.stderr, ptx.read_text())
    return builds


def entry(ptx: str, name: str) -> str:
    head = ptx[ptx.index(f".entry {name}(") :]
    following = head.find(".entry", 1)
    return head if following < 0 else head[:following]


@pytest.mark.full  # nvcc builds: test_cuda.py's PTX tests are the quick tier's; these in --full and CI
@ONE_NVCC_WORKER
@pytest.mark.parametrize("variant", BUILD_VARIANTS, ids=variant_id)
def test_multistep_kernel_compiles_for_sm80_and_fits_a_block_of_1024(nvcc_builds, variant):
    report, ptx = nvcc_builds[variant]
    body = entry(ptx, launch.STEPS_KERNEL)
    strict, generic, normals = variant
    # two state buffers (swap: in place), the normal buffer when asked for, the step count, the
    # scene if generic
    assert body[: body.index(")")].count(".param") == 2 + normals + 1 + scene_parameters(generic)
    assert "bar.sync" in body and ".shared" in ptx  # __syncthreads() and the dynamic shared state
    if strict:
        assert "fma." not in body and ".approx" not in body and ".ftz" not in body
    steps_report = report[report.index("entry function 'verlet_steps'") :]
    registers = int(steps_report.split("Used ", 1)[1].split(" registers", 1)[0])
    assert registers <= 64, f"{registers} registers: a block of 1024 threads could not launch"
    assert "0 bytes spill stores, 0 bytes spill loads" in steps_report


# --- 2. the CPU build: barriers, bit-exactness ------------------------------------------


@pytest.mark.parametrize("k", launch.STEPS_PER_LAUNCH)
@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("name", SCENES)
def test_multistep_strict_equals_numpy_after_1_37_and_500_steps(name, n, k):
    scene = SCENES[name](n)
    pp = start(multistep(scene, k), scene)
    done = 0
    for steps in CHECKPOINTS:
        pp.advance(steps - done)
        done = steps
        for got, want, what in zip(pp.read(), reference(scene, VERLET, steps, "f32"), ("pos", "prev")):
            assert_bit_exact(got, want, f"{what} after {steps} steps, {name}, n={n}, K={k}")
    # ceil(steps / K) launches for each advance: the remainder is one launch of its own
    expected = sum(len(launch_sizes(k, b - a)) for a, b in zip((0, *CHECKPOINTS), CHECKPOINTS))
    assert pp.runtime.launches == expected
    assert set(pp.runtime.shared_bytes) == {24 * n * n}


def launch_sizes(k: int, steps: int) -> list[int]:
    return [k] * (steps // k) + [steps % k] * (steps % k > 0)


def test_advance_makes_full_launches_then_the_remainder():
    scene = sphere(32)
    pp = multistep(scene, 16)
    assert pp.launches(37) == [16, 16, 5] and pp.launches(32) == [16, 16] and pp.launches(3) == [3]
    assert [int(a[2]) for a in map(pp.args, (16, 5))] == [16, 5]  # the step count follows the buffers
    assert (pp.grid, pp.block, pp.shared_bytes) == (1, 1024, 24 * 32 * 32)


@pytest.mark.parametrize("transfer", launch.TRANSFERS)
def test_advance_in_pieces_equals_one_call(transfer):
    scene = every_collider_scene(32)
    pieces = (1, 15, 16, 17, 64, 3, 100)
    whole = start(multistep(scene, 16, transfer=transfer), scene)
    whole.advance(sum(pieces))
    split = start(multistep(scene, 16, transfer=transfer), scene)
    for steps in pieces:
        split.advance(steps)
    for a, b, what in zip(whole.read(), split.read(), ("pos", "prev")):
        assert_bit_exact(a, b, f"{what}, {transfer}")
    assert whole.runtime.launches == 14 and split.runtime.launches == sum(len(launch_sizes(16, s)) for s in pieces)


def test_copy_transfer_copies_both_buffers_after_every_launch():
    # the chapter's cudaMemcpy(in, out, DeviceToDevice), once a launch, not once a step
    scene = sphere(32)
    pp = start(multistep(scene, 16, transfer="copy"), scene)
    copies = []
    copy = pp.runtime.copy
    pp.runtime.copy = lambda dst, src: (copies.append(1), copy(dst, src))
    inputs = (pp.pos_in, pp.prev_in)
    pp.advance(40)
    assert len(copies) == 2 * 3 and (pp.pos_in, pp.prev_in) == inputs  # the buffers stay put
    assert_bit_exact(pp.read()[0], reference(scene, VERLET, 40, "f32")[0], "pos, copy")


@pytest.mark.parametrize("block", [32, 100, 1024])
def test_any_block_size_takes_the_whole_grid(block):
    # 64 x 64 = 4096 particles: 128, 41 (the last thread 36) or 4 per thread
    scene = every_collider_scene(64)
    pp = start(multistep(scene, 16, block=block), scene)
    pp.advance(60)
    assert_bit_exact(pp.read()[0], reference(scene, VERLET, 60, "f32")[0], f"pos, {block} threads")


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_result_does_not_depend_on_the_order_threads_run_in(seed):
    # the shim runs the threads between two barriers one at a time; on a GPU they run at once
    # and in any order. Shuffled orders give the same bits: no thread reads, within a step,
    # what another writes in it. Small blocks: several particles a thread, many orders.
    scene = every_collider_scene(32)
    in_order = start(multistep(scene, 16, block=64), scene)
    in_order.runtime.schedule(0)
    in_order.advance(50)
    shuffled = start(multistep(scene, 16, block=64), scene)
    shuffled.runtime.schedule(seed)
    try:
        shuffled.advance(50)
    finally:
        shuffled.runtime.schedule(0)
    assert_bit_exact(shuffled.read()[0], in_order.read()[0], f"pos, schedule {seed}")


@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
def test_multistep_normals_are_those_of_the_last_step_read(generic):
    scene = sphere(32)
    pp = start(multistep(scene, 16, generic=generic, normals=True), scene)
    assert pp.read_normals() is None
    pp.advance(250)  # draped over the sphere: far from flat
    pos, prev = pp.read()
    assert_bit_exact(pos, reference(scene, VERLET, 250, "f32")[0], "pos with normals")
    normals = pp.read_normals()
    assert_bit_exact(normals[:, :3], grid_normals(prev, 32, np.float32), "normals of prev")
    assert np.all(normals[:, 3] == 0)


@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
def test_fast_multistep_equals_fast_per_step_on_the_cpu_build(generic):
    # both kernels call verlet_particle, so on the CPU (no contraction) the fast arithmetic is
    # the same too; on a GPU --use_fast_math may contract them differently (docs/cuda.md)
    scene = every_collider_scene(32)
    steps = start(multistep(scene, 16, strict=False, generic=generic), scene)
    lib = cpu.build(False, cuda.kernel_defines(scene, VERLET, False, generic))
    one = start(PingPong(cpu.ShimRuntime(lib), scene, VERLET, generic=generic), scene)
    steps.advance(120)
    one.advance(120)
    assert_bit_exact(steps.read()[0], one.read()[0], "pos, fast")
    assert not np.array_equal(steps.read()[0], reference(scene, VERLET, 120, "f32")[0])  # fast ran


def test_the_shim_refuses_more_shared_memory_than_it_holds():
    # and only the kernel with barriers runs its threads as fibers (has a schedule)
    scene = sphere(8)
    needs_gxx()
    lib = cpu.build(True, cuda.kernel_defines(scene, VERLET))
    assert not hasattr(lib, "verlet_step_schedule") and hasattr(lib, "verlet_steps_schedule")
    runtime = cpu.ShimRuntime(lib, "verlet_steps")
    pp = start(PingPong(runtime, scene, VERLET, block=64, steps_per_launch=4), scene)
    with pytest.raises(RuntimeError, match="more dynamic shared memory"):
        runtime.launch(1, 64, pp.args(4), 256 * 1024 + 4)


TOY_KERNELS = r"""
extern __shared__ float scratch[];

// each thread writes its slot, waits, reads its neighbour's: the same in any order
__global__ void rotate(float* out)
{
    const unsigned t = threadIdx.x;
    scratch[t] = float(t);
    __syncthreads();
    out[t] = scratch[(t + 1) % blockDim.x];
}

// the same without the barrier: a race, whose result depends on the order threads run in
__global__ void rotate_racy(float* out)
{
    const unsigned t = threadIdx.x;
    scratch[t] = float(t);
    out[t] = scratch[(t + 1) % blockDim.x];
}

// half the threads return before the barrier the others wait at
__global__ void divergent(float* out)
{
    if (threadIdx.x % 2) return;
    __syncthreads();
    out[threadIdx.x] = 1.0f;
}

__global__ void rotate_plain(float* out) { rotate(out); }

CUDA_SHIM_DYNAMIC_SHARED(float, scratch)
CUDA_SHIM_EXPORT_WITH_BARRIERS(rotate)
CUDA_SHIM_EXPORT_WITH_BARRIERS(rotate_racy)
CUDA_SHIM_EXPORT_WITH_BARRIERS(divergent)
CUDA_SHIM_EXPORT(rotate_plain)
"""


@pytest.fixture(scope="module")
def toy_shim(tmp_path_factory):
    """name -> (out after a launch of 64 threads with 256 bytes of shared memory, status),
    for the toy kernels above built with shim.h; schedule(name, seed) sets the order."""
    needs_gxx()
    folder = tmp_path_factory.mktemp("toy_shim")
    (folder / "toy.cpp").write_text(TOY_KERNELS)
    cmd = [cpu.gxx(), *cpu.GXX_FLAGS, "-fPIC", "-shared", "-include", str(cpu.SHIM / "shim.h"),
           str(folder / "toy.cpp"), "-o", str(folder / "toy.so")]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr
    lib = ctypes.CDLL(str(folder / "toy.so"))

    def run(name: str, seed: int = 0):
        if hasattr(lib, f"{name}_schedule"):
            getattr(lib, f"{name}_schedule").argtypes = [ctypes.c_ulonglong]
            getattr(lib, f"{name}_schedule")(seed)
        out = np.zeros(64, np.float32)
        params = (ctypes.c_void_p * 1)(ctypes.cast(ctypes.pointer(ctypes.c_void_p(out.ctypes.data)), ctypes.c_void_p))
        launch_fn = getattr(lib, f"{name}_launch")
        launch_fn.argtypes = [
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.POINTER(ctypes.c_void_p),
            ctypes.c_int,
        ]
        return out, launch_fn(1, 64, 64 * 4, params, 1)

    return run


def test_shim_barriers_hold_in_every_order_and_shuffling_exposes_a_race(toy_shim):
    want = np.float32((np.arange(64) + 1) % 64)
    for seed in (0, 1, 2):
        out, status = toy_shim("rotate", seed)
        assert status == 0 and np.array_equal(out, want), f"schedule {seed}"
    # without the barrier the result depends on the order (in order, a thread reads its
    # neighbour's slot before the neighbour wrote it: the NaN the shim fills shared memory with)
    racy = [toy_shim("rotate_racy", seed)[0] for seed in (0, 1)]
    assert np.isnan(racy[0][:63]).all() and racy[0][63] == 0
    assert not np.array_equal(racy[0], racy[1], equal_nan=True)


def test_shim_reports_barriers_it_cannot_honour(toy_shim):
    assert toy_shim("divergent")[1] == -3  # a barrier some threads never reach
    assert toy_shim("rotate_plain")[1] == -2  # a barrier where threads are not fibers
    assert cpu.STATUS[-3].startswith("a barrier that some") and cpu.STATUS[-2].startswith("__syncthreads()")


# --- 3. the kernel shapes, through CudaBackend ----------------------------------------


def test_shapes_offer_the_multistep_kernel_where_the_grid_fits():
    floor = launch.SMALLEST_SHARED_OPTIN
    assert launch.kernel_shapes(64 * 64, None, floor) == (
        "block=256",
        "block=64",
        "block=128",
        "block=512",
        "steps/launch=16",
        "steps/launch=64",
    )
    assert launch.kernel_shapes(65 * 65, None, floor) == ("block=256", "block=64", "block=128", "block=512")
    assert "steps/launch=16" in launch.kernel_shapes(98 * 98, None, 227 * 1024)  # sm_90's limit
    assert "steps/launch=16" not in launch.kernel_shapes(99 * 99, None, 227 * 1024)
    assert launch.kernel_shapes(32 * 32, 100, floor) == ("block=100", "steps/launch=16", "steps/launch=64")
    assert launch.kernel_shapes(32 * 32, 2048, floor) == ("block=2048",)
    assert launch.parse_shape("steps/launch=16", 20 * 20) == (16, 416)  # whole warps
    assert launch.parse_shape("block=64", 20 * 20) == (None, 64)
    with pytest.raises(ClothbenchError, match="block=N or steps/launch=K"):
        launch.parse_shape("wg=8x8", 400)


SHAPE_SCENES = {"sphere": sphere, "drape": lambda n: load_scene("drape").replace(grid=n)}


@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("name", SHAPE_SCENES)
def test_every_shape_runs_strict_bit_exact(cuda_on_cpu, name, n):  # noqa: F811
    scene = SHAPE_SCENES[name](n)
    shapes = cuda.CudaBackend.kernel_shapes(scene, BackendOptions(strict=True))
    assert len(shapes) == 6  # 4 block sizes and 2 multi-step counts: 64 x 64 fits everywhere
    want1, want500 = reference(scene, VERLET, 1, "f32"), reference(scene, VERLET, 500, "f32")
    for shape in shapes:
        backend, runtime = cuda_on_cpu(scene, strict=True, shape=shape)
        with backend:
            assert backend.mode.endswith(f"/{shape}") and backend.shape == shape
            backend.upload(*VERLET.initial_state(scene, np.float32))
            backend.advance(1)
            assert_bit_exact(backend.read()[0], want1[0], f"pos after 1 step, {shape}")
            backend.advance(499)
            pos, prev = backend.read()
        assert_bit_exact(pos, want500[0], f"pos after 500 steps, {shape}")
        assert_bit_exact(prev, want500[1], f"prev after 500 steps, {shape}")
        k = launch.parse_shape(shape, scene.particles)[0]
        assert runtime.launches == (500 if k is None else 1 + len(launch_sizes(k, 499)))


def test_backend_names_its_shape_driver_and_refuses_an_unknown_shape(cuda_on_cpu):  # noqa: F811
    backend, runtime = cuda_on_cpu(sphere(32), strict=True, shape="steps/launch=16")
    assert backend.mode == "strict/swap/ls=1024/steps/launch=16"
    # driver, the CuPy build and its CUDA runtime, the compiler (here the stand-in's), the module
    driver = backend.driver.split(", ")
    assert driver[0] == "CUDA driver 13.0" and "CUDA 13.0 runtime" in driver, backend.driver
    assert driver[-1] == "CPU build of verlet_cloth.cu", backend.driver
    assert runtime.signature == "ppi"
    backend, _ = cuda_on_cpu(sphere(32), shape="steps/launch=64", local_size=128)
    assert backend.mode == "fast/swap/ls=128/steps/launch=64"
    with pytest.raises(
        ClothbenchError, match=r"cuda has no kernel shape 'steps/launch=16' for this scene \(it has: block=256, "
    ):
        cuda_on_cpu(sphere(80), shape="steps/launch=16")  # 80 x 80 needs 150 KiB: not on every device


def test_tuning_times_every_shape_and_remembers_the_fastest(cuda_on_cpu, monkeypatch, tmp_path):  # noqa: F811
    # the stand-in's events are the CPU's clock: which shape wins means nothing here, only that
    # every one was timed, the fastest kept and read back, and the winner still exact
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    scene = sphere(16)
    backend, runtime = cuda_on_cpu(scene, strict=True)
    entry = next(iter(json.loads((tmp_path / "tuning" / "cuda.json").read_text()).values()))
    assert set(entry["ms"]) == set(cuda.CudaBackend.kernel_shapes(scene, BackendOptions()))
    assert backend.shape == entry["choice"] == min(entry["ms"], key=entry["ms"].get)
    assert runtime.launches > 0  # the chosen kernel was timed, on buffers of its own
    with backend:
        backend.upload(*VERLET.initial_state(scene, np.float32))
        backend.advance(100)
        assert_bit_exact(backend.read()[0], reference(scene, VERLET, 100, "f32")[0], f"pos, {backend.shape}")
    again, again_runtime = cuda_on_cpu(scene, strict=True)
    assert again.shape == backend.shape and again_runtime.launches == 0  # read back, not timed


def test_an_edit_to_the_kernel_or_a_file_it_includes_is_a_new_tuning_key(cuda_on_cpu, monkeypatch):  # noqa: F811
    # a block size was measured on verlet_cloth.cu and what it includes: an edit to any of them
    # must measure again (the key named no kernel text before 2026-12-06; VBD's always did)
    from clothbench import kernel_source

    backend, _ = cuda_on_cpu(sphere(16))
    before = backend._tuning_key()
    assert backend._tuning_key() == before
    original = kernel_source.read_kernel
    for name in ("verlet_cloth.cu", "collide.cuh", "self_collision.cuh"):
        monkeypatch.setattr(
            kernel_source, "read_kernel", lambda n, name=name: original(n) + ("//\n" if n == name else "")
        )
        assert backend._tuning_key()["kernel"] != before["kernel"], name


# --- 4. on a CUDA device (skipped without one) -----------------------------------------


def test_gpu_tuning_times_every_shape_with_events(monkeypatch, tmp_path):
    require("cuda")
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    scene = every_collider_scene(32)
    with create_backend("cuda", scene, VERLET, BackendOptions(strict=True, retune=True)) as backend:
        entry = next(iter(json.loads((tmp_path / "tuning" / "cuda.json").read_text()).values()))
        assert backend.shape == entry["choice"] and backend.mode.endswith(backend.shape)
        assert set(entry["ms"]) | set(entry["failed"]) == set(backend.kernel_shapes(scene, backend.options))
        assert all(ms > 0 for ms in entry["ms"].values())
        assert backend.driver.startswith("CUDA driver ") and backend.device in backend.driver


@pytest.mark.parametrize("shape", ["steps/launch=16", "steps/launch=64"])
def test_gpu_fast_multistep_is_as_accurate_as_float32(shape):
    require("cuda")
    scene = sphere(64)
    pos, _ = simulate("cuda", scene, VERLET, SPHERE_STEPS, BackendOptions(shape=shape))
    assert_as_accurate_as_float32(pos, scene, SPHERE_STEPS)
