"""Triangle meshes, moving colliders and pins attached to a body in the CUDA backend, proved
without a GPU the way tests/test_cuda.py proves the rest of it (docs/cuda.md, "Meshes and motion").

1. nvcc compiles kernels/verlet_cloth.cu with kernels/collide_mesh.cuh for sm_80, for a mesh
   scene (both algorithms) and for moving scenes, strict and fast, specialised and generic,
   without a warning; strict PTX has no fused multiply-add.
2. A build holds only what its scene needs: no mesh code without meshes, no motion code
   without motion, no BVH traversal in the naive build.
3. The same source on the CPU (shim.h), driven by PingPong, equals the NumPy float32 reference
   bit for bit (tolerance 0: strict performs the reference's operations in its order) after
   500 steps of `torus` (naive and accelerated), `sweep` (a rotating paddle) and `carried`
   (pins on a moving bar), in both kernels, and on hand-placed particles in every branch.
4. CudaBackend itself over the stand-in cupy of tests/test_cuda.py: capabilities, mode,
   shapes, the clock of the motion.
On a CUDA device the contract (tests/contract/test_bodies_contract.py) holds CudaBackend
itself to NumPy's bits after contact with either search, in every shape and build, and its
fast mode to float32's error.
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
from clothbench.model.kernel_inputs import pin_targets
from clothbench.model.colliders.mesh import Mesh
from clothbench.model.colliders.motion import Motion
from clothbench.harness import reference
from clothbench.kernel_source import kernel_path
from clothbench.model.scene import Scene, load_scene

from conftest import VERLET, assert_bit_exact, sphere
from test_cuda import assert_as_accurate_as_float32
from test_cuda import ONE_NVCC_WORKER, cuda_on_cpu, shim_library  # noqa: F401  (fixtures: the stand-in cupy)

KERNEL = kernel_path(cuda.KERNEL_FILE)
N = 32  # the contract's grid: the torus holds particles within 500 steps
STEPS = 500
ALGORITHMS = ("accelerated", "naive")
BUILDS = {"specialised": False, "generic": True}
# the paddle of `sweep` first touches the 32 x 32 curtain at step 869, the sphere of `carried`
# is reached after 500: the moving scenes are checked at 500 steps and again at 1000
MOVING_CHECKPOINTS = (500, 1000)


def scene_named(name: str, n: int = N) -> Scene:
    return load_scene(name).replace(grid=n)


def pingpong(scene, strict=True, generic=False, algorithm="accelerated", steps_per_launch=None, **options):
    """A PingPong on the CPU build of this scene: verlet_step, or verlet_steps with
    steps_per_launch steps a launch in one block."""
    if cpu.gxx() is None:
        pytest.skip("g++ not found: cannot build the CPU shim of the CUDA kernel")
    transfer = options.get("transfer", launch.TRANSFERS[0])  # the build's, as the backend's
    lib = cpu.build(strict, cuda.kernel_defines(scene, VERLET, False, generic, algorithm, transfer))
    if steps_per_launch is None:
        return PingPong(cpu.ShimRuntime(lib), scene, VERLET, generic=generic, **options)
    return PingPong(
        cpu.ShimRuntime(lib, launch.STEPS_KERNEL),
        scene,
        VERLET,
        generic=generic,
        block=launch.multistep_threads(scene.particles),
        steps_per_launch=steps_per_launch,
        **options,
    )


def run(pp: PingPong, scene: Scene, checkpoints=(STEPS,)):
    """Upload the initial state, then yield (steps, pos, prev) at each checkpoint."""
    pp.upload(*VERLET.initial_state(scene, np.float32))
    done = 0
    for steps in checkpoints:
        pp.advance(steps - done)
        done = steps
        yield (steps, *pp.read())


def assert_matches_reference(pp, scene, checkpoints, what):
    for steps, pos, prev in run(pp, scene, checkpoints):
        ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
        assert_bit_exact(pos, ref_pos, f"pos after {steps} steps, {what}")
        assert_bit_exact(prev, ref_prev, f"prev after {steps} steps, {what}")


# --- 1. nvcc ---------------------------------------------------------------------------

# (scene, strict, generic, algorithm): the mesh scene both ways, the moving scenes with the
# default algorithm (sweep's paddle is a mesh; carried has no mesh)
NVCC_VARIANTS = [
    *(
        (name, strict, generic, algorithm)
        for name in ("torus",)
        for algorithm in ALGORITHMS
        for strict in (True, False)
        for generic in (False, True)
    ),
    *(
        (name, strict, generic, "accelerated")
        for name in ("sweep", "carried")
        for strict in (True, False)
        for generic in (False, True)
    ),
]


def nvcc_id(v) -> str:
    name, strict, generic, algorithm = v
    return f"{name}-{'strict' if strict else 'fast'}-{'generic' if generic else 'specialised'}-{algorithm}"


@pytest.fixture(scope="module")
def nvcc_ptx(tmp_path_factory):
    """variant -> (nvcc's process, PTX): nvcc -ptx -arch=sm_80 with the backend's options."""
    if shutil.which("nvcc") is None:
        pytest.skip("nvcc not found on PATH (CUDA toolkit not installed)")
    folder = tmp_path_factory.mktemp("nvcc_meshes")
    out = {}
    for v in NVCC_VARIANTS:
        name, strict, generic, algorithm = v
        defines = [
            cuda._nvcc_escaped(d) for d in cuda.kernel_defines(scene_named(name), VERLET, False, generic, algorithm)
        ]
        ptx = folder / f"{nvcc_id(v)}.ptx"
        cmd = ["nvcc", "-ptx", "-arch=sm_80", *cuda.compile_options(strict), *defines,
               "-Werror", "all-warnings", "-o", str(ptx), str(KERNEL)]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        out[v] = done, ptx.read_text() if ptx.exists() else ""
    return out


def parameters(ptx: str, entry: str) -> int:
    head = ptx[ptx.index(f".entry {entry}(") :]
    return head[: head.index(")")].count(".param")


# buffers a launch adds for the scene, after the two state buffers (swap, the default: in
# place; copy's two pairs are four): the mesh rows and ints,
# the step table, the pin slots (generic: also the counts and the table's row count)
EXTRA_BUFFERS = {"torus": 2, "sweep": 2 + 1, "carried": 1 + 1}


@pytest.mark.full  # nvcc builds: test_cuda.py's PTX tests are the quick tier's; these in --full and CI
@ONE_NVCC_WORKER
@pytest.mark.parametrize("variant", NVCC_VARIANTS, ids=nvcc_id)
def test_mesh_and_moving_kernels_compile_for_sm80_without_warnings(nvcc_ptx, variant):
    done, ptx = nvcc_ptx[variant]
    assert done.returncode == 0 and not (done.stdout + done.stderr).strip(), f"{nvcc_id(variant)}: {done.stderr}"
    name, strict, generic, _ = variant
    if not generic:  # specialised: only buffers, the scene is compiled in
        assert parameters(ptx, launch.STEP_KERNEL) == 2 + EXTRA_BUFFERS[name]
        assert parameters(ptx, launch.STEPS_KERNEL) == 2 + 1 + EXTRA_BUFFERS[name]
    if strict:  # every operation rounded on its own, denormals kept: as NumPy
        assert "fma." not in ptx and ".approx" not in ptx and ".ftz" not in ptx and "rsqrt" not in ptx
        assert "div.rn.f32" in ptx
    else:  # the fast build is another computation, or comparing them measures nothing
        assert "fma.rn" in ptx


# --- 2. what a build holds ---------------------------------------------------------------


def preprocessed(scene: Scene, generic=False, algorithm="accelerated") -> str:
    """The kernel source after the preprocessor, as g++ -E runs the same #if switches (and
    finds collide_mesh.cuh beside the kernel, as nvcc does)."""
    gxx = cpu.gxx() or pytest.skip("g++ not found")
    defines = cuda.kernel_defines(scene, VERLET, False, generic, algorithm)
    done = subprocess.run(
        [gxx, "-E", "-P", "-x", "c++", *defines, str(KERNEL)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


MESH_CODE = ("collide_mesh", "closest_point", "mesh_rows", "mesh_ints")
MOTION_CODE = ("step_rows", "motion", "pin_slot")


@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
def test_a_scene_without_meshes_or_motion_builds_none_of_their_code(generic):
    for scene in (sphere(16), scene_named("drape")):
        source = preprocessed(scene, generic)
        for absent in (*MESH_CODE, *MOTION_CODE):
            assert absent not in source, f"{absent} compiled into a {scene.name} kernel"
        defines = " ".join(cuda.kernel_defines(scene, VERLET, False, generic))
        assert "MESH" not in defines and "MOTION" not in defines and "PIN" not in defines


def test_a_static_mesh_builds_no_motion_and_a_moving_scene_without_meshes_no_mesh_code():
    torus = preprocessed(scene_named("torus"))
    assert all(m in torus for m in MESH_CODE)
    assert not any(m in torus for m in MOTION_CODE), "motion code in a static mesh scene"
    carried = preprocessed(scene_named("carried"))
    assert "step_rows" in carried and "pin_slot" in carried
    assert not any(m in carried for m in MESH_CODE), "mesh code in a scene without meshes"
    # the moving scene's colliders come from the step's table, not from compiled-in rows
    assert "CLOTH_CYLINDERS=" not in " ".join(cuda.kernel_defines(scene_named("carried"), VERLET))


def test_only_the_accelerated_build_holds_the_bvh_traversal():
    accelerated = preprocessed(scene_named("torus"), algorithm="accelerated")
    naive = preprocessed(scene_named("torus"), algorithm="naive")
    assert "stack[" in accelerated and "leaf_tris" in accelerated
    assert "stack[" not in naive and "leaf_tris" not in naive
    with pytest.raises(ValueError, match="mesh_collision must be accelerated or naive"):
        cuda.kernel_defines(scene_named("torus"), VERLET, mesh_collision="grid")


def test_generic_builds_are_one_key_per_kind_of_scene():
    def key(name, algorithm=None):
        return cuda.kernel_defines(scene_named(name), VERLET, generic=True, mesh_collision=algorithm)

    assert key("sphere") == ("-DCLOTH_GENERIC",)  # as before meshes existed
    assert key("torus") == ("-DCLOTH_GENERIC", "-DCLOTH_MESHES", "-DCLOTH_MESH_BVH")
    assert key("torus", "naive") == ("-DCLOTH_GENERIC", "-DCLOTH_MESHES")
    assert key("carried") == ("-DCLOTH_GENERIC", "-DCLOTH_MOTION")
    assert key("sweep") == ("-DCLOTH_GENERIC", "-DCLOTH_MESHES", "-DCLOTH_MESH_BVH", "-DCLOTH_MOTION")


# --- 3. the CPU build, bit for bit ---------------------------------------------------------


@pytest.mark.full  # 500 steps on the CPU shim
@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_strict_torus_equals_numpy_after_500_steps(algorithm, build):
    scene = scene_named("torus")
    assert_matches_reference(
        pingpong(scene, generic=BUILDS[build], algorithm=algorithm), scene, (1, STEPS), f"torus, {algorithm}, {build}"
    )
    # the torus holds the sheet by then: tests/contract/test_bodies_contract.py checks the reference


@pytest.mark.full  # the torus to contact on the CPU shim
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_strict_torus_in_the_multistep_kernel_equals_numpy(algorithm):
    scene = scene_named("torus")
    pp = pingpong(scene, algorithm=algorithm, steps_per_launch=16)
    assert_matches_reference(pp, scene, (37, STEPS), f"torus, verlet_steps, {algorithm}")


@pytest.mark.full  # 1000 steps on the CPU shim
@pytest.mark.parametrize("kernel", ["verlet_step", "verlet_steps"])
@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("name", ["sweep", "carried"])
def test_strict_moving_scenes_equal_numpy_after_500_and_1000_steps(name, build, kernel):
    scene = scene_named(name)
    steps_per_launch = 64 if kernel == "verlet_steps" else None
    pp = pingpong(scene, generic=BUILDS[build], steps_per_launch=steps_per_launch)
    assert_matches_reference(pp, scene, MOVING_CHECKPOINTS, f"{name}, {build}, {kernel}")
    # by the last checkpoint the moving body has changed the sheet (the paddle or the bar's
    # pins): tests/contract/test_bodies_contract.py checks the reference


def test_attached_pins_are_their_targets_at_the_end_of_each_step_exactly():
    scene = scene_named("carried")
    ((_, pos, prev),) = run(pingpong(scene), scene, (STEPS,))
    pinned = scene.pinned()
    assert_bit_exact(pos[pinned, :3], pin_targets(scene, STEPS * VERLET.dt), "pins at t = 500 dt")
    assert_bit_exact(prev[pinned, :3], pin_targets(scene, (STEPS - 1) * VERLET.dt), "pins at t = 499 dt")
    start = VERLET.initial_state(scene, np.float32)[0]
    assert (pos[pinned, 2] > start[pinned, 2] + 0.05).all()  # the bar carried them 7.5 cm in +z
    assert (pos[pinned, 3] == 0).all()  # still pinned: inverse mass 0


@pytest.mark.parametrize("transfer", launch.TRANSFERS)
def test_advance_in_pieces_across_motion_windows_equals_one_call(transfer, monkeypatch):
    # 1000 steps in pieces that end inside, at and past windows of per-step rows made 256 steps
    # long (4096 by default) so that 1000 steps cross three of them
    monkeypatch.setattr(launch, "MOTION_WINDOW", 256)
    scene = scene_named("sweep")
    pieces = (1, 255, 3, 300, 441)
    whole = pingpong(scene, steps_per_launch=16, transfer=transfer)
    ((_, pos, prev),) = run(whole, scene, (sum(pieces),))
    split = pingpong(scene, steps_per_launch=16, transfer=transfer)
    split.upload(*VERLET.initial_state(scene, np.float32))
    assert split.motion.steps == 256
    for steps in pieces:
        split.advance(steps)
    assert split.motion.first > 2 * 256  # the window moved at least three times
    assert_bit_exact(split.read()[0], pos, f"pos, pieces, {transfer}")
    assert_bit_exact(pos, reference(scene, VERLET, sum(pieces), "f32")[0], f"pos, 1000 steps, {transfer}")


def test_upload_starts_the_motion_again_at_t_zero():
    # as the NumPy reference: the uploaded state is at t = 0, whatever ran before
    scene = scene_named("carried")
    pp = pingpong(scene)
    list(run(pp, scene, (300,)))
    assert_matches_reference(pp, scene, (STEPS,), "carried after a second upload")


BOX = Mesh(shape="box", margin=0.05)  # the unit cube around the origin, a 5 cm margin


def placed(scene: Scene, points) -> tuple[np.ndarray, np.ndarray]:
    """Particles at rest at `points` (the rest where the scene puts them), the last pinned."""
    pos, _ = scene.initial_state(np.float64)
    pos[: len(points), :3] = points
    pos[:, 3] = 100.0
    pos[len(points) - 1, 3] = 0.0
    state = pos.astype(np.float32)
    return state, state.copy()


# hand-placed, in the unit box (body frame): every kind of closest feature and ties
BOX_POINTS = [
    (0.0, 0.0, 0.0),     # 0: the centre, as close to all six faces: the lowest triangle wins
    (0.4, 0.1, 0.0),     # 1: inside near the +x face -> (0.55, 0.1, 0)
    (0.5, 0.5, 0.5),     # 2: exactly on a vertex: out along the vertex's pseudo-normal
    (0.5, 0.5, 0.0),     # 3: exactly on an edge: out along the edge's pseudo-normal
    (0.52, 0.0, 0.0),    # 4: outside within the margin -> (0.55, 0, 0)
    (0.6, 0.0, 0.0),     # 5: outside beyond the margin: unchanged
    (0.3, 0.3, 0.3),     # 6: inside, as close to three faces
    (0.45, 0.45, 0.2),   # 7: inside, as close to two faces
    (0.1, 0.2, 0.0),     # 8: inside but pinned: never collided
]  # fmt: skip


def one_step_both(pp: PingPong, scene: Scene, pos, prev):
    pp.upload(pos, prev)
    pp.step()
    with create_backend("numpy", scene, VERLET, BackendOptions(precision="f32")) as b:
        b.upload(pos, prev)
        b.advance(1)
        return pp.read()[0], b.read()[0]


def still(*meshes) -> Scene:
    # no springs, gravity or damping: only the collision moves a particle
    return Scene(grid=3, stiffness=0.0, damping=0.0, gravity=(0, 0, 0), meshes=meshes)


@pytest.mark.parametrize("build", BUILDS)
@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_every_feature_and_tie_of_a_box_matches_numpy(algorithm, build):
    scene = still(BOX)
    pos, prev = placed(scene, BOX_POINTS)
    got, want = one_step_both(pingpong(scene, generic=BUILDS[build], algorithm=algorithm), scene, pos, prev)
    assert_bit_exact(got, want, f"pos, box, {algorithm}, {build}")
    expected = {1: (0.55, 0.1, 0.0), 2: np.full(3, 0.5 + 0.05 / np.sqrt(3)), 3: (0.5 + 0.05 / np.sqrt(2),) * 2 + (0.0,),
                4: (0.55, 0.0, 0.0), 5: (0.6, 0.0, 0.0), 8: (0.1, 0.2, 0.0)}  # fmt: skip
    for i, xyz in expected.items():
        np.testing.assert_allclose(got[i, :3], xyz, rtol=0, atol=1e-6, err_msg=f"particle {i}")
    for i in (0, 6, 7):  # pushed onto one of the faces it was closest to, plus the margin
        assert np.abs(got[i, :3]).max() == pytest.approx(0.55, abs=1e-6), f"particle {i}"


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_a_rotated_moving_box_matches_numpy(algorithm):
    # R and T per step: the particle goes into the body frame and, when pushed, back
    box = Mesh(
        shape="box",
        margin=0.05,
        position=(0.2, 0.1, -0.1),
        rotation=(10.0, 20.0, 30.0),
        motion=Motion(velocity=(3.0, 0.0, 0.0), angular_velocity=(0.0, 400.0, 0.0)),
    )
    scene = still(box)
    rot, trans = box.pose_at(VERLET.dt)  # the pose the step uses: at its end
    pos, prev = placed(scene, np.array(BOX_POINTS) @ rot.T + trans)
    got, want = one_step_both(pingpong(scene, algorithm=algorithm), scene, pos, prev)
    assert_bit_exact(got, want, f"pos, moving box, {algorithm}")
    assert not np.array_equal(got[1], pos[1])  # a pushed particle


def test_an_open_mesh_matches_numpy(tmp_path):
    # one square, normals up: a skin of the margin's thickness below it, nothing above
    (tmp_path / "square.obj").write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n")
    square = Mesh(file=str(tmp_path / "square.obj"), margin=0.05)
    assert not square.geometry.closed
    scene = still(square)
    pos, prev = placed(scene, [(0.2, -0.02, 0.3), (0.2, 0.02, 0.3), (0.2, -0.1, 0.3), (1.5, -0.02, 0.0), (0, 0, 0)])
    for algorithm in ALGORITHMS:
        got, want = one_step_both(pingpong(scene, algorithm=algorithm), scene, pos, prev)
        assert_bit_exact(got, want, f"pos, open square, {algorithm}")
        np.testing.assert_allclose(got[0, :3], (0.2, 0.05, 0.3), rtol=0, atol=1e-6)  # out of the skin
        assert_bit_exact(got[1:4], pos[1:4], "above, below the skin and beside the square: unchanged")


@pytest.mark.full  # the torus to contact on the CPU shim
def test_fast_torus_is_as_accurate_as_float32():
    # fast mode (1/sqrt for rsqrt on the CPU, contraction where g++ is allowed) against the
    # float64 reference: held to float32's own error (tests/test_cuda.py, FAST_ERROR_FACTOR)
    scene = scene_named("torus")
    ((_, pos, _),) = run(pingpong(scene, strict=False), scene, (STEPS,))
    assert_as_accurate_as_float32(pos, scene, STEPS)


def test_the_mesh_buffers_hold_every_triangle_in_order():
    scene = scene_named("sweep").replace(meshes=(*scene_named("sweep").meshes, *scene_named("torus").meshes))
    rows, ints = launch.mesh_buffers(scene)
    assert rows.dtype == np.float32 and ints.dtype == np.int32
    for m, mesh in enumerate(scene.meshes):
        g = mesh.geometry
        first, count, node_row, link, leaves, closed = ints[launch.MESH_HEADER_INTS * m :][:6]
        tris = rows[first : first + launch.MESH_TRIANGLE_ROWS * count].reshape(count, launch.MESH_TRIANGLE_ROWS, 4)
        assert_bit_exact(tris[:, :3, :3], g.corners, f"corners of mesh {m}")
        assert_bit_exact(tris[:, 3:, :3], g.normals, f"pseudo-normals of mesh {m}")
        assert_bit_exact(rows[node_row : node_row + 2 * g.bvh.nodes : 2, :3], g.bvh.lo, f"node boxes of mesh {m}")
        assert_bit_exact(ints[leaves : leaves + count], g.bvh.tris, f"leaf triangles of mesh {m}")
        assert ints[link] == g.bvh.child[0] and bool(closed) == g.closed


# --- 4. CudaBackend over the stand-in cupy ----------------------------------------------


def test_the_cuda_backend_declares_meshes_and_motion():
    caps = backend_class("cuda").capabilities
    assert caps.meshes == ("verlet",) and caps.moving_colliders == ("verlet",)
    assert caps.mesh_collisions == ("accelerated", "naive")
    for name in ("torus", "sweep", "carried"):
        assert caps.scene_refusal("cuda", scene_named(name)) is None


@pytest.mark.parametrize("algorithm", ALGORITHMS)
def test_cuda_backend_builds_and_names_the_mesh_algorithm(cuda_on_cpu, algorithm):  # noqa: F811
    scene = scene_named("torus")
    options = {"strict": True} if algorithm == "accelerated" else {"strict": True, "mesh_collision": "naive"}
    backend, runtime = cuda_on_cpu(scene, **options)  # accelerated: the default
    with backend:
        assert backend.mode.endswith(f"/mesh={algorithm}")
        assert ("-DCLOTH_MESH_BVH" in backend.defines) == (algorithm == "accelerated")
        assert runtime.signature == "ppp" + "q"  # the state, then the mesh rows and ints
        backend.upload(*VERLET.initial_state(scene, np.float32))
        backend.advance(1)
        assert_bit_exact(backend.read()[0], reference(scene, VERLET, 1, "f32")[0], f"pos, {algorithm}")


@pytest.mark.parametrize("shape", ["block=256", "steps/launch=16", "steps/launch=64"])
def test_cuda_backend_runs_a_moving_mesh_in_every_shape(cuda_on_cpu, shape):  # noqa: F811
    scene = scene_named("sweep")
    backend, _ = cuda_on_cpu(scene, strict=True, shape=shape)
    with backend:
        assert shape in backend.mode
        backend.upload(*VERLET.initial_state(scene, np.float32))
        backend.advance(MOVING_CHECKPOINTS[-1])
        pos, prev = backend.read()
    assert_bit_exact(pos, reference(scene, VERLET, MOVING_CHECKPOINTS[-1], "f32")[0], f"pos, {shape}")
    assert_bit_exact(prev, reference(scene, VERLET, MOVING_CHECKPOINTS[-1], "f32")[1], f"prev, {shape}")


@pytest.mark.full  # the torus to contact on the CPU shim
def test_cuda_backend_strict_torus_equals_numpy(cuda_on_cpu):  # noqa: F811
    scene = scene_named("torus")
    backend, _ = cuda_on_cpu(scene, strict=True)
    with backend:
        backend.upload(*VERLET.initial_state(scene, np.float32))
        backend.advance(STEPS)
        pos, prev = backend.read()
    assert_bit_exact(pos, reference(scene, VERLET, STEPS, "f32")[0], "pos, torus through CudaBackend")
    assert_bit_exact(prev, reference(scene, VERLET, STEPS, "f32")[1], "prev, torus through CudaBackend")
