"""[self_collision] on the OpenCL backend's Verlet, PBD and VBD solvers (kernels/self_collision.cl,
docs/semantics.md "Self-collision"), beyond the contract's default build: strict is the NumPy
float32 reference bit for bit in the generic build, the split kernels, per-step transfer, with
normals and a padded launch, in every PBD method, with VBD's substeps and Chebyshev, and with
colliders, a mesh, motion and attached pins acting after the pass; fast stays within float32's own error; a scene without the
table compiles none of it; only the default kernel shape is offered with it."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.model.kernel_inputs import SelfCollisionConstants
from clothbench.backends.opencl import pbd as opencl_pbd
from clothbench.backends.opencl import verlet as opencl
from clothbench.harness import position_error
from clothbench.harness.health import self_contact
from clothbench.model.scene import SelfCollision
from clothbench.model.solver import Pbd, Vbd
from conftest import VERLET, assert_bit_exact, require
from folded_sheet import crumpled, folded, on_bodies
from test_opencl_meshes import program_sources

STEPS = 20  # the contract's longer run: every pair of the fold pushed, several times
# 1.5 spacings, the fold's layers 0.5 apart: each particle has about five pairs across the fold,
# so the order of its sum shows in the bits (at the contract's 0.8 it has one)
THICK = 1.5


def sheet(n: int = 16):
    return folded(n, thickness=THICK)


def sheet_with_cell(cell: float):
    """The sheet with a search cell of `cell` thicknesses."""
    scene, pos = sheet()
    t = scene.self_collision.thickness
    return scene.replace(self_collision=SelfCollision(thickness=t, cell=cell * t)), pos


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


PBD = {
    "jacobi": Pbd(dt=VERLET.dt),
    "chebyshev": Pbd(dt=VERLET.dt, chebyshev_rho=0.9, iterations=5),  # an odd count: the other buffer last
    "coloured": Pbd(dt=VERLET.dt, method="coloured", substeps=2),
}
VBD = {
    "plain": Vbd(dt=VERLET.dt),
    "chebyshev": Vbd(dt=VERLET.dt, chebyshev_rho=0.9, substeps=2),  # the pass after the last weight, twice a step
}


def run(name: str, scene, pos, steps: int, options: BackendOptions, solver=VERLET):
    with create_backend(name, scene, solver, options) as b:
        b.upload(pos, pos)
        b.advance(steps)
        return b.read()


def assert_matches_numpy(
    scene, pos, options: BackendOptions, what: str, steps: int = STEPS, solver=VERLET, backend: str = "opencl"
):
    got = run(backend, scene, pos, steps, options, solver)
    expected = run("numpy", scene, pos, steps, BackendOptions(), solver)
    assert_bit_exact(got[0], expected[0], f"pos, {what}")
    assert_bit_exact(got[1], expected[1], f"prev, {what}")
    without = run("numpy", scene.replace(self_collision=None), pos, steps, BackendOptions(), solver)[0]
    assert not np.array_equal(expected[0], without), f"{what}: the pass pushed no pair, the test shows nothing"


@pytest.mark.parametrize(
    "n, build",
    [
        (16, {"generic": True}),
        (16, {"transfer": "per-step"}),
        (16, {"normals": True, "local_size": 24}),  # 256 particles in work-groups of 24: a padded launch
        (16, {"generic": True, "local_size": 24}),
        (12, {}),  # narrower than a vector: the split kernels, the border's scalar path included
    ],
    ids=lambda v: str(v),
)
def test_strict_matches_numpy_f32_bit_for_bit_in_every_build(n, build):
    scene, pos = sheet(n)
    assert_matches_numpy(scene, pos, BackendOptions(strict=True, **build), f"n={n} {build}")


@pytest.mark.parametrize("cell", [1.0, 2.5])
def test_strict_matches_numpy_f32_with_cells_larger_than_the_thickness(cell):
    # 2.5 thicknesses: every cell holds several particles of both layers, so the runs merged
    # hold candidates past the thickness that the distance test rejects
    scene, pos = sheet_with_cell(cell)
    for solver in (VERLET, PBD["jacobi"]):
        assert_matches_numpy(scene, pos, BackendOptions(strict=True), f"cell {cell} {solver.name}", solver=solver)


def test_strict_matches_numpy_f32_where_the_cell_keys_are_clamped():
    # 200 km out along every axis the keys pass 2^20 cells and clamp: the whole sheet is in one
    # cell, whose 27 neighbours are that cell again; each candidate is met once
    scene, pos = sheet()
    pos[:, :3] += np.float32(2e5)
    assert float(pos[:, :3].min()) * float(SelfCollisionConstants.of(scene).inv_cell) > 2**20, "keys clamp"
    for solver in (VERLET, PBD["coloured"]):
        assert_matches_numpy(scene, pos, BackendOptions(strict=True), f"clamped {solver.name}", solver=solver)


@pytest.mark.parametrize("solver", [VERLET, PBD["jacobi"]], ids=lambda s: s.name)
def test_strict_holds_where_the_sort_spans_several_local_blocks(solver):
    # 32^2 = 1,024 slots, two blocks of self_sort_local: the stage between them is a global
    # launch, then a local one merges each block (at 16^2 one local launch sorts everything)
    scene, pos = sheet(32)
    with create_backend("opencl", scene, solver, BackendOptions(strict=True)) as b:
        kinds = [kind for kind, _, _ in b._contact.sort_passes]
    assert "stage" in kinds and kinds.count("local") > 1, f"the sort is {kinds}: one block, nothing shown"
    assert_matches_numpy(scene, pos, BackendOptions(strict=True), f"32^2 {solver.name}", steps=5, solver=solver)


@pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])
def test_strict_holds_where_a_particle_has_more_pairs_than_it_sorts_in_private_memory(generic):
    # every particle has dozens of pairs, more than the kernel's SELF_HITS (32): it merges its
    # cells' runs by smallest index instead of sorting the pairs it found
    scene, pos = folded()
    pos = crumpled(scene, pos)
    assert self_contact(pos, scene)[0] > 32 * scene.particles / 2, "the merge is not reached"
    assert_matches_numpy(scene, pos, BackendOptions(strict=True, generic=generic), f"crumpled {generic}", steps=3)


@pytest.mark.parametrize("variant", [*(f"pbd-{m}" for m in PBD), *(f"vbd-{v}" for v in VBD)])
def test_pbd_and_vbd_strict_match_numpy_f32_bit_for_bit_in_every_method(variant):
    solver_name, _, method = variant.partition("-")
    scene, pos = sheet()
    solver = (PBD if solver_name == "pbd" else VBD)[method]
    for build in ({}, {"local_size": 24}):  # 24 does not divide 256: padded launches, the cell keys too
        options = BackendOptions(strict=True, **build)
        assert_matches_numpy(scene, pos, options, f"{variant} {build}", solver=solver)


def bodies_scene():
    return on_bodies(sheet(16))


@pytest.mark.parametrize("build", [{}, {"generic": True}, {"mesh_collision": "naive"}], ids=str)
def test_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit(build):
    scene, pos = bodies_scene()
    assert_matches_numpy(scene, pos, BackendOptions(strict=True, **build), f"bodies {build}", steps=40)


@pytest.mark.parametrize("method", ["jacobi", "coloured"])
def test_pbd_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit(method):
    scene, pos = bodies_scene()
    options = BackendOptions(strict=True)
    assert_matches_numpy(scene, pos, options, f"pbd bodies {method}", steps=40, solver=PBD[method])


def test_vbd_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit():
    scene, pos = bodies_scene()
    options = BackendOptions(strict=True)
    assert_matches_numpy(scene, pos, options, "vbd bodies", steps=40, solver=VBD["chebyshev"])


@pytest.mark.parametrize("generic", [False, True])
def test_fast_error_is_of_the_order_of_strict_float32s(generic):
    # Fast mode contracts FMAs (the pass's d*s + corr too) and uses rsqrt in the springs:
    # O(float32 epsilon) per operation. Held to strict's own distance from float64 (NumPy f64),
    # 3x with a 1 nm floor; measured here (PoCL, 20 steps) 0.95-1.06x, PBD 0.90-1.00x, about
    # 4-40 um. A slip in the pass (a sign, a share) moves a pair by up to the thickness, centimetres.
    scene, pos = sheet()
    ref64 = run("numpy", scene, pos.astype(np.float64), STEPS, BackendOptions(precision="f64"))[0]
    _, strict_max = position_error(run("numpy", scene, pos, STEPS, BackendOptions())[0], ref64)
    fast = run("opencl", scene, pos, STEPS, BackendOptions(generic=generic))[0]
    _, fast_max = position_error(fast, ref64)
    assert fast_max <= 3 * strict_max + 1e-9, f"fast {fast_max:.3g} m, NumPy f32 {strict_max:.3g} m"


@pytest.mark.parametrize("method", [*PBD, "vbd"])
def test_pbd_and_vbd_fast_error_is_of_the_order_of_strict_float32s(method):
    # as for Verlet; PBD's fast constraints take one rsqrt each (fast_math.cl's estimates in
    # the vector interior), VBD's springs one each, O(float32 epsilon) too
    scene, pos, solver = *sheet(), PBD.get(method, VBD["chebyshev"])
    ref64 = run("numpy", scene, pos.astype(np.float64), STEPS, BackendOptions(precision="f64"), solver)[0]
    _, strict_max = position_error(run("numpy", scene, pos, STEPS, BackendOptions(), solver)[0], ref64)
    fast = run("opencl", scene, pos, STEPS, BackendOptions(), solver)[0]
    _, fast_max = position_error(fast, ref64)
    assert fast_max <= 3 * strict_max + 1e-9, f"{method}: fast {fast_max:.3g} m, NumPy f32 {strict_max:.3g} m"


def compiled(scene, generic: bool, solver=VERLET) -> tuple[str, str]:
    """The source and build options of the backend's programs for `scene`."""
    with create_backend("opencl", scene, solver, BackendOptions(generic=generic)) as b:
        if solver is VERLET:
            return program_sources(b), " ".join(o for key in b.key for o in key)
        return b.source if solver.name == "vbd" else b._source, " ".join(b.build_options())


