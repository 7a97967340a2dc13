"""The OpenCL VBD solver beyond the contracts (tests/contract/test_vbd_contract.py, and
test_bodies_contract.py for its meshes, moving colliders and attached pins): strict is the
NumPy float32 reference bit for bit on every runtime here that compiles; a scene compiles only
the parts it has."""

from __future__ import annotations

import json

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import device
from clothbench.backends.tuning import TUNING_ROUNDS
from clothbench.backends.opencl import vbd as vbd_module
from clothbench.backends.opencl.vbd import VECTOR_WIDTHS, OpenCLVbdBackend, parse_planes, planes_shapes, vector_rest
from clothbench.harness import reference, simulate
from clothbench.harness.plan import without_motion
from clothbench.model.scene import load_setup
from clothbench.model.solver import Vbd
from conftest import assert_bit_exact, require

N = 16  # as tests/test_pbd_meshes.py: the spacing still drapes over the torus's tube


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


def scene_of(name: str):
    """Built-in scene `name` at N, or a skip where it has meshes and trimesh is missing."""
    scene = load_setup(name).scene.replace(grid=N)
    if scene.meshes:
        pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")
    return scene


# the curtain's pins and sphere; the torus's mesh; the carried sheet's pins on a moving bar (the
# bodies in --full; the bodies contract's 16^2 is too narrow for a vector of 8 or 16 lanes)
PLANES_SCENES = ("curtain", "torus", "carried")


@pytest.mark.every_runtime  # each runtime's device picked here: .ci/run's per-runtime legs leave it out
@pytest.mark.parametrize(
    "scene_name", [PLANES_SCENES[0], *(pytest.param(s, marks=pytest.mark.full) for s in PLANES_SCENES[1:])]
)
def test_strict_vbd_is_bit_exact_in_every_shape_on_every_runtime_here_that_compiles(scene_name):
    # the Intel CPU runtime as well as PoCL: no runtime may contract or reorder a strict build.
    # n = 41: an interior row of a colour holds 18 or 19 particles, so the planes shapes' vector
    # sweep takes one or more vectors of 4, 8 or 16 lanes, the last moved back over the one
    # before it, in rows of both column parities; with Chebyshev's planar extrapolation, and the
    # bodies through the planes' predict (attached pins) and update (colliders)
    scene = scene_of(scene_name).replace(grid=41)
    solver = Vbd(dt=1 / 60, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, 30, "f32")
    compiling = [(spec, dev, kind) for spec, dev, kind in device.ordered_devices() if device.compile_error(dev) is None]
    assert compiling, "no OpenCL device here compiles"
    for spec, dev, kind in compiling:
        shapes = OpenCLVbdBackend.kernel_shapes(scene, BackendOptions(device=spec), solver)
        planes = planes_shapes(dev, scene, BackendOptions())
        assert set(planes) <= set(shapes), shapes
        for name in planes:  # not vacuous: the vectors take particles, and leave some
            taken = ~vector_rest(scene.grid, parse_planes(name)[0])
            assert 0 < taken.sum() < scene.particles
        for shape in shapes:
            pos, prev = simulate("opencl", scene, solver, 30, BackendOptions(strict=True, device=spec, shape=shape))
            assert_bit_exact(pos, ref_pos, f"pos, {kind} ({spec}) {scene_name} {shape}")
            assert_bit_exact(prev, ref_prev, f"prev, {kind} ({spec}) {scene_name} {shape}")


@pytest.mark.full
def test_the_bodies_move_the_planes_test_s_cloth():
    # not vacuous: in those 30 steps the mesh and the moving bar change where the cloth ends
    solver = Vbd(dt=1 / 60, chebyshev_rho=0.9)
    for name in PLANES_SCENES[1:]:
        scene = scene_of(name).replace(grid=41)
        other = scene.replace(meshes=()) if scene.meshes else without_motion(scene)
        moved = reference(scene, solver, 30, "f32")[0] - reference(other, solver, 30, "f32")[0]
        assert np.abs(moved[:, :3]).max() > 0.1, name


def test_the_planes_shape_leaves_to_the_rest_launch_exactly_what_no_vector_takes():
    # each colour's particles are swept once a sweep: by a vector lane or by the rest launch
    from clothbench.model.constraints import vertex_colours

    for n, width in ((41, 16), (41, 8), (40, 4), (9, 4), (36, 16)):
        rest = vector_rest(n, width).reshape(n, n)
        rows, cols = np.divmod(np.arange(n * n), n)
        interior = (rows >= 2) & (rows <= n - 3) & (cols >= 2) & (cols <= n - 3)
        assert rest.reshape(-1)[~interior].all(), "the border is the rest launch's"
        colour = vertex_colours(n).reshape(n, n)
        for row in range(2, n - 2):
            for c in range(4):
                mine = [col for col in range(2, n - 2) if colour[row, col] == c]
                taken = [col for col in mine if not rest[row, col]]
                assert taken == (mine if len(mine) >= width else []), (n, width, row, c)


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


def test_the_tuned_vbd_shape_is_kept_under_vbd_s_own_key(monkeypatch, tmp_path):
    # the fastest shape wins and is read back without measuring; Verlet's choices and VBD's
    # with other sweep settings are other keys of the same tuning file, never an answer here
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    timed: list[str] = []

    def fake(backend, name):  # the last shape offered is the fastest
        timed.append(name)
        return 1e-4 if name == backend.kernel_shapes(backend.scene, backend.options, backend.solver)[-1] else 2e-4

    monkeypatch.setattr(OpenCLVbdBackend, "_time_shape", fake)
    scene = load_setup("drape").scene.replace(grid=41)
    offered = OpenCLVbdBackend.kernel_shapes(scene, BackendOptions(), Vbd())
    if len(offered) < 2:
        pytest.skip(f"the default OpenCL device offers VBD one shape here ({offered[0]}): nothing to choose")
    for solver in (Vbd(), Vbd(), Vbd(iterations=20), Vbd(chebyshev_rho=0.9)):
        with create_backend("opencl", scene, solver, BackendOptions()) as b:
            assert b.shape == offered[-1] and b.mode.endswith(offered[-1]), b.mode
    assert len(timed) == 3 * TUNING_ROUNDS * len(offered)  # the second Vbd() read the first's choice
    kept = json.loads((tmp_path / "tuning" / "opencl.json").read_text())
    assert [json.loads(k)["solver"] for k in kept] == ["vbd"] * 3


@pytest.mark.parametrize("width", VECTOR_WIDTHS)
def test_every_lane_width_is_bit_exact_whatever_the_device_offers(width, monkeypatch):
    # a device offers its native width only (16 with AVX-512, 8 with AVX2): each width's vector
    # sweep is built and held to NumPy here too, with the runtime's work-groups and with 4
    shapes = (f"planes/v{width}", f"planes/v{width}/wg=4")
    monkeypatch.setattr(vbd_module, "planes_shapes", lambda device, scene, options: shapes)
    scene, solver = scene_of("curtain").replace(grid=41), Vbd(dt=1 / 60, chebyshev_rho=0.9)
    ref_pos, ref_prev = reference(scene, solver, 30, "f32")
    for shape in shapes:
        pos, prev = simulate("opencl", scene, solver, 30, BackendOptions(strict=True, shape=shape))
        assert_bit_exact(pos, ref_pos, f"pos, {shape}")
        assert_bit_exact(prev, ref_prev, f"prev, {shape}")
