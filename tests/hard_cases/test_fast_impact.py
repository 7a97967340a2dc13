"""Hard case 4: a sheet fast enough to cross the sphere in one step.

The collider only sees where a particle lands; one moving at least the sphere's radius per
step can land past the centre and be pushed out through the far side, or jump it entirely
(docs/accuracy.md, "Fast impact"). Expectation: clothbench.harness.energy.fast_impact_warning
flags such a state, the tunnelling it warns about really happens, and an ordinary impact
is not flagged.
"""

import numpy as np

from clothbench.harness.energy import fast_impact_warning, predicted_fast_impact
from clothbench.model.scene import Scene, Sphere
from clothbench.model.solver import Verlet
from conftest import VERLET, setup
from hard_case_variants import run_from, variant  # noqa: F401

BALL = Sphere((0.2, 0.0, 0.2), 0.1)
# 9 x 9 over 0.4 m: the middle particle (40) is right above the centre
SCENE = Scene(grid=9, size=0.4, spheres=(BALL,))
SOLVER = Verlet(dt=1e-3)


def _start(height: float, speed: float):
    scene = SCENE.replace(height=height)
    pos, prev = SOLVER.initial_state(scene, np.float64)
    prev[:, 1] += speed * SOLVER.dt  # moving down at `speed`
    return scene, (pos, prev)


def test_a_sheet_crossing_the_sphere_in_one_step_is_flagged_and_really_tunnels(variant):
    # 300 m/s at dt = 1 ms: 0.3 m per step, past the radius 0.1. From y = 0.55 the middle
    # particle lands at 0.25, then at -0.05: inside the sphere but past its centre, so the
    # projection pushes it out at the bottom (y = -0.1) instead of catching it on top.
    scene, start = _start(0.55, 300.0)
    warning = fast_impact_warning(*start, scene, SOLVER.dt)
    assert warning is not None and "fast impact" in warning and "dt <" in warning
    after, after_prev = run_from(variant, scene, start, 2, SOLVER)
    assert fast_impact_warning(after, after_prev, scene, SOLVER.dt) is not None
    assert after[40, 1] <= BALL.center[1] - 0.99 * BALL.radius, "expected the tunnelling the rule predicts"


def test_an_ordinary_impact_is_not_flagged_and_is_caught(variant):
    # 1 m/s from 5 cm above the top: 1 mm per step, contact after ~40 steps
    scene, start = _start(0.15, 1.0)
    state = start
    for _ in range(10):
        state = run_from(variant, scene, state, 10, SOLVER)
        assert fast_impact_warning(*state, scene, SOLVER.dt) is None
    # the middle particle rests on top of the sphere, not inside or below it
    assert state[0][40, 1] >= BALL.center[1] + BALL.radius - 1e-5


def test_the_rule_predicted_from_a_scene():
    sphere = setup("sphere")
    assert predicted_fast_impact(sphere.scene, sphere.solver) is None  # 1.4 m/s: 0.7 mm/step << 0.3 m
    # dropped from 100 m onto a 1 cm ball: 44 m/s, 2.2 cm per step at dt = 0.5 ms
    far = Scene(height=100.0, spheres=(Sphere((0.5, 0.0, 0.5), 0.01),))
    assert "fast impact" in predicted_fast_impact(far, VERLET)


def test_the_float32_screen_passes_on_every_step_at_the_radius_to_the_exact_scan():
    # fast_impact_warning first screens the state in its own precision (largest_step_squared)
    # and runs the float64 scan only where some step comes within SCREEN_MARGIN of the radius:
    # a float32 particle whose step is the radius to within float32's rounding, just over or
    # just under it, must get the exact scan's verdict, and the screen must see it
    from clothbench.harness import energy

    scene = SCENE.replace(height=0.55)
    r = BALL.radius
    for factor, flagged in ((1.0 + 1e-6, True), (1.0 - 1e-6, False), (1.0 - 1e-2, False)):
        pos, prev = SOLVER.initial_state(scene, np.float32)
        prev[40, :3] = pos[40, :3] + np.float32(factor * r / np.sqrt(3.0))
        d, i = energy.max_step_displacement(pos, prev)
        assert i == 40 and (d >= r) == flagged, factor
        assert (energy.largest_step_squared(pos, prev) >= (1 - energy.SCREEN_MARGIN) * r * r) == (factor > 0.99)
        assert (fast_impact_warning(pos, prev, scene, SOLVER.dt) is not None) == flagged, factor
    pos[[3, 7], 0] = np.nan  # a NaN is passed over by the screen: it never hides a finite step
    prev[40, :3] = pos[40, :3] + np.float32(2 * r)
    assert energy.largest_step_squared(pos, prev) >= 12 * r * r
