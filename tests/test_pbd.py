"""The PBD solver's reference (docs/pbd.md): race-free batches, stability, convergence."""

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.model.constraints import DIRECTIONS, coloured_batches
from clothbench.errors import BlowUp, ClothbenchError
from clothbench.harness import max_penetration, run_timed, simulate
from clothbench.model.scene import Scene, count_springs
from clothbench.model.solver import Pbd

from conftest import setup

F32 = BackendOptions(precision="f32")


@pytest.mark.parametrize("n", range(3, 41))
def test_coloured_batches_are_independent_and_complete(n):
    batches = coloured_batches(n)
    assert len(batches) == 12
    seen = set()
    for b in batches:
        touched = np.concatenate([b.i, b.j])
        assert len(np.unique(touched)) == len(touched), f"batch {b.direction}/{b.parity} reuses a particle"
        for i, j in zip(b.i.tolist(), b.j.tolist()):
            key = (min(i, j), max(i, j))
            assert key not in seen, f"constraint {key} is in two batches"
            seen.add(key)
    # every spring of the chapter's count, each seen once instead of from both ends
    assert 2 * len(seen) == count_springs(n)


def test_twelve_colours_are_needed():
    # a lower bound, shown on the graph itself: an interior particle has 12 constraints,
    # which must all have different colours
    n = 9
    centre = 4 * n + 4
    degree = sum(int(np.sum(b.i == centre) + np.sum(b.j == centre)) for b in coloured_batches(n))
    assert degree == 12 == 2 * len(DIRECTIONS)


def curtain_pbd(method, iterations, grid=24, steps=2000):
    """The curtain file stepped by PBD at 60 Hz: a Setup (scene, solver, steps)."""
    curtain = setup("curtain", grid)
    return curtain.replace(solver="pbd", method=method, iterations=iterations, dt=1 / 60, steps=steps)


def structural_strain(pos, s):
    x = pos[:, :3].astype(np.float64).reshape(s.grid, s.grid, 3)
    lengths = np.concatenate(
        [np.linalg.norm(x[:, 1:] - x[:, :-1], axis=2).ravel(), np.linalg.norm(x[1:] - x[:-1], axis=2).ravel()]
    )
    return float(np.abs(lengths / s.spacing - 1).mean())


@pytest.mark.full  # 2000 steps of the curtain
@pytest.mark.parametrize("method", ["jacobi", "coloured"])
def test_pinned_curtain_at_60hz_stays_bounded(method):
    run = curtain_pbd(method, iterations=10)
    s = run.scene
    with create_backend("numpy", s, run.solver, F32) as b:
        result = run_timed(b, run.steps)  # raises BlowUp if it is not
    pos = result.pos
    assert np.isfinite(pos).all()
    start, _ = s.initial_state(np.float32)
    assert np.array_equal(pos[s.pinned()], start[s.pinned()])
    # hangs below its pins, within the sheet's length of them, and outside the sphere
    assert pos[:, 1].max() <= s.height + 1e-6
    assert pos[:, 1].min() > s.height - 2 * s.size
    assert max_penetration(pos, s) < 1e-5


@pytest.mark.parametrize("method", ["jacobi", "coloured"])
def test_constraint_violation_falls_as_iterations_rise(method):
    strains = []
    for iterations in (2, 8, 32):
        run = curtain_pbd(method, iterations, grid=16, steps=120)
        pos, _ = simulate("numpy", run.scene, run.solver, run.steps, F32)
        strains.append(structural_strain(pos, run.scene))
    assert strains[0] > strains[1] > strains[2], strains


def test_verlet_at_the_same_dt_and_stiffness_blows_up():
    run = curtain_pbd("jacobi", 10).replace(solver="verlet", steps=200)
    with create_backend("numpy", run.scene, run.solver, F32) as b, pytest.raises(BlowUp) as err:
        run_timed(b, run.steps)
    assert err.value.step < 50


def test_gauss_seidel_converges_faster_than_jacobi():
    # at equal iterations the coloured form leaves less constraint violation (docs/pbd.md)
    sj, sc = curtain_pbd("jacobi", 8, grid=16, steps=120), curtain_pbd("coloured", 8, grid=16, steps=120)
    pj, _ = simulate("numpy", sj.scene, sj.solver, sj.steps, F32)
    pc, _ = simulate("numpy", sc.scene, sc.solver, sc.steps, F32)
    assert structural_strain(pc, sc.scene) < structural_strain(pj, sj.scene)


