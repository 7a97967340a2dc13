"""glsl-compute (and glsl, the fragment path) with triangle-mesh colliders (naive loop and BVH
traversal), moving colliders and pins attached to a body (docs/semantics.md, "Triangle mesh",
"Moving colliders", "Pins attached to a body"; kernels/collide_mesh.glsl): strict is the NumPy
float32 reference bit for bit, fast is as accurate as float32, and a scene without them
compiles none of their code."""

from __future__ import annotations

import pytest

pytest.importorskip("trimesh", reason="the built-in mesh scenes load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions, create_backend
from clothbench.colliders.mesh import Mesh
from clothbench.colliders.motion import Motion
from clothbench.harness import position_error, reference, simulate
from clothbench.scene import load_scene

from conftest import VERLET, assert_bit_exact, require

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker

N = 32
# 500 steps, after contact: the torus is reached after about 200, the carried sheet moves at
# once; the swinging curtain reaches the paddle only after about 900 (at 700 it has not)
STEPS = {"torus": 500, "sweep": 1000, "carried": 500}


def two_meshes(n: int = 16):
    """A sheet falling onto a still icosphere and a turning box: two meshes in one buffer,
    the second read from the per-step rows."""
    return load_scene("torus").replace(
        name="two-meshes",
        grid=n,
        height=0.36,
        planes=(),
        meshes=(
            Mesh(shape="icosphere", subdivisions=1, position=(0.3, 0.0, 0.3), scale=0.3, name="ball"),
            Mesh(shape="box", position=(0.75, 0.2, 0.7), scale=(0.3, 0.3, 0.3), name="block",
                 motion=Motion(angular_velocity=(0.0, 120.0, 0.0))),
        ),
    )  # fmt: skip


def without_bodies(scene):
    """The scene with its meshes and motion taken away: what the bodies' effect is measured from."""
    return scene.replace(meshes=(), pin_attach=None, cylinders=tuple(c for c in scene.cylinders if c.motion is None))


FULL = pytest.mark.full  # the quick tier: glsl-compute's BVH (the default) on the torus, each backend's carried sheet
CASES = [
    pytest.param("glsl-compute", "torus", "naive", None, marks=FULL),
    ("glsl-compute", "torus", "accelerated", None),
    pytest.param("glsl-compute", "sweep", "naive", None, marks=FULL),  # 1000 steps: the paddle comes late
    pytest.param("glsl-compute", "sweep", "accelerated", None, marks=FULL),
    pytest.param(
        "glsl-compute", "sweep", "accelerated", "steps/dispatch=16", marks=FULL
    ),  # K steps' rows in one launch
    ("glsl-compute", "carried", None, None),
    pytest.param("glsl-compute", "carried", None, "steps/dispatch=64", marks=FULL),
    # the fragment path: exact while no value is subnormal (llvmpipe flushes them there,
    # docs/semantics.md), which none is in these runs
    pytest.param("glsl", "torus", "naive", None, marks=FULL),
    pytest.param(
        "glsl", "torus", "accelerated", None, marks=FULL
    ),  # the fragment path's moving carried sheet stays quick
    pytest.param("glsl", "sweep", "accelerated", None, marks=FULL),
    ("glsl", "carried", None, None),
]


@pytest.mark.parametrize("backend, scene_name, algorithm, shape", CASES)
def test_strict_matches_numpy_f32_bit_for_bit_after_contact(backend, scene_name, algorithm, shape):
    require(backend)
    scene = load_scene(scene_name).replace(grid=N)
    options = BackendOptions(strict=True, mesh_collision=algorithm, shape=shape)
    steps = STEPS[scene_name]
    pos, prev = simulate(backend, scene, VERLET, steps, options)
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    what = f"{backend} {scene_name} mesh={algorithm} shape={shape} n={scene.grid} steps={steps}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")
    # the bodies did something: without them the sheet ends elsewhere (by more than 1 mm)
    bare, _ = reference(without_bodies(scene), VERLET, steps, "f32")
    assert position_error(pos, bare)[1] > 1e-3, f"{what}: the mesh, motion or pins changed nothing"


@pytest.mark.parametrize("algorithm", ["naive", "accelerated"])
@pytest.mark.parametrize("backend", ["glsl-compute"])  # not glsl: on llvmpipe its flushed subnormals
def test_two_meshes_one_moving_match_numpy_bit_for_bit(backend, algorithm):  # part it from NumPy here by step 20
    require(backend)
    scene, steps = two_meshes(), 400
    pos, prev = simulate(backend, scene, VERLET, steps, BackendOptions(strict=True, mesh_collision=algorithm))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, two meshes, mesh={algorithm}")
    assert_bit_exact(prev, ref_prev, f"prev, two meshes, mesh={algorithm}")
    bare, _ = reference(without_bodies(scene), VERLET, steps, "f32")
    assert position_error(pos, bare)[1] > 1e-3, "the meshes changed nothing"


