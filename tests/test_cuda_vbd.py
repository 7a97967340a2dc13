"""The CUDA VBD solver (kernels/vbd_cloth.cu, clothbench/backends/cuda/vbd.py), proved as far
as a machine without a GPU can prove it (docs/cuda.md, "VBD"):

1. nvcc -ptx compiles the kernel for sm_80 and sm_90, strict and fast, for a scene of every
   collider kind, a mesh scene and a moving one, without a warning; strict PTX has no FMA and
   no approximation; a scene compiles only the collider code it has, and a Verlet build
   compiles none of the VBD kernel.
2. The CPU build (cuda/shim) driven by VbdLaunches, the backend's own launch list, is the
   NumPy float32 reference bit for bit with meshes (either search), moving colliders, pins
   attached to a body (one row set per substep, across windows of them), boxes, substeps and
   Chebyshev (fast within 8x NumPy float32's own error is the contract's, which runs this
   build too).
3. CudaVbdBackend itself over tests/test_cuda.py's stand-in cupy: mode, block size, refusals.
(The contract, tests/contract/test_vbd_contract.py, runs CUDA through the same stand-in.)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import shutil
import subprocess

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.errors import ClothbenchError
from clothbench.backends.cuda import cpu, launch, vbd
from clothbench.backends.cuda import verlet as cuda
from clothbench.backends.tuning import TUNING_ROUNDS
from clothbench.harness import reference
from clothbench.kernel_source import kernel_path, read_kernel, resolve_includes
from clothbench.model.scene import load_scene, load_setup
from clothbench.model.solver import Vbd

from conftest import BOX_SCENE, VERLET, assert_bit_exact, every_kind
from test_cuda import cuda_on_cpu, shim_library  # noqa: F401  (fixtures: the stand-in cupy)
from test_opencl_vbd import N, scene_of  # built-in scenes at 16^2, as the OpenCL VBD tests take them

KERNEL = kernel_path(vbd.KERNEL_FILE)
# 5 substeps: 60 steps are 300 row sets of a moving scene; the window is made 128 below, so
# they cross it; the torus is touched from about 0.14 s, the paddle sweeps 90 degrees in 1 s
SUBSTEPS = 5
STEPS = {"torus": 30, "sweep": 60, "carried": 60}
ARCHS = ("sm_80", "sm_90")


def boxes_scene():
    """The contract's boxes (tests/data/boxes.toml): a fixed rotated box and a moving one."""
    return load_scene(str(BOX_SCENE))


def all_kinds(n: int = N):
    """every_kind with the contract's two boxes held still: every collider kind, fixed."""
    return every_kind(n).replace(boxes=tuple(dataclasses.replace(b, motion=None) for b in boxes_scene().boxes))


@functools.lru_cache(maxsize=None)
def launches_on_cpu(scene, solver, strict=True, mesh_collision=None, block=launch.AUTO_BLOCK):
    """VbdLaunches on the CPU build of vbd_cloth.cu for exactly this scene."""
    lib = cpu.build(strict, vbd.vbd_defines(scene, mesh_collision), vbd.KERNEL_FILE)
    return vbd.VbdLaunches({k: cpu.ShimRuntime(lib, k) for k in vbd.kernels_of(scene)}, scene, solver, block)


def run_on_cpu(scene, solver, steps, **options):
    state = launches_on_cpu(scene, solver, **options)
    state.upload(*solver.initial_state(scene, np.float32))
    state.advance(steps)
    return state.read()


# --- 1. nvcc -ptx --------------------------------------------------------------------


def nvcc_ptx(scene, strict: bool, arch: str, tmp_path) -> str:
    if shutil.which("nvcc") is None:
        pytest.skip("nvcc not found on PATH (CUDA toolkit not installed)")
    out = tmp_path / f"vbd-{arch}-{strict}.ptx"
    defines = [cuda._nvcc_escaped(d) for d in vbd.vbd_defines(scene)]
    cmd = ["nvcc", "-ptx", f"-arch={arch}", *cuda.compile_options(strict), *defines,
           "-Werror", "all-warnings", "-o", str(out), str(KERNEL)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and not done.stderr.strip(), done.stderr
    return out.read_text()


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("mode", ["strict", "fast"])
def test_kernel_compiles_to_ptx_without_warnings(tmp_path, arch, mode):
    ptx = nvcc_ptx(all_kinds(), mode == "strict", arch, tmp_path)
    for name in vbd.KERNELS:
        assert f".entry {name}(" in ptx  # extern "C": the names the host looks up
    if mode == "strict":  # every operation rounded on its own, correctly, denormals kept
        assert "fma." not in ptx and "rsqrt" not in ptx and ".approx" not in ptx and ".ftz" not in ptx
        assert "sqrt.rn.f32" in ptx and "div.rn.f32" in ptx
    else:
        assert "rsqrt.approx" in ptx


@pytest.mark.parametrize("name", ["torus", "sweep", "carried"])
def test_bodies_compile_to_strict_ptx(tmp_path, name):
    ptx = nvcc_ptx(scene_of(name), True, ARCHS[0], tmp_path)
    assert "fma." not in ptx and ".entry vbd_collide(" in ptx


def test_a_scene_compiles_only_the_collider_code_it_has():
    def preprocessed(scene):
        cmd = ["g++", "-E", "-P", "-x", "c++", *vbd.vbd_defines(scene), str(KERNEL)]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=True).stdout

    every = preprocessed(all_kinds())
    assert all(f"collide_{kind}(" in every for kind in ("sphere", "cylinder", "box", "plane"))
    drape = preprocessed(load_setup("drape").scene.replace(grid=N))
    assert not any(f"collide_{kind}(" in drape for kind in ("sphere", "cylinder", "box", "plane", "mesh"))