def test_free_fall_without_constraints_matches_symplectic_euler():
    # no damping, compliance so large the constraints do nothing: after S substeps of
    # h = dt / substeps, x_S = x0 + g h^2 S(S+1)/2
    s, solver, steps = Scene(grid=4, damping=0.0), Pbd(compliance=(1e30, 1e30, 1e30)), 50
    pos, _ = simulate("numpy", s, solver, steps, BackendOptions(precision="f64"))
    h, substeps = solver.dt / solver.substeps, steps * solver.substeps
    closed = s.height + s.gravity[1] * h**2 * substeps * (substeps + 1) / 2
    assert np.abs(pos[:, 1] - closed).max() < 1e-12


def test_state_round_trips_through_velocity():
    run = curtain_pbd("jacobi", 4, grid=8)
    pos, prev = run.scene.initial_state(np.float64)
    prev[:, 1] += 1e-3  # moving down
    with create_backend("numpy", run.scene, run.solver, BackendOptions(precision="f64")) as b:
        b.upload(pos, prev)
        p2, q2 = b.read()
    np.testing.assert_allclose(q2, prev, atol=1e-15)
    np.testing.assert_array_equal(p2, pos)


def test_backend_without_pbd_says_which_have_it():
    run = curtain_pbd("jacobi", 4, grid=8)
    with pytest.raises(
        ClothbenchError, match=r"has no pbd solver: use --solver verlet( or --solver vbd)? .pbd runs on: numpy"
    ):
        _create_unusual(run)


def _create_unusual(run):
    from clothbench.backends import BACKENDS, availability

    for name, entry in BACKENDS.items():
        if entry.pbd is None and availability(name).usable:
            return create_backend(name, run.scene, run.solver)
    pytest.skip("every usable backend has a pbd solver")


def test_chebyshev_jacobi_at_rho_095_and_10_iterations_stays_bounded():
    # docs/pbd.md: at 10 iterations rho = 0.99 blows up within 300 steps at 60 Hz (curtain
    # and drape, 24^2 and 64^2: steps 35-75), 0.95 does not; run_timed raises BlowUp
    run = curtain_pbd("jacobi", 10, grid=24, steps=300)
    with create_backend("numpy", run.scene, run.solver.replace(chebyshev_rho=0.95), F32) as b:
        result = run_timed(b, run.steps)
    assert max_penetration(result.pos, run.scene) < 1e-5


@pytest.mark.parametrize("rho", [1.0, -0.1, "0.9", True, float("nan")])
def test_chebyshev_rho_outside_0_to_1_is_refused_in_one_line(rho):
    from clothbench.errors import SceneError
    from clothbench.model.scene import setup_from_dict

    with pytest.raises(SceneError) as err:
        setup_from_dict({"sim": {"solver": "pbd"}, "pbd": {"chebyshev_rho": rho}})
    message = str(err.value)
    assert "\n" not in message and "chebyshev_rho must be in [0, 1)" in message, message


def test_cli_refuses_a_bad_chebyshev_rho_in_one_line_and_exit_2(tmp_path, capsys):
    from clothbench.cli import main

    scene = tmp_path / "bad.toml"
    scene.write_text('[sim]\nsolver = "pbd"\n[pbd]\nchebyshev_rho = 1.5\n')
    assert main(["run", "--backend", "numpy", "--scene", str(scene), "--steps", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "chebyshev_rho must be in [0, 1)" in err and "Traceback" not in err, err


def test_chebyshev_weights_follow_wang_2015():
    # omega_1 = 1, omega_2 = 2 / (2 - rho^2), omega_k+1 = 4 / (4 - rho^2 omega_k): falling from
    # omega_2 to 2 / (1 + sqrt(1 - rho^2)), the optimal over-relaxation for spectral radius rho
    rho = 0.9
    omega = Pbd(iterations=60, chebyshev_rho=rho).chebyshev_omega()
    assert omega[0] == 1 and omega[1] == pytest.approx(2 / (2 - rho**2))
    assert all(a >= b for a, b in zip(omega[1:], omega[2:])) and omega[1] > omega[-1]
    assert omega[-1] == pytest.approx(2 / (1 + (1 - rho**2) ** 0.5), rel=1e-9)
    assert Pbd(iterations=5).chebyshev_omega() == (1.0,) * 5