@pytest.mark.parametrize("backend", ["glsl-compute", pytest.param("glsl", marks=FULL)])
def test_an_upload_restarts_the_bodies_clock_and_advances_add_up(backend):
    # step k's poses are those at (k + 1) dt counted from the last upload, however the steps
    # are split over advance() calls (here across a block of uploaded rows)
    require(backend)
    scene = load_scene("sweep").replace(grid=16)
    with create_backend(backend, scene, VERLET, BackendOptions(strict=True)) as b:
        b.upload(*b.initial_state())
        b.advance(40)
        b.upload(*b.initial_state())  # back to t = 0
        for steps in (7, 250, 43):
            b.advance(steps)
        pos, prev = b.read()
    ref_pos, ref_prev = reference(scene, VERLET, 300, "f32")
    assert_bit_exact(pos, ref_pos, "pos after an upload and advances of 7, 250, 43")
    assert_bit_exact(prev, ref_prev, "prev after an upload and advances of 7, 250, 43")


@pytest.mark.parametrize("scene_name", ["torus", pytest.param("sweep", marks=FULL), "carried"])
@pytest.mark.parametrize(
    "backend", ["glsl-compute", pytest.param("glsl", marks=FULL)]
)  # llvmpipe's fragment path: slow
def test_fast_error_is_of_the_order_of_numpy_f32s_own(backend, scene_name):
    # Fast mode may use dot() and contract products: each an O(float32 epsilon) change per
    # operation, like the reference's own roundings. In contact those are amplified alike, so
    # the distance to float64 after contact is of the order of NumPy float32's; 3x with a
    # 1 um floor is the contract's bound (tests/contract/test_verlet_contract.py). Measured
    # here on llvmpipe (glsl-compute): 1.0x (torus), 0.6x (sweep), 1.2x (carried).
    require(backend)
    scene, steps = load_scene(scene_name).replace(grid=N), STEPS[scene_name]
    ref64, _ = reference(scene, VERLET, steps, "f64")
    _, f32_max = position_error(reference(scene, VERLET, steps, "f32")[0], ref64)
    pos, _ = simulate(backend, scene, VERLET, steps, BackendOptions())
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 3 * max(f32_max, 1e-6), (
        f"{backend} {scene_name}: fast {fast_max:.3g} m, numpy f32 {f32_max:.3g} m"
    )


def sources(scene, **values) -> str:
    require("glsl-compute")
    with create_backend("glsl-compute", scene, VERLET, BackendOptions(strict=True, **values)) as b:
        return "\n".join(b.sources.values())


def switches(source: str) -> set[str]:
    """The names the host defines in front of the kernel (the lines before its first #line)."""
    head = source.split("#line", 1)[0]
    return {line.split()[1] for line in head.splitlines() if line.startswith("#define ")}


def test_a_scene_without_meshes_or_motion_compiles_none_of_their_code():
    source = sources(load_scene("sphere").replace(grid=16))
    assert "closest_point(" not in source and "collide_meshes(" not in source, "mesh code in a scene without meshes"
    assert not switches(source) & {"MESH_COUNT", "MOTION", "PIN_ATTACH", "MESH_BVH"}, "switches of bodies it lacks"


def test_a_still_mesh_compiles_no_motion_and_the_naive_loop_no_bvh():
    torus = load_scene("torus").replace(grid=16)
    accelerated = sources(torus)  # the default
    assert "MESH_BVH" in switches(accelerated) and "MOTION" not in switches(accelerated)
    naive = sources(torus, mesh_collision="naive")
    assert "closest_point(" in naive and not switches(naive) & {"MESH_BVH", "MOTION"}
    moving = sources(load_scene("sweep").replace(grid=16))
    assert "MOTION" in switches(moving) and "MOTION_ROW(MOTION_MESHES" in moving


def test_the_default_algorithm_is_the_bvh_and_the_mode_says_which():
    require("glsl-compute")
    torus = load_scene("torus").replace(grid=16)
    with create_backend("glsl-compute", torus, VERLET, BackendOptions()) as b:
        assert b.mesh_collision == "accelerated" and "/mesh=accelerated" in b.mode
    with create_backend("glsl-compute", torus, VERLET, BackendOptions(mesh_collision="naive")) as b:
        assert "/mesh=naive" in b.mode
    with create_backend("glsl-compute", load_scene("sphere").replace(grid=16), VERLET, BackendOptions()) as b:
        assert "/mesh=" not in b.mode  # no meshes, no algorithm
