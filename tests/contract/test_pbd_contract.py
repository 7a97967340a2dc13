"""The backend contract for the PBD solver (docs/pbd.md), on every backend of the registry
that implements it with a strict mode: strict is the NumPy float32 reference bit for bit with
either method and in every kernel shape, and the work-group size changes no bit."""

from __future__ import annotations

import pytest

from clothbench.harness import reference, simulate
from clothbench.model.scene import Cylinder, Plane, Sphere, load_scene
from clothbench.model.solver import PBD_METHODS, Pbd

from conftest import assert_bit_exact, setup
from registry_variants import backend_params, options, shapes_of, usable

AT_60HZ = 1 / 60
STRICT_GRID = 24  # n - 4 = 20: OpenCL's Jacobi interior has whole vectors and leftover columns


def curtain(grid: int):
    """The pinned curtain swinging onto its sphere."""
    return load_scene("curtain").replace(grid=grid)


def three_colliders(grid: int):
    """A sheet held by two corners falls across a cylinder and a sphere onto a tilted floor:
    every collider kind, each touched within 200 steps at 60 Hz (tests/test_pbd_gpu.py checks)."""
    return load_scene("cylinder").replace(
        grid=grid,
        height=0.8,
        cylinders=(Cylinder((0.1, 0.45, 0.3), (0.9, 0.45, 0.3), 0.15),),
        spheres=(Sphere((0.5, 0.4, 0.75), 0.2),),
        planes=(Plane((0.0, 0.2, 0.0), (0.05, 1.0, 0.0)),),
        pin_corners=("top-left", "top-right"),
    )


SCENES = {"curtain": curtain, "three colliders": three_colliders}


@pytest.mark.parametrize("method", PBD_METHODS)
@pytest.mark.parametrize("scene_name", list(SCENES))
@pytest.mark.parametrize("param", backend_params("pbd", needs="strict"))  # a peer has no strict form
def test_strict_pbd_matches_numpy_f32_bit_for_bit_after_200_steps(param, scene_name, method):
    # docs/pbd.md fixes every operation's order; the strict kernels follow it with no
    # contraction and no dot()/length(), so IEEE rounding leaves no room. Jacobi: each end of
    # a constraint keeps its own lambda, and both compute the same bits. Coloured too: within
    # a batch no two constraints share a particle, so the launch order cannot matter.
    # Every kernel shape the backend offers (tuning may pick any): they split the work
    # differently, never the operations on one particle or constraint.
    name, _ = usable(param)
    scene, solver = SCENES[scene_name](STRICT_GRID), Pbd(dt=AT_60HZ, method=method)
    ref_pos, ref_prev = reference(scene, solver, 200, "f32")
    for shape in shapes_of(name, scene, solver):
        pos, prev = simulate(name, scene, solver, 200, options(name, "pbd", strict=True, shape=shape))
        assert_bit_exact(pos, ref_pos, f"{name} {shape} {method} {scene_name} pos")
        assert_bit_exact(prev, ref_prev, f"{name} {shape} {method} {scene_name} prev")


@pytest.mark.parametrize("grid", [4, STRICT_GRID])  # 4: the border code only
@pytest.mark.parametrize("param", backend_params("pbd", needs="strict"))
def test_strict_chebyshev_jacobi_matches_numpy_bit_for_bit(param, grid):
    # the extrapolation y = omega (y - before) + before, of the iterate and of every lambda,
    # in the reference's order, in every kernel shape; the curtain file's PBD settings at 60 Hz
    name, _ = usable(param)
    run = setup("curtain", grid).replace(solver="pbd", method="jacobi", iterations=10, dt=AT_60HZ)
    scene, solver = run.scene, run.solver.replace(chebyshev_rho=0.99)
    ref_pos, ref_prev = reference(scene, solver, 60, "f32")
    for shape in shapes_of(name, scene, solver):
        pos, prev = simulate(name, scene, solver, 60, options(name, "pbd", strict=True, shape=shape))
        assert_bit_exact(pos, ref_pos, f"{name} {shape} n={grid} pos")
        assert_bit_exact(prev, ref_prev, f"{name} {shape} n={grid} prev")


@pytest.mark.parametrize("param", backend_params("pbd", needs="local_size"))
def test_work_group_size_changes_no_strict_bit(param):
    # 7 divides neither n*n nor any batch: launches are padded and the extra items return
    name, _ = usable(param)
    scene = three_colliders(13)
    for method in PBD_METHODS:
        solver = Pbd(dt=AT_60HZ, method=method)
        ref = reference(scene, solver, 30, "f32")[0]
        for shape in shapes_of(name, scene, solver):
            for ls in (7, 128):
                opts = options(name, "pbd", strict=True, local_size=ls, shape=shape)
                pos = simulate(name, scene, solver, 30, opts)[0]
                assert_bit_exact(pos, ref, f"{name} {method} {shape} local size {ls}")