@pytest.mark.parametrize("generic", [False, True])
def test_a_scene_without_self_collision_compiles_none_of_it(generic):
    scene, _ = sheet()
    source, options = compiled(scene, generic)
    assert "self_push" in source and "-DCLOTH_SELF_COLLISION" in options, "the scene with the table has the pass"
    source, options = compiled(scene.replace(self_collision=None), generic)
    assert "self_push" not in source and "CLOTH_SELF_COLLISION" not in options


@pytest.mark.parametrize("solver", [PBD["jacobi"], VBD["plain"]], ids=["pbd", "vbd"])
def test_a_pbd_or_vbd_scene_without_self_collision_compiles_none_of_it(solver):
    scene, _ = sheet()
    source, options = compiled(scene, False, solver)
    assert "self_push" in source and "-DCLOTH_SELF_COLLISION" in options, "the scene with the table has the pass"
    source, options = compiled(scene.replace(self_collision=None), False, solver)
    assert "self_push" not in source and "CLOTH_SELF_COLLISION" not in options


def test_self_collision_offers_the_default_shape_only():
    scene, _ = sheet(32)
    options = BackendOptions(strict=True)
    plain = opencl.OpenCLBackend.kernel_shapes(scene.replace(self_collision=None), options)
    assert len(plain) > 1, "the test needs a grid with several candidates"
    assert opencl.OpenCLBackend.kernel_shapes(scene, options) == plain[:1]
    for solver in PBD.values():
        plain = opencl_pbd.OpenCLPbdBackend.kernel_shapes(scene.replace(self_collision=None), options, solver)
        assert len(plain) > 1 and opencl_pbd.OpenCLPbdBackend.kernel_shapes(scene, options, solver) == plain[:1]
