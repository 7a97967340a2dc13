"""The PBD solver with meshes, moving colliders and pins attached to a body (docs/pbd.md,
"Colliders, motion and attached pins"): the strict PBD of OpenCL (either kernel shape) and of
GLSL compute is the NumPy float32 reference bit for bit with either mesh search and either
method; the final state lies
outside the mesh (checked by trimesh and a winding number, not by the reference's own answer);
attached pins sit exactly on their body; a scene compiles only the parts it has."""

from __future__ import annotations

import functools

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.kernel_inputs import pin_targets
from clothbench.backends.opencl.pbd import OpenCLPbdBackend
from clothbench.harness import reference, simulate
from clothbench.scene import load_setup
from clothbench.solver import Pbd
from conftest import assert_bit_exact, require
from test_meshes import winding_number, world_mesh

N = 16  # small and fast; the spacing (6.7 cm) still drapes over the torus's 10.5 cm tube
DT = 1 / 60  # PBD's own step: at the scenes' 5e-4 s a float32 sheet at y = 1 never starts to
# fall (g h^2 at 10 substeps is below half an ulp of 1.0: x + v h rounds back to x)
# steps: the torus is touched from about step 9 (0.14 s), the paddle sweeps 45 degrees in 30,
# the bar carries the sheet 9 cm in 60
STEPS = {"torus": 30, "sweep": 30, "carried": 60}
METHODS = ("jacobi", "coloured")
BACKENDS = ("opencl", "glsl-compute")
ALGORITHMS = ("naive", "accelerated")


@functools.lru_cache(maxsize=None)
def setup(name: str, method: str = "jacobi", chebyshev_rho: float = 0.0):
    return load_setup(name).scene.replace(grid=N), Pbd(dt=DT, method=method, chebyshev_rho=chebyshev_rho)


def numpy_f32(name: str, method: str, chebyshev_rho: float = 0.0):
    scene, solver = setup(name, method, chebyshev_rho)
    return reference(scene, solver, STEPS[name], "f32")  # cached by the harness


def builds(backend: str, scene, solver, algorithm) -> list[BackendOptions]:
    """Strict options of every build of `backend` to compare: each OpenCL kernel shape."""
    options = BackendOptions(strict=True, mesh_collision=algorithm)
    if backend != "opencl":
        return [options]
    shapes = OpenCLPbdBackend.kernel_shapes(scene, options, solver)
    # every shape runs the bodies' code: the bands (Jacobi) predict the pins on the body too,
    # the coloured vector sweep collides from its planar scratch
    jacobi = solver.method == "jacobi"
    assert {"per-stage", "one-launch"} <= set(shapes)
    assert jacobi == ("bands-8" in shapes) and jacobi != ("one-launch-vectors" in shapes), shapes
    return [BackendOptions(strict=True, mesh_collision=algorithm, shape=shape) for shape in shapes]


def end_time(name: str) -> float:
    """The collider time of the last substep: substep j ends at j * (dt / substeps), float64."""
    _, solver = setup(name)
    return STEPS[name] * solver.substeps * (solver.dt / solver.substeps)


