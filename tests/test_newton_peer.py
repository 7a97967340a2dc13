"""The Newton peer (clothbench/peers/newton.py): the same scene through Newton's XPBD and VBD.

Newton runs its own model (summed Jacobi, contacts as constraints, no drag: docs/newton.md),
so it is held to clothbench's PBD by physics, not bits. Every physics test runs undamped at
20 substeps of 1/1200 s with 2 iterations: Newton's summed Jacobi over 12 springs a particle
is stable only where the compliance term outweighs the inverse mass (h below ~1 ms here,
docs/newton.md), and at this setting both solvers are near the springs' own answer.
"""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.model.constraints import coloured_batches
from clothbench.backends import BACKENDS, BackendOptions, backend_class, create_backend
from clothbench.errors import ClothbenchError
from clothbench.harness.health import max_penetration
from clothbench.harness.simulate import position_error, simulate
from clothbench.peers.newton import stencil_springs
from clothbench.model.scene import load_scene
from clothbench.model.solver import Pbd, Vbd

from conftest import require

STABLE = Pbd(dt=1 / 60, method="coloured", substeps=20, iterations=2)
F64 = BackendOptions(precision="f64")
# Newton (Jacobi, float32) and clothbench's coloured Gauss-Seidel at 20 x 2 differ by 2-5 mm
# on a 16^2 drape after 0.5 s (docs/newton.md); a wrong mapping (gravity along z, rest lengths
# or compliance off, pins free) moves the sheet by decimetres
SAG_TOLERANCE_M = 0.01


def test_the_springs_are_the_stencil_once_each():
    for n in (3, 8, 13):
        springs = stencil_springs(n)
        pairs = {(i, j) for i, j, _ in springs}
        batched = {(min(i, j), max(i, j)) for b in coloured_batches(n) for i, j in zip(b.i, b.j)}
        assert len(springs) == len(pairs) and pairs == batched  # the springs clothbench's PBD solves
        assert all(i < j for i, j in pairs)


def test_newton_is_a_pbd_and_vbd_peer_and_says_so_for_verlet():
    entry = BACKENDS["newton"]
    assert entry.peer and entry.verlet is None and entry.solvers() == ("pbd", "vbd")
    with pytest.raises(ClothbenchError, match="newton has no verlet solver") as e:
        backend_class("newton", "verlet")
    assert "\n" not in str(e.value)


def test_hanging_drape_sags_and_spreads_like_clothbench_pbd():
    require("newton")
    scene = load_scene("drape").replace(grid=16, damping=0.0)
    steps = 30  # 0.5 s: the sheet has fallen and swings
    newton, _ = simulate("newton", scene, STABLE, steps)
    ours, _ = simulate("numpy", scene, STABLE, steps, F64)
    assert abs(newton[:, 1].min() - ours[:, 1].min()) < SAG_TOLERANCE_M, "lowest point (sag)"
    # the sheet starts flat across z = 0..1 and swings down: its depth now (x is held by the pins)
    depth = lambda p: p[:, 2].max() - p[:, 2].min()  # noqa: E731
    assert abs(depth(newton) - depth(ours)) < SAG_TOLERANCE_M, "extent in z"
    assert depth(ours) < 0.5, "the sheet swung down from its flat start"
    assert ours[:, 1].min() < 0.5, "the sheet fell: a sag comparison of a sheet at rest would prove nothing"


def test_pinned_particles_never_move():
    require("newton")
    scene = load_scene("curtain").replace(grid=12, damping=0.0)
    with create_backend("newton", scene, STABLE) as b:
        start, _ = b.initial_state()
        b.upload(start, start)
        b.advance(20)
        pos, _ = b.read()
    pinned = start[:, 3] == 0
    assert pinned.sum() == 12
    np.testing.assert_array_equal(pos[pinned, :3], start[pinned, :3])
    assert np.abs(pos[~pinned, 1] - start[~pinned, 1]).max() > 0.1, "the free cloth moved"


@pytest.mark.full  # Newton's contact kernels are slow to compile cold; the quick tier runs its drape and pins
def test_collisions_keep_the_curtain_outside_the_sphere():
    require("newton")
    scene = load_scene("curtain").replace(grid=16, damping=0.0)
    pos, _ = simulate("newton", scene, STABLE, 30)
    sphere = scene.spheres[0]
    gap = np.linalg.norm(pos[:, :3] - np.array(sphere.center), axis=1) - sphere.radius
    assert gap.min() < 0.02, "the curtain reached the sphere: otherwise this test checks nothing"
    # contacts are constraints relaxed (0.9) inside the iterations, found once a substep: a
    # particle may end a step a little inside; a missed contact would leave it centimetres in
    assert max_penetration(pos, scene) < 1e-3


@pytest.mark.full  # a physics comparison: 0.5 s of the drape in Newton and in NumPy float64 VBD
def test_newton_vbd_hangs_the_drape_as_clothbench_vbd_does():
    # both implicit Euler of the same springs, undamped; at 10 substeps of 10 iterations they are
    # 1.7 mm RMS apart on the 16^2 drape after 0.5 s (contact and convergence differ: docs/newton.md);
    # a wrong mapping (stiffness as compliance, pins free, no colours) is decimetres off
    require("newton")
    scene, solver = load_scene("drape").replace(grid=16, damping=0.0), Vbd(dt=1 / 60, substeps=10, iterations=10)
    newton, _ = simulate("newton", scene, solver, 30)
    ours, _ = simulate("numpy", scene, solver, 30, F64)
    assert position_error(newton, ours)[0] < SAG_TOLERANCE_M
    assert np.array_equal(newton[scene.pinned(), :3], scene.initial_state(np.float32)[0][scene.pinned(), :3])
