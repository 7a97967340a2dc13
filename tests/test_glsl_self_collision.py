"""[self_collision] on glsl-compute's Verlet, PBD and VBD solvers (kernels/self_collision.glsl and
self_collision.comp, docs/semantics.md "Self-collision"), beyond the contract's default build
(tests/contract/test_self_collision_contract.py): the sort itself against NumPy's; strict is the
NumPy float32 reference bit for bit with several pairs per particle (so the sum's order shows) in
the generic build, with normals, a padded dispatch and SSBO reads, in every PBD method, with VBD's
substeps and Chebyshev, with
cells of 1 and 2.5 thicknesses and clamped keys, and with colliders, a mesh, motion and attached
pins acting after the pass; fast stays within float32's own error; a scene without the table
compiles none of it; only the default kernel shape is offered with it."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.gl import compute, compute_pbd, shapes
from clothbench.errors import ClothbenchError
from clothbench.harness import position_error
from clothbench.model.colliders.self_contact import KEY_LIMIT, cell_keys
from clothbench.model.kernel_inputs import SelfCollisionConstants
from conftest import VERLET, require
from test_opencl_self_collision import PBD, STEPS, VBD, assert_matches_numpy, bodies_scene, run, sheet, sheet_with_cell

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker
NAME = "glsl-compute"


@pytest.fixture(autouse=True)
def _glsl_compute():
    require(NAME)


def assert_exact(scene, pos, what: str, solver=VERLET, steps: int = STEPS, **build):
    options = BackendOptions(strict=True, **build)
    assert_matches_numpy(scene, pos, options, what, steps=steps, solver=solver, backend=NAME)


def test_the_sort_orders_the_particles_by_cell_then_index_as_numpy_does():
    # 900 particles in 1024 slots: the pad slots sort last, after every particle's cell
    scene, pos = sheet(30)
    with create_backend(NAME, scene, VERLET, BackendOptions(strict=True)) as b:
        b.upload(pos, pos)
        b.advance(1)
        with b.gl:
            x_new = np.frombuffer(b.x_new.read(), np.float32).reshape(-1, 4)[:, :3]
            words = np.frombuffer(b.contact.keys.read(), np.uint32).reshape(-1, 2).astype(np.int64)
            order = np.frombuffer(b.contact.order.read(), np.int32)
    k = cell_keys(x_new, SelfCollisionConstants.of(scene).inv_cell) + KEY_LIMIT
    ids = k[:, 0] | (k[:, 1] << 21) | (k[:, 2] << 42)  # OpenCL's one 64-bit id
    expected = np.argsort(ids, kind="stable")
    count, slots = len(ids), len(order)
    assert slots == 1024 and np.array_equal(order[:count], expected), "particles by (cell, index)"
    assert np.array_equal(order[count:], np.arange(count, slots)), "the pad slots last, by index"
    assert np.array_equal(words[:count, 0] | (words[:count, 1] << 32), ids[expected]), "two uints: the same id"


@pytest.mark.parametrize(
    "n, build",
    [
        (16, {}),
        (16, {"generic": True}),
        (16, {"normals": True, "local_size": 24}),  # 256 particles in groups of 24: a padded dispatch
        (12, {"generic": True, "local_size": 24}),
        (4, {}),  # no interior: the step is one dispatch with bounds tests
    ],
    ids=str,
)
def test_strict_matches_numpy_f32_bit_for_bit_in_every_build(n, build):
    scene, pos = sheet(n)
    assert_exact(scene, pos, f"n={n} {build}", **build)


def test_strict_matches_numpy_f32_with_ssbo_reads(monkeypatch):
    # the pass reads x_new through an imageBuffer view where the driver allows; the SSBO too
    monkeypatch.setattr(compute, "PREFER_IMAGE_READS", False)
    monkeypatch.setattr(compute_pbd, "PREFER_IMAGE_READS", False)
    scene, pos = sheet()
    for solver in (VERLET, PBD["jacobi"]):
        assert_exact(scene, pos, f"ssbo reads {solver.name}", solver=solver)


@pytest.mark.parametrize("solver", [VERLET, PBD["jacobi"]], ids=lambda s: s.spec)
@pytest.mark.parametrize("cell", [1.0, 2.5])
def test_strict_matches_numpy_f32_with_cells_larger_than_the_thickness(cell, solver):
    # 2.5 thicknesses: every cell holds several particles of both layers, so the runs merged
    # hold candidates past the thickness that the distance test rejects
    scene, pos = sheet_with_cell(cell)
    assert_exact(scene, pos, f"cell {cell} {solver.name}", solver=solver)


def test_strict_matches_numpy_f32_where_the_cell_keys_are_clamped():
    # 200 km out along every axis the keys pass 2^20 cells and clamp: the whole sheet is in one
    # cell, whose 27 neighbours are that cell again; each candidate is met once
    scene, pos = sheet()
    pos[:, :3] += np.float32(2e5)
    assert float(pos[:, :3].min()) * float(SelfCollisionConstants.of(scene).inv_cell) > 2**20, "keys clamp"
    for solver in (VERLET, PBD["coloured"]):
        assert_exact(scene, pos, f"clamped {solver.name}", solver=solver)


@pytest.mark.parametrize("method", PBD)
def test_pbd_strict_matches_numpy_f32_bit_for_bit_in_every_method(method):
    scene, pos = sheet()
    for build in ({}, {"local_size": 24}):  # 24 does not divide 256: padded dispatches, the sort's too
        assert_exact(scene, pos, f"pbd {method} {build}", solver=PBD[method], **build)


@pytest.mark.parametrize("variant", VBD)
def test_vbd_strict_matches_numpy_f32_bit_for_bit_with_substeps_and_chebyshev(variant):
    scene, pos = sheet()
    for build in ({}, {"local_size": 24}):  # a padded dispatch, the sort's too
        assert_exact(scene, pos, f"vbd {variant} {build}", solver=VBD[variant], **build)


def test_vbd_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit():
    scene, pos = bodies_scene()
    assert_exact(scene, pos, "vbd bodies", steps=40, solver=VBD["chebyshev"])


@pytest.mark.parametrize("build", [{}, {"generic": True}, {"mesh_collision": "naive"}], ids=str)
def test_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit(build):
    scene, pos = bodies_scene()
    assert_exact(scene, pos, f"bodies {build}", steps=40, **build)


@pytest.mark.parametrize("method", ["jacobi", "coloured"])
def test_pbd_colliders_meshes_motion_and_attached_pins_act_after_the_pass_bit_for_bit(method):
    scene, pos = bodies_scene()
    assert_exact(scene, pos, f"pbd bodies {method}", steps=40, solver=PBD[method])


@pytest.mark.parametrize("solver", [VERLET, PBD["jacobi"], PBD["coloured"]], ids=lambda s: s.spec)
def test_fast_error_is_of_the_order_of_strict_float32s(solver):
    # Fast mode may contract the pass's d*s + corr and takes an inversesqrt per spring or
    # constraint: O(float32 epsilon) per operation. Held to NumPy float32's own distance from
    # float64, 3x with a 1 nm floor; a slip in the pass (a sign, a share) moves a pair by up to
    # the thickness, centimetres.
    scene, pos = sheet()
    ref64 = run("numpy", scene, pos.astype(np.float64), STEPS, BackendOptions(precision="f64"), solver)[0]
    _, strict_max = position_error(run("numpy", scene, pos, STEPS, BackendOptions(), solver)[0], ref64)
    _, fast_max = position_error(run(NAME, scene, pos, STEPS, BackendOptions(), solver)[0], ref64)
    assert fast_max <= 3 * strict_max + 1e-9, f"fast {fast_max:.3g} m, NumPy f32 {strict_max:.3g} m"


def compiled(scene, solver=VERLET, **build) -> tuple[str, set[str], int]:
    """The backend's solver programs' sources, the switches the host defines in front of them
    (the lines before the first #line), and how many search programs it built."""
    with create_backend(NAME, scene, solver, BackendOptions(strict=True, **build)) as b:
        heads = [source.split("#line", 1)[0].splitlines() for source in b.sources.values()]
        switches = {line.split()[1] for head in heads for line in head if line.startswith("#define ")}
        return "\n".join(b.sources.values()), switches, 0 if b.contact is None else len(b.contact.programs)


@pytest.mark.parametrize(
    "solver, generic", [(VERLET, False), (VERLET, True), (PBD["jacobi"], False), (VBD["chebyshev"], False)], ids=str
)
def test_a_scene_without_self_collision_compiles_none_of_it(solver, generic):
    scene, _ = sheet()
    source, switches, search = compiled(scene, solver, generic=generic)
    assert "vec3 self_push(" in source and "SELF_COLLISION" in switches and search == 2, "the table has the pass"
    source, switches, search = compiled(scene.replace(self_collision=None), solver, generic=generic)
    assert "vec3 self_push(" not in source and not {s for s in switches if s.startswith("SELF_")} and search == 0


def test_self_collision_offers_the_default_shape_only():
    scene, _ = sheet(32)
    plain = shapes.candidates(scene.replace(self_collision=None), BackendOptions(strict=True))
    assert len(plain) > 1 and "steps/dispatch=16" in plain, "the test needs a grid with several candidates"
    assert shapes.candidates(scene, BackendOptions(strict=True)) == (shapes.DEFAULT_SHAPE,)
    with pytest.raises(ClothbenchError) as e:  # the one-group shape has no dispatch between steps
        create_backend(NAME, scene, VERLET, BackendOptions(strict=True, shape="steps/dispatch=16"))
    assert "steps/dispatch=16" in str(e.value) and "\n" not in str(e.value)
