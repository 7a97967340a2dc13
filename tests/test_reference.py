"""The NumPy reference against closed forms and physical invariants (docs/semantics.md)."""

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.errors import BlowUp
from clothbench.harness import max_penetration, position_error, run_timed, simulate, state_problem
from clothbench.model.scene import Scene, Sphere, load_scene
from clothbench.model.solver import Verlet

from conftest import VERLET, sphere

F32 = BackendOptions(precision="f32")
F64 = BackendOptions(precision="f64")
U32 = 2.0**-24  # unit roundoff of float32


def free_fall_scene(n=16):
    return Scene(grid=n, damping=0.0, height=1.0)


def test_free_fall_matches_verlet_closed_form_in_float64():
    # Verlet from rest: y_S = y0 + a*dt^2 * S(S+1)/2, exactly, in real arithmetic.
    s, steps, dt = free_fall_scene(), 300, VERLET.dt
    pos, _ = simulate("numpy", s, VERLET, steps, F64)
    closed = s.height + s.gravity[1] * dt**2 * steps * (steps + 1) / 2
    assert np.abs(pos[:, 1] - closed).max() < 1e-9


def test_free_fall_in_float32_follows_the_rounded_recurrence_within_the_derived_bound():
    # A flat sheet falls with d.y = 0 on every spring, so y gets no spring force and every
    # particle follows the same scalar float32 recurrence y' = (2y - y_prev) + g*dt2. That
    # recurrence is exact bit for bit below; its distance to the closed form is then bounded
    # by rounding alone: 2y - y_prev is exact (Sterbenz, while falling) and each addition of
    # g*dt2 rounds by at most ulp(y)/2, an error Verlet carries forward with weight (S - s),
    # plus g and dt2 each rounded once (relative 2^-24): in all
    #   |y_S - closed| <= S(S+1)/2 * (ulp(y0)/2 + 3 * 2^-24 * |g| * dt^2).
    s, steps, dt = free_fall_scene(), 300, VERLET.dt
    pos, _ = simulate("numpy", s, VERLET, steps, F32)
    y, yp = np.float32(s.height), np.float32(s.height)
    g_dt2 = np.float32(s.gravity[1]) * np.float32(dt * dt)
    for _ in range(steps):
        y, yp = (np.float32(2) * y - yp) + g_dt2, y
    assert np.all(pos[:, 1] == y), "every particle must follow the scalar float32 recurrence"
    closed = s.height + s.gravity[1] * dt**2 * steps * (steps + 1) / 2
    ulp = np.spacing(np.float32(s.height))
    bound = steps * (steps + 1) / 2 * (ulp / 2 + 3 * U32 * abs(s.gravity[1]) * dt**2)
    assert abs(float(y) - closed) <= bound


def test_sheet_at_rest_length_without_gravity_stays_put():
    # float64: rest lengths are exact to ~1e-16, so nothing moves beyond 1e-9.
    # float32: positions and rest lengths are each rounded once, so a spring's length is
    # wrong by at most eps_L = 2*u*size + 3*u*h; if every spring along a row were wrong the
    # same way the sheet would settle up to n*eps_L away, and a release from rest overshoots
    # an equilibrium by at most a factor 2 (no damping): bound 2*n*eps_L.
    s = Scene(grid=32, damping=0.0, gravity=(0.0, 0.0, 0.0))
    steps = 2000
    start, _ = s.initial_state(np.float64)
    pos64, _ = simulate("numpy", s, VERLET, steps, F64)
    assert np.abs(pos64[:, :3] - start[:, :3]).max() < 1e-9
    pos32, _ = simulate("numpy", s, VERLET, steps, F32)
    eps_l = 2 * U32 * s.size + 3 * U32 * s.spacing
    assert np.abs(pos32[:, :3] - start[:, :3]).max() <= 2 * s.grid * eps_l


def test_no_particle_ends_inside_the_sphere():
    s = sphere(32)
    pos, _ = simulate("numpy", s, VERLET, 600, F32)  # contact starts near step 200
    center = np.array(s.spheres[0].center)
    dist = np.sqrt(((pos[:, :3] - center) ** 2).sum(axis=1))
    assert dist.min() < s.spheres[0].radius + 0.01, "the cloth should be resting on the sphere"
    # the projection c + d*(r/L) rounds; allow a few float32 ulps of r
    assert max_penetration(pos, s) <= 4 * np.spacing(np.float32(s.spheres[0].radius))


def test_sphere_scene_is_mirror_symmetric():
    # sheet and sphere are symmetric under x -> 1 - x (columns reversed); float64, short
    # horizon: the only asymmetry is the summation order of the stencil, ~1e-15 per step.
    s = sphere(24)
    pos, _ = simulate("numpy", s, VERLET, 400, F64)
    grid = pos[:, :3].reshape(s.grid, s.grid, 3)
    mirrored = grid[:, ::-1].copy()
    mirrored[..., 0] = s.size - mirrored[..., 0]
    assert np.abs(grid - mirrored).max() < 1e-9


