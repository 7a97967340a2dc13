"""Hard cases 2 and 3: a spring of length 0, and a particle exactly at a sphere's centre.

docs/semantics.md defines both: a zero-length spring has no direction and adds no spring
force (s = 0; a kernel must test L2 > 0 rather than divide 0 by 0), and a particle landing
exactly on a sphere's centre is pushed straight up to c + (0, r, 0).
"""

import numpy as np

from clothbench.harness.energy import energy_problem
from clothbench.model.scene import Scene, Sphere
from hard_case_variants import exact_arithmetic, run_from, variant  # noqa: F401


def test_two_coincident_particles_stay_finite_and_separate(variant):
    # particle 27 placed exactly on its right neighbour 28: their structural spring has L = 0
    scene = Scene(grid=8, pin_edge="top")
    pos, prev = scene.initial_state(np.float64)
    pos[27, :3] = pos[28, :3]
    prev[27, :3] = pos[28, :3]
    out, out_prev = run_from(variant, scene, (pos, prev), 200)
    assert np.isfinite(out[:, :3]).all() and np.isfinite(out_prev[:, :3]).all()
    # healthy: the energy stored by the displacement is only converted, never grown
    assert energy_problem(out, out_prev, scene, variant.solver, 200, start=(pos, prev)) is None
    # the other eleven springs of each pull them apart again, towards rest length
    assert np.linalg.norm(out[27, :3] - out[28, :3]) > 0.5 * scene.spacing


def test_a_sheet_collapsed_to_one_point_falls_as_one_point(variant):
    # every spring has L = 0: no spring force anywhere. Undamped, all particles share one
    # state and fall freely together; the point stays a point, bit for bit.
    scene = Scene(grid=6, damping=0.0)
    pos, prev = scene.initial_state(np.float64)
    pos[:, :3] = prev[:, :3] = (0.5, 1.0, 0.5)
    out, _ = run_from(variant, scene, (pos, prev), 50)
    assert np.isfinite(out[:, :3]).all()
    assert np.ptp(out[:, :3], axis=0).max() == 0.0, "the collapsed sheet came apart"
    assert out[0, 1] < 1.0, "it should fall"


def test_a_collapsed_damped_sheet_springs_apart_finite(variant):
    # damped, an edge particle (fewer springs, less drag) falls faster than an interior one;
    # the point opens and every spring, far shorter than its rest length, pushes it apart
    # hard. Violent, but defined: finite throughout.
    scene = Scene(grid=6)
    pos, prev = scene.initial_state(np.float64)
    pos[:, :3] = prev[:, :3] = (0.5, 1.0, 0.5)
    out, out_prev = run_from(variant, scene, (pos, prev), 50)
    assert np.isfinite(out[:, :3]).all() and np.isfinite(out_prev[:, :3]).all()
    assert np.ptp(out[:, :3], axis=0).max() > 0.0


def test_a_particle_exactly_at_the_sphere_centre_is_pushed_to_the_surface(variant):
    # n = 5, size 1: h = 0.25 and every rest length is exactly the float32 length of its
    # spring, so with no gravity and prev = pos no force acts and particle 12 (the middle one)
    # lands exactly on the sphere's centre. r = 0.1 < h: no other particle is inside.
    scene = Scene(grid=5, gravity=(0.0, 0.0, 0.0), height=0.0, spheres=(Sphere((0.5, 0.0, 0.5), 0.1),))
    pos, prev = scene.initial_state(np.float64)
    out, out_prev = run_from(variant, scene, (pos, prev), 1)
    assert np.isfinite(out[:, :3]).all()
    c, r = np.array(scene.spheres[0].center), scene.spheres[0].radius
    dist = np.linalg.norm(out[12, :3].astype(np.float64) - c)
    assert abs(dist - r) <= 4 * np.spacing(np.float32(r)), f"not on the surface: |x - c| = {dist}"
    if exact_arithmetic(variant):
        # the defined direction for a particle with no direction: straight up
        assert tuple(out[12, :3]) == (0.5, 0.1, 0.5)
    # and the run goes on finite: the pushed particle springs back into the sheet. No energy
    # check here: from a start with no energy at all, the push (a collider's projection is
    # an energy source) is all the energy there is.
    later, _ = run_from(variant, scene, (pos, prev), 100)
    assert np.isfinite(later[:, :3]).all() and np.abs(later[:, :3]).max() < 10.0