# --- strict: bit for bit ----------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(
    "name, algorithm",
    [("torus", "naive"), ("torus", "accelerated"), ("sweep", "naive"), ("sweep", "accelerated"), ("carried", None)],
)  # a mesh; a moving mesh; pins on a moving bar over a sphere (no mesh: no search to choose)
def test_strict_pbd_matches_numpy_f32_bit_for_bit(name, algorithm, method, backend):
    require(backend)
    scene, solver = setup(name, method)
    ref_pos, ref_prev = numpy_f32(name, method)
    for options in builds(backend, scene, solver, algorithm):
        pos, prev = simulate(backend, scene, solver, STEPS[name], options)
        assert_bit_exact(pos, ref_pos, f"pos, {backend} {name} {method} {algorithm} {options.shape}")
        assert_bit_exact(prev, ref_prev, f"prev, {backend} {name} {method} {algorithm} {options.shape}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_chebyshev_jacobi_collides_bit_for_bit_too(backend):
    # its multipliers ping-pong in two buffers: another launch plan around the same collide
    require(backend)
    scene, solver = setup("sweep", "jacobi", 0.9)
    ref_pos, _ = numpy_f32("sweep", "jacobi", 0.9)
    for options in builds(backend, scene, solver, "accelerated"):
        pos, _ = simulate(backend, scene, solver, STEPS["sweep"], options)
        assert_bit_exact(pos, ref_pos, f"pos, {backend} {options.shape}")


def test_the_colliders_change_the_result():
    # not vacuous: without the paddle (the same sheet, the same steps) the state differs
    scene, solver = setup("sweep")
    free, _ = simulate("numpy", scene.replace(meshes=()), solver, STEPS["sweep"], BackendOptions(precision="f32"))
    pos, _ = numpy_f32("sweep", "jacobi")
    assert np.abs(pos[:, :3] - free[:, :3]).max() > 1e-2, "the paddle never reached the cloth"


@pytest.mark.parametrize("backend", BACKENDS)
def test_upload_starts_the_bodies_clock_over(backend):
    # substep j's poses are at j * h counted from the last upload, as NumPy counts them
    require(backend)
    scene, solver = setup("sweep")
    with create_backend(backend, scene, solver, BackendOptions(strict=True)) as b:
        runs = []
        for _ in range(2):
            b.upload(*b.initial_state())
            b.advance(10)
            runs.append(b.read()[0])
        b.upload(*b.initial_state())
        b.profile_stages(10)  # synchronised launch by launch, each substep's poses uploaded alike
        runs.append(b.read()[0])
    assert_bit_exact(runs[1], runs[0], "the second run from the same state")
    assert_bit_exact(runs[2], runs[0], "the profiled run")


# --- checked against the mesh and the body -----------------------------------------------------


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("name", ["torus", "sweep"])
def test_final_state_is_outside_the_mesh(name, method):
    scene, _ = setup(name, method)
    pos, _ = numpy_f32(name, method)  # the OpenCL strict state too: the same bits (above)
    x = pos[:, :3].astype(np.float64)
    mesh = scene.meshes[0]
    tm = world_mesh(mesh, end_time(name))  # the pose of the last substep's collision
    assert tm.is_watertight
    _, dist, _ = trimesh.proximity.closest_point_naive(tm, x)
    inside = winding_number(tm, x) > 0.5
    assert dist.min() < 1e-3, f"closest particle {dist.min():.3g} m away: the cloth never touched it"
    assert inside.sum() == 0 or dist[inside].max() <= 1e-5, f"{inside.sum()} inside, deepest {dist[inside].max():.3g} m"


@pytest.mark.parametrize("method", METHODS)
def test_attached_pins_sit_exactly_on_their_body(method):
    scene, _ = setup("carried", method)
    pos, _ = numpy_f32("carried", method)
    pinned = scene.pinned()
    target = pin_targets(scene, end_time("carried"), np.float32)  # the bar's pose, float64, rounded once
    assert_bit_exact(pos[pinned, :3], target, "pinned particles")
    start = scene.initial_state(np.float32)[0][pinned, :3]
    assert np.abs(target - start).max() > 0.05  # the bar has moved: this is not vacuous


# --- only what the scene has is compiled -------------------------------------------------------


def test_a_scene_compiles_only_the_body_code_it_has():
    require("opencl")
    built = {}
    for name in ("curtain", "torus", "sweep", "carried"):
        scene, solver = setup(name)
        with create_backend("opencl", scene, solver, BackendOptions(strict=True, shape="per-stage")) as b:
            built[name] = (set(b.build_options()), "float3 collide_meshes(" in b._source)  # collide_mesh.cl's
    assert not any(o.startswith(("-DCLOTH_MESH", "-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED")) for o in built["curtain"][0])
    assert not built["curtain"][1] and built["torus"][1] and built["sweep"][1] and not built["carried"][1]
    assert "-DCLOTH_MESHES=1" in built["torus"][0] and "-DCLOTH_PER_STEP" not in built["torus"][0]  # static: no motion
    assert {"-DCLOTH_MESHES=1", "-DCLOTH_PER_STEP"} <= built["sweep"][0]
    assert {"-DCLOTH_PER_STEP", "-DCLOTH_ATTACHED_PINS"} <= built["carried"][0]