def test_pinned_particles_never_move():
    s = load_scene("drape").replace(grid=16)
    start, _ = s.initial_state(np.float32)
    pos, prev = simulate("numpy", s, VERLET, 500, F32)
    pinned = s.pinned()
    assert np.array_equal(pos[pinned], start[pinned])
    assert np.array_equal(prev[pinned], start[pinned])
    assert np.abs(pos[:, 1] - start[:, 1]).max() > 0.01  # and the rest of the cloth did move


def test_float32_and_float64_agree_over_a_short_horizon():
    # 100 steps (0.05 s) of the sphere scene: the float32 error is dominated by the rounded
    # Verlet increment of the fall (see the free-fall bound: S(S+1)/2 * ulp/2 ~ 1.5e-4 at
    # S = 100); 2e-4 m allows that and nothing structural.
    s = sphere(32)
    p32, _ = simulate("numpy", s, VERLET, 100, F32)
    p64, _ = simulate("numpy", s, VERLET, 100, F64)
    rms, worst = position_error(p32, p64)
    assert worst < 2e-4
    assert rms > 0  # they are different computations


def test_coincident_particles_stay_finite():
    s = Scene(grid=4, damping=0.01)
    pos, prev = s.initial_state(np.float32)
    pos[5, :3] = pos[6, :3]  # a structural spring of length 0
    prev[5, :3] = prev[6, :3]
    with create_backend("numpy", s, VERLET, F32) as b:
        b.upload(pos, prev)
        b.advance(10)
        out, _ = b.read()
    assert np.isfinite(out).all()


def test_particle_at_sphere_centre_is_pushed_to_the_top():
    s = Scene(grid=3, stiffness=0.0, damping=0.0, gravity=(0, 0, 0), spheres=(Sphere((0.5, 1.0, 0.5), 0.25),))
    pos, prev = s.initial_state(np.float64)  # particle 4 (row 1, col 1) is at (0.5, 1, 0.5)
    with create_backend("numpy", s, VERLET, F64) as b:
        b.upload(pos, prev)
        b.advance(1)
        out, _ = b.read()
    assert np.array_equal(out[4, :3], [0.5, 1.25, 0.5])
    assert np.isfinite(out).all()


def test_a_blow_up_is_detected_with_its_step():
    # dt far past the stability limit 2/omega (omega^2 <= 24 k/m): grows within a few steps
    s, solver = Scene(grid=8, stiffness=1e5), Verlet(dt=2e-3)
    with create_backend("numpy", s, solver, F32) as b, pytest.raises(BlowUp) as err:
        run_timed(b, 200)
    assert 1 <= err.value.step < 200
    # the named step is the first bad one: the step before it is still healthy
    pos, prev = simulate("numpy", s, solver, err.value.step - 1, F32)
    assert state_problem(pos, prev, s, solver, err.value.step - 1) is None


@pytest.mark.parametrize("block", [7, 1])
def test_the_checks_that_go_particle_by_particle_give_the_whole_sheets_answer_in_blocks(block, monkeypatch):
    # max_step_displacement and max_penetration take the sheet in blocks of particles (their
    # temporaries stay small): the largest displacement and its particle (the first of equals,
    # or the first NaN, as np.argmax over the sheet) and the deepest penetration are the sheet's
    from clothbench.harness import energy, health

    from conftest import every_collider_scene

    scene = every_collider_scene(12)
    pos, prev = simulate("numpy", scene, VERLET, 150)
    prev[90, :3] = prev[20, :3]
    pos[[20, 90], :3] = prev[20, :3] + np.float32(0.05)  # two equal largest steps: the first is named

    def whole_sheet(p, q):
        d = np.sqrt(((p[:, :3].astype(np.float64) - q[:, :3]) ** 2).sum(axis=1))
        d[p[:, 3] == 0] = 0.0
        return float(d[np.argmax(d)]), int(np.argmax(d))

    monkeypatch.setattr(health, "PARTICLES_PER_BLOCK", len(pos))
    deepest = max_penetration(pos, scene)
    monkeypatch.setattr(energy, "PARTICLES_PER_BLOCK", block)
    monkeypatch.setattr(health, "PARTICLES_PER_BLOCK", block)
    assert energy.max_step_displacement(pos, prev) == whole_sheet(pos, prev) == (pytest.approx(0.05 * 3**0.5), 20)
    assert max_penetration(pos, scene) == pytest.approx(deepest, rel=1e-12, abs=0.0) and deepest > 0
    pos[[100, 130], 0] = np.nan  # a NaN after the largest step: the first NaN is named
    d, i = energy.max_step_displacement(pos, prev)
    assert np.isnan(d) and i == whole_sheet(pos, prev)[1] == 100
