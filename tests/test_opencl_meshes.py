"""Meshes, moving colliders and pins attached to a body on the OpenCL Verlet backend
(kernels/collide_mesh.cl, docs/semantics.md "Triangle mesh", "Moving colliders", "Pins
attached to a body"): strict is the NumPy float32 reference bit for bit with either mesh
search, in every kernel shape and the generic build; fast stays within float32's own error
of float64; the naive and accelerated searches agree on a mesh of thousands of triangles; a
scene compiles only the parts it has."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import verlet as opencl
from clothbench.colliders.mesh import Mesh
from clothbench.harness import position_error, reference, simulate
from clothbench.scene import load_setup
from conftest import assert_bit_exact, require

N = 32  # the contract's grid: the torus is touched well within 500 steps (contact from ~200)
ALGORITHMS = ("naive", "accelerated")


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


@functools.lru_cache(maxsize=None)
def setup(name: str, n: int = N):
    s = load_setup(name)
    return s.scene.replace(grid=n), s.solver


@functools.lru_cache(maxsize=None)
def numpy_f32(name: str, steps: int):
    scene, solver = setup(name)
    return reference(scene, solver, steps, "f32")


def strict(algorithm: str, **values) -> BackendOptions:
    return BackendOptions(strict=True, mesh_collision=algorithm, **values)


# --- strict: bit for bit ----------------------------------------------------------------------


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("name", ["torus", "sweep", "carried"])  # a mesh; a moving mesh; pins on a moving bar
def test_strict_matches_numpy_f32_bit_for_bit_after_500_steps(name, algorithm):
    scene, solver = setup(name)
    pos, prev = simulate("opencl", scene, solver, 500, strict(algorithm))
    ref_pos, ref_prev = numpy_f32(name, 500)
    assert_bit_exact(pos, ref_pos, f"pos, {name} {algorithm}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} {algorithm}")


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("name", ["sweep", "carried"])
def test_every_kernel_shape_and_the_generic_build_take_per_step_poses_bit_for_bit(name, algorithm):
    # the multi-step kernel reads one table per step of its launch, 256 steps per upload:
    # 300 steps cross an upload and end inside a launch of fewer than 32 steps
    scene, solver = setup(name)
    ref_pos, ref_prev = numpy_f32(name, 300)
    builds = [{"shape": s} for s in opencl.OpenCLBackend.kernel_shapes(scene, strict(algorithm))]
    assert any(b["shape"].startswith("steps/") for b in builds), "the multi-step shape is a candidate"
    for build in [*builds, {"generic": True}, {"transfer": "per-step"}]:
        pos, prev = simulate("opencl", scene, solver, 300, strict(algorithm, **build))
        assert_bit_exact(pos, ref_pos, f"pos, {name} {algorithm} {build}")
        assert_bit_exact(prev, ref_prev, f"prev, {name} {algorithm} {build}")


def test_upload_starts_the_bodies_clock_over():
    # a moving scene's step k uses the poses of (k + 1) dt counted from the last upload, as
    # NumPy does: the same 200 steps twice from the same state give the same bits
    scene, solver = setup("sweep")
    with create_backend("opencl", scene, solver, strict("accelerated")) as b:
        b.upload(*b.initial_state())
        b.advance(200)
        first = b.read()
        b.upload(*b.initial_state())
        b.advance(200)
        again = b.read()
    assert_bit_exact(again[0], first[0], "pos after a second upload")
    ref = numpy_f32("sweep", 200)[0]
    assert_bit_exact(first[0], ref, "pos, sweep 200 steps")


# --- fast: as accurate as float32 -------------------------------------------------------------


@pytest.mark.parametrize("algorithm", ALGORITHMS)
@pytest.mark.parametrize("name", ["torus", "sweep", "carried"])
def test_fast_error_is_of_the_order_of_numpy_f32s_own(name, algorithm):
    # Fast mode contracts FMAs and uses rsqrt in the springs (the mesh code is the same
    # operations, contracted): O(float32 epsilon) per operation, like the reference's own
    # roundings. 300 steps: in contact with the torus (from ~200) and the paddle, before
    # contact turns rounding into millimetres (at 500 both reach 1-20 mm). Measured here:
    # 0.8-1.2x NumPy f32's max error; 3x with a 1 um floor, the contract's bound, still
    # catches a physics slip (a wrong bend rest length is 25x).
    scene, solver = setup(name)
    ref64 = reference(scene, solver, 300, "f64")[0]
    _, f32_max = position_error(numpy_f32(name, 300)[0], ref64)
    pos = simulate("opencl", scene, solver, 300, BackendOptions(mesh_collision=algorithm))[0]
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 3 * f32_max + 1e-6, f"{name} {algorithm}: fast {fast_max:.3g} m, NumPy f32 {f32_max:.3g} m"


# --- naive against accelerated on thousands of triangles --------------------------------------


def icosphere_drop(subdivisions: int):
    """A sheet dropped from 2 cm onto an icosphere of radius 0.2 (20 * 4^s triangles)."""
    scene, solver = setup("torus")
    ball = Mesh(shape="icosphere", subdivisions=subdivisions, position=(0.5, 0.3, 0.5), scale=0.2, name="ball")
    return replace(scene, meshes=(ball,), planes=(), height=0.52), solver


@pytest.mark.parametrize("subdivisions", [4])  # 5,120 triangles
def test_naive_and_accelerated_agree_bit_for_bit_on_thousands_of_triangles(subdivisions):
    scene, solver = icosphere_drop(subdivisions)
    assert scene.meshes[0].geometry.triangles == 20 * 4**subdivisions
    naive = simulate("opencl", scene, solver, 150, strict("naive"))
    accelerated = simulate("opencl", scene, solver, 150, strict("accelerated"))
    assert_bit_exact(accelerated[0], naive[0], "pos, accelerated against naive")
    assert_bit_exact(accelerated[1], naive[1], "prev, accelerated against naive")
    # and the mesh was touched: without it the sheet falls through where the ball is
    free = simulate("opencl", replace(scene, meshes=()), solver, 150, strict("naive"))[0]
    assert not np.array_equal(free, naive[0]), "the cloth never reached the icosphere"
    assert naive[0][:, 1].min() > 0.3, "the sheet is held above the ball's centre"


# --- what is compiled -------------------------------------------------------------------------


def program_sources(backend) -> str:
    """The source build_program handed the compiler for each of the backend's programs. Not
    the program's own SOURCE: on Intel's runtime a program pyopencl's binary cache serves is
    made from the binary, and its source is empty (PoCL's is always built from source)."""
    from clothbench.backends.opencl.device import _programs

    sources = [source for (_, source, _), program in _programs.items() if any(program is p for p in backend.programs)]
    assert len(sources) == len({id(p) for p in backend.programs}), "every program is in the program cache"
    return "".join(sources)


@pytest.mark.parametrize("generic", [False, True])
def test_a_scene_without_meshes_or_motion_compiles_none_of_it(generic):
    scene, solver = setup("drape")
    with create_backend("opencl", scene, solver, BackendOptions(strict=True, generic=generic)) as b:
        source, options = program_sources(b), " ".join(o for key in b.key for o in key)
    assert "closest_point" not in source and "collide_mesh(" not in source, "mesh code in the source"
    for option in ("CLOTH_MESHES", "CLOTH_MESH_BVH", "CLOTH_PER_STEP", "CLOTH_ATTACHED_PINS"):
        assert option not in options


def test_a_static_mesh_scene_compiles_its_search_and_no_motion():
    scene, solver = setup("torus")
    for algorithm in ALGORITHMS:
        with create_backend("opencl", scene, solver, strict(algorithm)) as b:
            source, options = program_sources(b), " ".join(o for key in b.key for o in key)
            assert b.mode.endswith(f"/mesh={algorithm}")
        assert "closest_point" in source and "-DCLOTH_MESHES=1" in options
        assert ("-DCLOTH_MESH_BVH" in options) == (algorithm == "accelerated")
        assert "CLOTH_PER_STEP" not in options and "CLOTH_ATTACHED_PINS" not in options


def test_accelerated_is_the_default_mesh_search():
    scene, solver = setup("torus")
    with create_backend("opencl", scene, solver, BackendOptions(strict=True)) as b:
        assert b.mesh_collision == "accelerated" and b.mode.endswith("/mesh=accelerated")