def test_a_verlet_build_compiles_none_of_vbd():
    # the Verlet module's sources are verlet_cloth.cu and the collider headers, never vbd_cloth.cu
    files = resolve_includes(cuda.KERNEL_FILE, read_kernel(cuda.KERNEL_FILE), lambda *_: "")[1]
    assert vbd.KERNEL_FILE not in files and "collide.cuh" in files


def test_the_vbd_kernel_has_no_generic_build():
    cmd = ["g++", "-fsyntax-only", "-x", "c++", "-DCLOTH_GENERIC", str(KERNEL)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode != 0 and "vbd_cloth.cu has no generic build" in done.stderr


# --- 2. the CPU build, through VbdLaunches ------------------------------------------------


# a mesh with either search; a moving mesh and pins on a moving bar with the default one
# (the moving mesh in the quick tier; the torus's two searches and the carried pins, each a few
# hundred substeps of NumPy's VBD to compare with, in --full)
FULL = pytest.mark.full
BODY_CASES = [
    pytest.param("torus", "naive", marks=FULL),
    pytest.param("torus", "accelerated", marks=FULL),
    ("sweep", None),
    pytest.param("carried", None, marks=FULL),
]


@pytest.mark.parametrize("name, algorithm", BODY_CASES)
def test_strict_vbd_with_bodies_matches_numpy_f32_bit_for_bit(name, algorithm, monkeypatch):
    monkeypatch.setattr(launch, "MOTION_WINDOW", 128)  # 300 substeps cross two windows
    scene, solver = scene_of(name), Vbd(dt=1 / 60, substeps=SUBSTEPS, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, STEPS[name], "f32")
    launches_on_cpu.cache_clear()  # a fresh window of the size set above
    pos, prev = run_on_cpu(scene, solver, STEPS[name], mesh_collision=algorithm)
    assert_bit_exact(pos, ref_pos, f"pos, {name} {algorithm}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} {algorithm}")
    if scene.meshes:  # and the mesh was touched: without it the sheet ends elsewhere
        free = reference(scene.replace(meshes=()), solver, STEPS[name], "f32")[0]
        assert not np.array_equal(free, pos), f"{name}: the cloth never reached the mesh"


def test_strict_vbd_with_boxes_and_every_kind_matches_numpy_f32_bit_for_bit():
    solver = Vbd(dt=1 / 60, substeps=2, iterations=6)
    for scene in (boxes_scene().replace(grid=N), all_kinds()):
        ref_pos, ref_prev = reference(scene, solver, 60, "f32")
        pos, prev = run_on_cpu(scene, solver, 60)
        assert_bit_exact(pos, ref_pos, f"pos, {scene.name}")
        assert_bit_exact(prev, ref_prev, f"prev, {scene.name}")


def test_advance_in_pieces_and_a_second_upload_equal_one_run():
    scene, solver = scene_of("sweep"), Vbd(dt=1 / 60, substeps=2)
    whole = run_on_cpu(scene, solver, 20)[0]
    state = launches_on_cpu(scene, solver)
    for _ in range(2):  # the upload starts the motion again at t = 0
        state.upload(*solver.initial_state(scene, np.float32))
        for steps in (1, 7, 12):
            state.advance(steps)
        assert_bit_exact(state.read()[0], whole, "pos, in pieces")


@pytest.mark.parametrize("block", [7, 1024])
def test_block_size_changes_no_strict_bit(block):
    # 7 divides neither n*n nor a colour's count: the last block runs past and its extra threads return
    scene, solver = every_kind(13), Vbd(dt=1 / 60)
    assert_bit_exact(run_on_cpu(scene, solver, 30, block=block)[0], reference(scene, solver, 30, "f32")[0])


# --- 3. CudaVbdBackend over the stand-in cupy ---------------------------------------------


def test_cuda_vbd_backend_runs_the_cpu_build_of_its_own_kernel(cuda_on_cpu):  # noqa: F811
    compiled = cuda_on_cpu.install()
    scene, solver = all_kinds(), Vbd(dt=1 / 60, chebyshev_rho=0.9)
    with vbd.CudaVbdBackend(scene, solver, BackendOptions(strict=True, local_size=64)) as backend:
        assert compiled[-1] == (True, vbd.vbd_defines(scene))
        assert backend.mode == "strict/vbd/ls=64/block=64"  # --local-size: that one shape, untuned
        assert backend.device_timer == "cuda-events"
        backend.upload(*solver.initial_state(scene, np.float32))
        backend.advance(40)
        backend.synchronize()
        pos, prev = backend.read()
        assert backend.device_elapsed_ms() > 0
    ref_pos, ref_prev = reference(scene, solver, 40, "f32")
    assert_bit_exact(pos, ref_pos, "pos")
    assert_bit_exact(prev, ref_prev, "prev")
    with vbd.CudaVbdBackend(scene, solver, BackendOptions()) as backend:  # the defaults: fast, 256 a block
        b = launch.AUTO_BLOCK
        assert backend.mode == f"fast/vbd/ls={b}/block={b}" and backend.state.block == b
    with vbd.CudaVbdBackend(scene, solver, BackendOptions(shape="block=128")) as backend:  # a shape named
        assert backend.mode == "fast/vbd/ls=128/block=128" and backend.state.block == 128


@pytest.mark.parametrize(
    "options, message",
    [
        ({"generic": True}, "cuda does not take --generic"),
        ({"normals": True}, "cuda does not take --save-normals"),
        ({"transfer": "copy"}, "cuda does not take --transfer copy"),
        ({"shape": "block=100"}, "cuda has no kernel shape 'block=100' for this scene"),
        ({"shape": "steps/launch=32"}, "cuda has no kernel shape 'steps/launch=32'"),  # Verlet's only
        ({"local_size": 2048}, r"cuda --local-size must be 1 \.\. 1024 here, got 2048"),
    ],
)
def test_cuda_vbd_refuses_what_it_does_not_take_in_one_line(cuda_on_cpu, options, message):  # noqa: F811
    cuda_on_cpu.install()
    with pytest.raises(ClothbenchError, match=message):
        create_backend("cuda", every_kind(8), Vbd(dt=1 / 60), BackendOptions(**options)).close()


def test_the_verlet_class_is_unchanged_by_vbd(cuda_on_cpu):  # noqa: F811
    # the registry still builds the Verlet class for a Verlet solver, with its own kernel
    backend, runtime = cuda_on_cpu(every_kind(8), strict=True)
    with backend:
        assert type(backend) is cuda.CudaBackend and runtime.kernel == launch.STEP_KERNEL
        assert backend.defines == cuda.kernel_defines(every_kind(8), VERLET)


def test_the_tuned_block_is_kept_under_vbd_s_own_key(cuda_on_cpu, monkeypatch, tmp_path):  # noqa: F811
    # the fastest block wins and is read back without measuring; a Verlet choice for the same
    # scene, and VBD's with other sweeps, are other keys of cuda's one tuning file
    cuda_on_cpu.install()
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    timed: list[str] = []

    def fake(backend, shape):  # block=128 is the fastest, for either solver
        timed.append(shape)
        return 1e-4 if shape == "block=128" else 2e-4

    monkeypatch.setattr(cuda.CudaDevice, "_time_shape", fake)
    scene = every_kind(8)
    for solver in (Vbd(dt=1 / 60), Vbd(dt=1 / 60), Vbd(dt=1 / 60, iterations=20), VERLET):
        with create_backend("cuda", scene, solver, BackendOptions()) as b:
            assert b.shape == "block=128" and b.effective_local_size == 128, b.mode
    vbd_blocks = len(vbd.CudaVbdBackend.kernel_shapes(scene, BackendOptions()))
    verlet_shapes = len(cuda.CudaBackend.kernel_shapes(scene, BackendOptions()))
    assert len(timed) == TUNING_ROUNDS * (2 * vbd_blocks + verlet_shapes)  # the second Vbd read the first's
    keys = [json.loads(k) for k in json.loads((tmp_path / "tuning" / "cuda.json").read_text())]
    assert sorted(k.get("solver", "verlet") for k in keys) == ["vbd", "vbd", "verlet"]
