"""Accuracy and stability machinery: order fitting, the lattice bound, bisection, energy, CLI."""

import argparse
import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from clothbench.analysis.artefacts import solver_artefacts
from clothbench.analysis.convergence import converged_reference, fit_order, run_accuracy
from clothbench.analysis.lattice import dt_limit, dynamical_matrix, finite_grid_omega2, lattice_omega2
from clothbench.analysis.stability import (
    DT_60HZ,
    is_stable,
    measure_stability_limit,
    stability_problem,
    stability_scene,
    stability_state,
)
from clothbench import environment
from clothbench.backends import BackendOptions
from clothbench.cli import main
from clothbench.harness import simulate
from clothbench.harness import energy
from clothbench.harness.energy import energy_problem, total_energy, watched_energy
from clothbench.harness.plan import Variant, plan_variants
from clothbench.model.scene import OFFSETS, Scene, load_scene
from clothbench.model.solver import Pbd
from conftest import VERLET, require, setup

F64 = Variant("numpy", BackendOptions(precision="f64"), VERLET, "f64")
# ten passes in one substep: the setting these checks were measured with (not the default)
PBD_F32 = Variant("numpy", BackendOptions(precision="f32"), Pbd(method="jacobi", iterations=10, substeps=1), "f32")
PBD_F64 = Variant("numpy", BackendOptions(precision="f64"), Pbd(method="coloured", iterations=10, substeps=1), "f64")
# how the default PBD's iterations and substeps appear in labels: '1itx10'
DEFAULT_IT = f"{Pbd().iterations}it" + (f"x{Pbd().substeps}" if Pbd().substeps > 1 else "")


@pytest.mark.parametrize("order", [1.0, 2.0, 4.0])
def test_fit_order_recovers_the_order_of_a_synthetic_series(order):
    dts = [1e-3 / 2**i for i in range(5)]
    errors = [3.0 * dt**order * (1 + 0.01 * (-1) ** i) for i, dt in enumerate(dts)]
    assert fit_order(dts, errors) == pytest.approx(order, abs=0.02)


def test_fit_order_needs_two_points_and_ignores_bad_ones():
    assert math.isnan(fit_order([1e-3], [1e-4]))
    assert fit_order([1e-3, 5e-4, 2.5e-4], [4e-6, 1e-6, float("nan")]) == pytest.approx(2.0)


def test_flat_lattice_frequencies_by_hand():
    # q = (pi, pi): only structural springs see a phase (1 - cos pi = 2), 2 x 2 per axis: 4 k/m
    d = dynamical_matrix(np.array([math.pi, math.pi]))
    assert np.allclose(d, np.diag([4.0, 0.0, 4.0]))
    # q = (pi, 0): structural along x (4) and all four shear springs (4 x 2 x 1/2 per axis)
    d = dynamical_matrix(np.array([math.pi, 0.0]))
    assert np.allclose(d, np.diag([8.0, 0.0, 4.0]))


def test_lattice_bound_lies_between_the_hand_values_and_gershgorin():
    w2 = lattice_omega2()
    assert w2 == pytest.approx(10.25, abs=1e-6)  # 41/4, at q = (pi, 1.32) and its mirrors
    assert 8.0 < w2 < 24.0
    assert lattice_omega2(1.5) > w2  # tension adds transverse stiffness


def test_a_finite_free_grid_is_softer_than_the_infinite_lattice():
    values = [finite_grid_omega2(n) for n in (6, 10, 14)]
    assert values == sorted(values) and values[-1] < lattice_omega2()


def test_damped_limit_matches_the_scalar_recurrence():
    # x' = 2x - x_p - (w dt)^2 x - beta dt (x - x_p): 1 % under the limit bounded, 1 % over grows
    w, beta = 1000.0, 300.0
    limit = dt_limit(w, beta)
    assert limit < 2 / w
    for factor, grows in ((0.99, False), (1.01, True)):
        dt = factor * limit
        x, xp = 1.0, 1.0
        for _ in range(5000):
            x, xp = (2 - (w * dt) ** 2 - beta * dt) * x - (1 - beta * dt) * xp, x
        assert (abs(x) > 1e3) == grows


def test_bisection_brackets_the_flat_lattice_limit_within_10_percent():
    row = measure_stability_limit(F64, "flat", 1000.0, steps=1000, grid=16, rtol=0.01)
    assert row.dt_stable < row.dt_unstable <= 1.011 * row.dt_stable
    assert abs(row.ratio - 1) < 0.10
    # a finite grid is softer, so the measured limit is at or above the infinite lattice's
    assert row.dt_unstable >= row.predicted


def test_stability_scenes_start_in_equilibrium_where_they_claim_to():
    for kind in ("flat", "stretched"):
        scene = stability_scene(kind, 1000.0, grid=12)
        assert scene.gravity == (0.0, 0.0, 0.0)
    stretched = stability_scene("stretched", 1000.0, grid=12)
    assert len(stretched.pinned()) == 12 * 12 - 8 * 8  # a border two particles deep


def test_converged_reference_of_a_short_drape():
    drape = setup("drape", 8)
    ref = converged_reference(drape.scene, drape.solver, 0.02, 2.5e-4)
    assert ref.converged and ref.order == pytest.approx(1.0, abs=0.1)  # start = rest
    assert ref.uncertainty < 1e-8


def test_energy_of_free_fall_is_constant_and_a_blow_up_is_caught():
    # flat sheet, b = 0, no pins: no spring stretches, gravity is linear, so the averaged
    # potential makes Verlet's energy exact to float64 rounding
    scene = Scene(grid=8, damping=0.0)
    e0 = total_energy(*VERLET.initial_state(scene), scene, VERLET.dt).total
    pos, prev = simulate("numpy", scene, VERLET, 300, BackendOptions(precision="f64"))
    assert total_energy(pos, prev, scene, VERLET.dt).total == pytest.approx(e0, abs=1e-9)
    assert energy_problem(pos, prev, scene, VERLET, 300) is None
    pos = pos.copy()
    pos[5, :3] += 10.0  # one particle 10 m off in one step: 2e4 m/s, springs torn
    assert "total energy grew" in energy_problem(pos, prev, scene, VERLET, 300)


@pytest.mark.parametrize("block_rows", [64, 4, 1])
def test_the_energy_is_its_sum_over_particles_and_springs_written_out(block_rows, monkeypatch):
    # the definitions of harness/energy.py, one particle and one spring at a time, on a random
    # state with a pinned row (pins hold no kinetic or gravitational energy; their springs
    # count): the vectorised sums, over blocks of rows (one block; blocks whose springs reach
    # into the next two; a row each), agree to float64 rounding
    monkeypatch.setattr(energy, "BLOCK_ROWS", block_rows)
    scene = Scene(grid=9, pin_edge="top")
    rng = np.random.default_rng(3)
    pos, prev = VERLET.initial_state(scene)
    free = pos[:, 3] != 0
    pos[free, :3] += 0.01 * rng.standard_normal((int(free.sum()), 3))
    prev[free, :3] += 0.01 * rng.standard_normal((int(free.sum()), 3))
    n, m, k, dt, g = scene.grid, scene.mass, scene.stiffness, VERLET.dt, np.array(scene.gravity)
    kinetic = sum(0.5 * m * np.sum(((pos[i, :3] - prev[i, :3]) / dt) ** 2) for i in range(n * n) if free[i])
    gravity = sum(-m * g @ (0.5 * (pos[i, :3] + prev[i, :3])) for i in range(n * n) if free[i])
    spring = 0.0
    for (dr, dc), rest in zip(OFFSETS, scene.rest_lengths()):
        for r in range(n):
            for c in range(n):
                if 0 <= r + dr < n and 0 <= c + dc < n:  # each spring from both ends: half of each
                    i, j = r * n + c, (r + dr) * n + c + dc
                    stretch = np.linalg.norm(pos[j, :3] - pos[i, :3]) - rest
                    stretch_prev = np.linalg.norm(prev[j, :3] - prev[i, :3]) - rest
                    spring += 0.25 * k * stretch * stretch_prev
    e = total_energy(pos, prev, scene, dt)
    assert (e.kinetic, e.gravity, e.spring) == pytest.approx((kinetic, gravity, spring), rel=1e-12)
    # the check's energy: every term for Verlet; PBD's leaves the springs out (not computed)
    assert watched_energy(pos, prev, scene, VERLET) == e
    unwatched = watched_energy(pos, prev, scene, Pbd(dt=dt))
    assert (unwatched.kinetic, unwatched.gravity) == (e.kinetic, e.gravity) and math.isnan(unwatched.spring)
    assert unwatched.watched(Pbd(dt=dt)) == e.watched(Pbd(dt=dt))


def test_the_blow_up_check_weighs_a_float32_state_in_float32_to_a_millionth():
    # the check's energy (watched_energy) is computed in the state's precision, its sums in
    # float64: a float32 state's is float32 arithmetic, measured here against the float64
    # evaluation of the same bits on a moving, stretched 64^2 sheet: each term within 1e-6 of
    # the energy the state holds (|kinetic| + |spring| + |gravity|; 8.5e-8 measured). Near the
    # check's limit that is of the order of its margin, one energy scale (ENERGY_GROWTH), so the
    # verdict moves only for a state within a millionth of the limit
    scene = Scene(grid=64, pin_edge="top")
    rng = np.random.default_rng(5)
    pos, prev = VERLET.initial_state(scene, np.float32)
    free = pos[:, 3] != 0
    pos[free, :3] += (0.002 * rng.standard_normal((int(free.sum()), 3))).astype(np.float32)
    prev[free, :3] += (0.002 * rng.standard_normal((int(free.sum()), 3))).astype(np.float32)
    exact = total_energy(pos, prev, scene, VERLET.dt)
    checked = watched_energy(pos, prev, scene, VERLET)
    assert checked != exact  # float32 arithmetic: not the float64 bits
    held = abs(exact.kinetic) + abs(exact.spring) + abs(exact.gravity)
    for a, b in zip((checked.kinetic, checked.spring, checked.gravity), (exact.kinetic, exact.spring, exact.gravity)):
        assert abs(a - b) < 1e-6 * held
    assert watched_energy(pos.astype(np.float64), prev.astype(np.float64), scene, VERLET) == exact


def _assert_measured_here(rows: list[dict], since: str) -> None:
    """Every row of a study's CSV records this machine and commit, as a sweep row does, and
    when: between `since` (a timestamp before the study) and now."""
    here = environment.machine()
    for column in ("cpu", "cores", "python", "packages", "env", "git_commit"):
        assert {r[column] for r in rows} == {here[column]}, column
    assert all(since <= r["timestamp"] <= environment.timestamp() for r in rows)


def test_the_row_classes_end_with_the_columns_environment_collects():
    # environment.with_columns declares them once: a row writes what collect() returns
    from dataclasses import fields

    from clothbench.analysis.convergence import AccuracyRow
    from clothbench.analysis.stability import StabilityRow

    assert tuple(environment.collect()) == environment.COLUMNS
    # VBD's columns came after the machine columns (with_columns' `after`): an older file lacks
    # only its last columns
    for row_class, after in ((AccuracyRow, ("vs_exact_rms", "vs_exact_max")), (StabilityRow, ())):
        names = tuple(f.name for f in fields(row_class))
        assert names[len(names) - len(environment.COLUMNS) - len(after) :] == environment.COLUMNS + after, row_class


def test_numpy_variants_are_f32_and_f64():
    variants, _ = plan_variants(["numpy"])
    assert [v.options.precision for v in variants] == ["f64", "f32"]  # the float64 reference first


def test_accuracy_cli_writes_a_csv_and_both_plots(tmp_path, capsys):
    out = tmp_path / "acc.csv"
    argv = ["accuracy", "--backends", "numpy", "--grid", "8", "--time", "0.02", "--levels", "3", "--out", str(out)]
    since = environment.timestamp()
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "fitted convergence order: numpy f64: 1.0" in text  # start = rest: first order
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2 * 3 and {r["label"] for r in rows} == {"numpy f32", "numpy f64"}
    assert all(float(r["disc_rms"]) > 0 and float(r["ms_per_sim_s"]) > 0 for r in rows)
    _assert_measured_here(rows, since)
    for png in ("acc-speed.png", "acc-convergence.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_accuracy_rows_name_the_driver_that_ran_them_and_an_older_file_still_reads(tmp_path, capsys):
    from clothbench.backends import availability
    from clothbench.reports.results_files import analysis_rows, read_results

    require("c")
    out = tmp_path / "acc.csv"
    argv = ["accuracy", "--backends", "c", "--grid", "8", "--time", "0.02", "--levels", "3", "--out", str(out)]
    assert main(argv) == 0
    rows = list(csv.DictReader(open(out)))
    assert {r["driver"] for r in rows} == {availability("c").driver} != {""}  # the compiler that built each
    # the same file without the column (written before it was): read, its driver empty
    older = tmp_path / "older.csv"
    with older.open("w", newline="") as f:
        columns = [c for c in rows[0] if c != "driver"]
        writer = csv.DictWriter(f, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    read = analysis_rows(read_results(older))
    assert [r.driver for r in read] == [""] * len(rows) and [r.label for r in read] == [r["label"] for r in rows]


def test_stability_cli_prints_measured_beside_predicted(tmp_path, capsys):
    out = tmp_path / "stab.csv"
    argv = [
        "stability",
        "--backends",
        "numpy",
        "--stiffness",
        "1000",
        "--scenes",
        "flat",
        "--grid",
        "10",
        "--steps",
        "300",
        "--out",
        str(out),
    ]
    since = environment.timestamp()
    assert main(argv) == 0
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2
    for r in rows:
        assert abs(float(r["ratio"]) - 1) < 0.1
    _assert_measured_here(rows, since)
    assert (tmp_path / "stab.png").exists()
    assert "numpy f64" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["accuracy", "--backends", "numpy", "--time", "0.0123"], "not a whole number of steps"),
        (["accuracy", "--backends", "numpy", "--dts", "1e-3,x"], "--dts must be comma-separated"),
        (["stability", "--backends", "numpy", "--stiffness", "-5"], "--stiffness must be positive"),
        (["stability", "--backends", "numpy", "--scenes", "wavy"], "unknown stability scene 'wavy'"),
        (["accuracy", "--backends", "numpy", "--solvers", "verlet,xpbd"], "--solvers takes verlet, pbd"),
        (["stability", "--backends", "numpy", "--solvers", "pbd", "--pbd-methods", "sor"], "--pbd-methods takes"),
        (["stability", "--backends", "numpy", "--solvers", "pbd", "--pbd-iterations", "0"], "--pbd-iterations must"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


@pytest.mark.parametrize(
    "committed, argv, lacks",
    [
        ("accuracy-drape.csv", ["accuracy", "--backends", "numpy", "--grid", "8"], "lacks driver, cores, python"),
        ("stability.csv", ["stability", "--backends", "numpy", "--grid", "8"], "lacks cpu, cores"),
    ],
)
def test_resuming_a_study_csv_older_than_the_machine_columns_says_which_it_lacks(
    committed, argv, lacks, tmp_path, capsys
):
    old = tmp_path / committed
    old.write_bytes((Path(__file__).resolve().parents[1] / "results" / committed).read_bytes())
    assert main([*argv, "--out", str(old), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "has other columns than this clothbench writes" in err and lacks in err and err.count("\n") == 1
    assert old.read_bytes() == (Path(__file__).resolve().parents[1] / "results" / committed).read_bytes()


# --- the solver dimension: Verlet against PBD (docs/accuracy.md, "Verlet or PBD") --------


def test_pbd_variants_come_from_each_backends_pbd_class():
    from clothbench.cli.accuracy import solvers_from_args

    args = argparse.Namespace(solvers="verlet,pbd", pbd_methods="jacobi,coloured", pbd_iterations=[10, 4])
    solvers = solvers_from_args(args, VERLET, Pbd())
    variants, skipped = plan_variants(["numpy"], solvers)
    pbd = [v for v in variants if v.solver.name == "pbd"]
    assert len(variants) == 2 + 2 * 2 * 2 and len(pbd) == 8 and not skipped
    assert {(v.solver.method, v.solver.iterations) for v in pbd} == {
        ("jacobi", 10),
        ("jacobi", 4),
        ("coloured", 10),
        ("coloured", 4),
    }
    assert pbd[0].solver.name == "pbd" and variants[0].solver.name == "verlet"
    f32 = [v for v in variants if v.options.precision == "f32"]
    assert f32[1].name == "numpy f32/pbd-jacobi/10it" + (f"x{Pbd().substeps}" if Pbd().substeps > 1 else "")
    assert f32[0].name == "numpy f32"  # Verlet labels are as before


def test_a_backend_without_a_pbd_class_is_skipped_and_said(monkeypatch):
    import clothbench.harness.plan as plan
    from clothbench.backends import Availability

    monkeypatch.setitem(plan.BACKENDS, "numpy", dataclasses.replace(plan.BACKENDS["numpy"], pbd=None))
    monkeypatch.setattr(plan, "availability", lambda name: Availability(True))
    variants, skipped = plan.plan_variants(["numpy"], (Pbd(),))
    assert variants == [] and skipped == [("numpy (pbd)", "numpy has no pbd solver")]


def test_pbd_stays_stable_where_verlet_explodes_at_the_same_stiffness():
    verlet = measure_stability_limit(F64, "flat", 1000.0, steps=300, grid=10, rtol=0.02, check_60hz=True)
    pbd = measure_stability_limit(PBD_F32, "flat", 1000.0, steps=300, grid=10, check_60hz=True)
    assert verlet.dt_stable < 2.2e-3 and not verlet.capped  # the explicit limit, ~2/omega
    assert pbd.dt_stable > verlet.dt_unstable
    assert pbd.dt_stable >= DT_60HZ and pbd.capped and pbd.cap == pytest.approx(0.1)
    assert pbd.solver == "pbd" and pbd.predicted is None and "stable up to the cap" in pbd.note
    assert verlet.stable_at_60hz is False and verlet.at_60hz.startswith("unstable (step <=")
    assert pbd.stable_at_60hz is True


def test_pbd_from_a_strained_start_is_not_called_a_blow_up_but_an_explosion_is():
    # the crumpled sheet springs open: motion from the strain energy it held, not a blow-up.
    # The harness's PBD check (kinetic + gravity against a scale without strain energy)
    # would call this unstable at step 10.
    scene = stability_scene("crumpled", 1e5, grid=8)
    solver = Pbd(dt=1e-3)
    start = stability_state(scene, "crumpled")
    assert energy_problem(*_run(scene, solver, start, 10), scene, solver, 10, start=start) is not None
    assert is_stable(PBD_F64, scene, solver, start, 100, chunk=10)[0]
    pos, prev = start[0].copy(), start[1].copy()
    assert stability_problem(pos, prev, scene, solver, 1, start) is None
    pos[3, :3] += 5.0  # 5 m in one 1 ms step: 5 km/s
    assert "grew" in stability_problem(pos, prev, scene, solver, 1, start)


def _run(scene, solver, start, steps):
    from clothbench.backends import create_backend

    with create_backend("numpy", scene, solver, PBD_F64.options) as b:
        b.upload(*start)
        b.advance(steps)
        return b.read()


def test_a_cap_stops_the_bisection_and_a_cap_above_the_limit_does_not_move_it():
    flat = measure_stability_limit(F64, "flat", 1000.0, steps=200, grid=10, rtol=0.02)
    low = measure_stability_limit(F64, "flat", 1000.0, steps=200, grid=10, rtol=0.02, cap=1e-3)
    assert low.capped and low.dt_stable == 1e-3 and low.probes == 1
    high = measure_stability_limit(F64, "flat", 1000.0, steps=200, grid=10, rtol=0.02, cap=5e-3)
    assert not high.capped and high.dt_stable == pytest.approx(flat.dt_stable, rel=0.03)


@pytest.mark.full  # a physics study: 2,000 XPBD steps at four iteration counts
def test_undamped_xpbd_converges_to_the_mass_spring_answer():
    # XPBD with compliance 1/k is implicit in the same springs: as dt -> 0 (at fixed
    # iterations) its answer tends to Verlet's. With b = 0 the damping forms cannot differ.
    scene = load_scene("drape").replace(grid=8, damping=0.0)
    result = run_accuracy(scene, [PBD_F64], [5e-4, 2.5e-4], 0.08, pbd_dts=[2e-3, 1e-3])
    (diff,) = result.differences
    assert diff.a == "verlet" and diff.b == "pbd-coloured/10it" and diff.converged
    coarse = max(r.disc_rms for r in result.rows)
    assert math.isfinite(diff.rms) and diff.rms < coarse / 20  # the models agree far below PBD's dt error
    assert all(r.solver == "pbd" and r.ref_model == "pbd-coloured/10it" for r in result.rows)


def test_accuracy_cli_puts_both_solvers_in_one_csv_and_states_the_model_difference(tmp_path, capsys):
    out = tmp_path / "both.csv"
    argv = [
        "accuracy",
        "--backends",
        "numpy",
        "--solvers",
        "verlet,pbd",
        "--pbd-methods",
        "jacobi",
        "--grid",
        "8",
        "--time",
        "0.02",
        "--levels",
        "2",
        "--pbd-dts",
        "0.004,0.002",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    rows = list(csv.DictReader(open(out)))
    assert {r["solver"] for r in rows} == {"verlet", "pbd"}
    pbd = [r for r in rows if r["solver"] == "pbd"]
    assert len(pbd) == 2 * 2 and {r["pbd_method"] for r in pbd} == {"jacobi"}
    assert {r["iterations"] for r in pbd} == {str(Pbd().iterations)}
    assert {float(r["dt"]) for r in pbd} == {0.004, 0.002}
    assert all(r["ref_model"].startswith(f"pbd-jacobi/{DEFAULT_IT}") for r in pbd)
    assert all(r["ref_model"] == "verlet" and r["pbd_method"] == "" for r in rows if r["solver"] == "verlet")
    # PBD's error is against its own converged model, and also written against Verlet's
    assert all(float(r["disc_rms"]) > 0 and float(r["vs_verlet_rms"]) > 0 for r in pbd)
    assert len({r["label"] for r in rows}) == 4  # numpy f32, f64 and their two PBD lines
    line = next(t for t in text.splitlines() if t.startswith("converged models differ"))
    assert f"verlet vs pbd-jacobi/{DEFAULT_IT}" in line
    assert math.isfinite(float(line.split("RMS ")[1].split(" m")[0]))
    assert (
        f"fitted convergence order: numpy f64/pbd-jacobi/{DEFAULT_IT}: 1.0" in text
    )  # first order, as Verlet's rest start
    assert (tmp_path / "both-speed.png").read_bytes()[:4] == b"\x89PNG"


def test_stability_cli_shows_both_solvers_side_by_side_and_marks_60hz(tmp_path, capsys):
    out = tmp_path / "stab.csv"
    argv = [
        "stability",
        "--backends",
        "numpy",
        "--solvers",
        "verlet,pbd-jacobi",  # the sweep's spelling
        "--stiffness",
        "1000",
        "--scenes",
        "flat",
        "--grid",
        "8",
        "--steps",
        "150",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    text = capsys.readouterr().out
    rows = list(csv.DictReader(open(out)))
    by_solver = {s: [r for r in rows if r["solver"] == s] for s in ("verlet", "pbd")}
    assert len(by_solver["verlet"]) == 2 and len(by_solver["pbd"]) == 2
    assert {r["pbd_method"] for r in by_solver["pbd"]} == {"jacobi"}
    assert all(r["stable_at_60hz"] == "False" for r in by_solver["verlet"])
    assert all(r["stable_at_60hz"] == "True" and r["capped"] == "True" for r in by_solver["pbd"])
    verlet_worst = max(float(r["dt_unstable"]) for r in by_solver["verlet"])
    assert min(float(r["dt_stable"]) for r in by_solver["pbd"]) > verlet_worst
    assert "side by side" in text and ">=0.1" in text
    assert "Verlet explodes in 2 of 2 runs and PBD stays stable in 2 of 2" in text


@pytest.mark.full  # a physics study of PBD's iteration counts and steps
def test_pbd_is_softer_at_few_iterations_and_damps_at_a_large_step():
    drape = setup("drape", 6)
    verlet, few, many = solver_artefacts(drape.scene, drape.pbd, ("coloured",), (2, 30), (DT_60HZ,))
    assert verlet.model == "verlet" and abs(verlet.energy_change) < 1e-3  # symplectic: keeps its energy
    assert few.strain_ratio > 5 and many.strain_ratio < 1.5  # unresolved constraints stretch
    assert few.settle_speed < 0.05 and verlet.settle_speed < 0.05  # at rest when the strain is read
    assert many.energy_change < -0.1  # resolved constraints, still damped by the 1/60 s step


# --- the figures (reports/accuracy_plots.py) -------------------------------------------------


def accuracy_rows() -> list:
    """Four dts of 14 backend modes, Verlet and PBD, every platform: more than a panel holds."""
    from clothbench.analysis.convergence import AccuracyRow

    modes = [
        ("numpy", "f32"),
        ("numpy", "f64"),
        ("opencl", "strict"),
        ("opencl", "fast"),
        ("glsl", "strict"),
        ("glsl-compute", "fast"),
        ("cuda", "swap"),
        ("taichi", "fast"),
        ("warp", "default"),
        ("numba", "fast"),
    ]
    rows = []
    for i, (backend, mode) in enumerate(modes):
        for solver, method in [("verlet", "")] + (
            [("pbd", "jacobi"), ("pbd", "coloured")] if backend == "opencl" else []
        ):
            label = f"{backend} {mode}" + (f"/pbd-{method}/10it" if method else "")
            for dt in (2e-3, 1e-3, 5e-4, 2.5e-4):
                rows.append(
                    AccuracyRow(
                        scene="drape",
                        grid=8,
                        start="rest",
                        damping=0.002,
                        time_s=0.1,
                        backend=backend,
                        label=label,
                        mode=mode,
                        device="cpu",
                        dt=dt,
                        steps=round(0.1 / dt),
                        solver=solver,
                        pbd_method=method,
                        ms_per_sim_s=(1 + i) * 1e-3 / dt * (10 if method else 1),
                        disc_rms=dt * (1 + 0.1 * i),
                        impl_rms=1e-7,
                        order=1.0,
                    )
                )
    return rows


@pytest.mark.full  # every figure of a committed accuracy run
def test_accuracy_figures_split_by_platform_mark_peers_and_label_the_front(tmp_path):
    from types import SimpleNamespace

    from clothbench.reports.accuracy_plots import convergence_chart, plot_speed_vs_error, speed_vs_error_chart
    from clothbench.reports.figures_common import FRONT_TOLERANCE, MAX_SERIES, pareto_front

    result = SimpleNamespace(rows=accuracy_rows(), differences=[])
    speed = speed_vs_error_chart(result)
    titles = list(speed.panels)
    assert titles == ["every run", "CPU (numpy, c)", "OpenCL", "GL", "CUDA", "peers"]
    assert all(len(labels) <= MAX_SERIES for labels in speed.panels.values())
    assert sum(len(v) for k, v in speed.panels.items() if k != "every run") == 14  # every line, once
    assert set(speed.panels["peers"]) == {"taichi fast (peer)", "warp default (peer)", "numba fast (peer)"}
    front = pareto_front(
        result.rows, cost=lambda r: r.ms_per_sim_s, error=lambda r: r.disc_rms, tolerance=FRONT_TOLERANCE
    )
    assert speed.fronts["every run"] == [f"{r.label}, dt {r.dt * 1e3:.3g} ms" for r in front]
    assert speed.fronts["every run"][0] == "numpy f32, dt 0.25 ms"  # the most accurate, at the smallest dt
    drawn = {t.get_text() for t in speed.figure.axes[0].texts}
    assert set(speed.fronts["every run"]) <= drawn
    peers = speed.figure.axes[titles.index("peers")]
    for line in peers.get_lines():
        if not line.get_label().startswith("_") and "Pareto" not in line.get_label():
            assert line.get_linestyle() == "--" and line.get_markerfacecolor() == "white"
    opencl = speed.figure.axes[titles.index("OpenCL")]
    styles = {line.get_label(): line.get_linestyle() for line in opencl.get_lines()}
    assert styles["opencl fast"] == "-" and styles["opencl fast/pbd-jacobi/10it"] == "-."
    convergence = convergence_chart(result)
    assert list(convergence.panels) == titles[1:]  # no overview: a panel per platform
    assert all(len(labels) <= MAX_SERIES for labels in convergence.panels.values())
    plot_speed_vs_error(result, tmp_path / "acc-speed.png")
    assert (tmp_path / "acc-speed.png").read_bytes()[:4] == b"\x89PNG"
    assert "<svg" in (tmp_path / "acc-speed.svg").read_text()[:2000]


def test_stability_map_has_a_panel_per_scene_with_pbd_as_its_worst_backend(tmp_path):
    from clothbench.analysis.stability import StabilityRow
    from clothbench.reports.accuracy_plots import plot_stability_map, stability_map_chart
    from clothbench.reports.figures_common import MAX_SERIES

    rows = []
    for kind in ("flat", "crumpled"):
        for k in (1000.0, 10000.0):
            for backend, label in (("numpy", "numpy f32"), ("opencl", "opencl fast"), ("glsl", "glsl fast")):
                rows.append(
                    StabilityRow(
                        kind,
                        k,
                        0.002,
                        10,
                        300,
                        backend,
                        label,
                        0.06 / math.sqrt(k),
                        0.061 / math.sqrt(k),
                        None,
                        0.06 / math.sqrt(k),
                        0.04 / math.sqrt(k),
                        10,
                    )
                )
                dt = 0.1 if backend != "glsl" else 0.05  # one backend's PBD is worse: the panel shows that one
                rows.append(
                    StabilityRow(
                        kind,
                        k,
                        0.002,
                        10,
                        300,
                        backend,
                        f"{label}/pbd-jacobi/10it",
                        dt,
                        math.nan,
                        None,
                        0.06 / math.sqrt(k),
                        0.04 / math.sqrt(k),
                        10,
                        solver="pbd",
                        pbd_method="jacobi",
                        iterations=10,
                        capped=dt == 0.1,
                        cap=0.1,
                    )
                )
    chart = stability_map_chart(rows)
    assert list(chart.panels) == ["flat", "crumpled"]
    assert all(len(labels) <= MAX_SERIES for labels in chart.panels.values())
    assert chart.panels["flat"] == [
        "Verlet, CPU (numpy, c) (1 mode)",
        "Verlet, OpenCL (1 mode)",
        "Verlet, GL (1 mode)",
        "PBD jacobi (10 it): smallest of 3 backend modes",
    ]
    pbd = next(line for line in chart.figure.axes[0].get_lines() if line.get_label().startswith("PBD jacobi"))
    assert list(pbd.get_ydata()) == [0.05, 0.05]  # the worst backend, not the best
    plot_stability_map(rows, tmp_path / "stab.png")
    assert (tmp_path / "stab.png").exists() and (tmp_path / "stab.svg").exists()


# --- the machine under the accuracy and stability figures ------------------------------------

# environment.collect()'s columns of a row measured on a test machine
MACHINE_A = dict(
    cpu="Test CPU A",
    cores="4",
    python="CPython 3.11",
    packages="numpy=2.0",
    env="",
    git_commit="abc123def456",
    timestamp="2026-03-04T10:00:00+00:00",
)
MACHINE_B = {
    **MACHINE_A,
    "cpu": "Test CPU B",
    "cores": "8",
    "git_commit": "fedcba654321",
    "timestamp": "2026-03-06T09:00:00+00:00",
}
LINE_A = "Test CPU A · 4 cores · commit abc123def456 · 2026-03-04"


def _small_accuracy(*machines: dict) -> list:
    """Two lines of three dts each, row i measured on machines[i % len(machines)] (none: a file
    older than the machine columns)."""
    from clothbench.analysis.convergence import AccuracyRow

    rows = []
    for label in ("numpy f64", "numpy f32"):
        for dt in (2e-3, 1e-3, 5e-4):
            machine = machines[len(rows) % len(machines)] if machines else {}
            rows.append(
                AccuracyRow(
                    scene="drape",
                    grid=8,
                    start="rest",
                    damping=0.002,
                    time_s=0.1,
                    backend="numpy",
                    label=label,
                    mode=label.split()[1],
                    device="cpu",
                    dt=dt,
                    steps=round(0.1 / dt),
                    ms_per_sim_s=1e-3 / dt,
                    disc_rms=dt,
                    impl_rms=1e-7,
                    order=1.0,
                    **machine,
                )
            )
    return rows


def _small_stability(*machines: dict) -> list:
    from clothbench.analysis.stability import StabilityRow

    rows = []
    for k in (1000.0, 10000.0, 100000.0):
        machine = machines[len(rows) % len(machines)] if machines else {}
        rows.append(
            StabilityRow(
                "flat",
                k,
                0.002,
                10,
                300,
                "numpy",
                "numpy f32",
                0.06 / math.sqrt(k),
                0.061 / math.sqrt(k),
                0.06 / math.sqrt(k),
                0.06 / math.sqrt(k),
                0.04 / math.sqrt(k),
                10,
                **machine,
            )
        )
    return rows


def _chart(figure: str, rows):
    from types import SimpleNamespace

    from clothbench.reports.accuracy_plots import convergence_chart, speed_vs_error_chart, stability_map_chart

    if figure == "stability":
        return stability_map_chart(rows)
    draw = speed_vs_error_chart if figure == "speed" else convergence_chart
    return draw(SimpleNamespace(rows=rows, differences=[]))


FIGURES = {"speed": _small_accuracy, "convergence": _small_accuracy, "stability": _small_stability}


@pytest.mark.parametrize("figure", FIGURES)
def test_accuracy_and_stability_figures_name_the_machine_commit_and_day_of_their_rows(figure):
    from conftest import drawn_text

    assert LINE_A in drawn_text(_chart(figure, FIGURES[figure](MACHINE_A)).figure)


@pytest.mark.parametrize("figure", FIGURES)
def test_figures_of_rows_from_two_machines_name_both_and_the_days_between(figure):
    from conftest import drawn_text

    text = drawn_text(_chart(figure, FIGURES[figure](MACHINE_A, MACHINE_B)).figure)
    assert "2 machines: Test CPU A (4 cores), Test CPU B (8 cores)" in text
    assert "commit abc123def456, fedcba654321" in text and "2026-03-04..2026-03-06" in text


@pytest.mark.parametrize("figure", FIGURES)
def test_figures_of_rows_older_than_the_machine_columns_draw_without_the_line(figure):
    from conftest import drawn_text

    chart = _chart(figure, FIGURES[figure]())
    text = drawn_text(chart.figure)
    assert "cores" not in text and "commit" not in text and "machines" not in text
    if figure != "convergence":  # its footer holds its line-style notes still
        assert not chart.figure.subfigs  # no footer at all


def test_a_study_csv_round_trip_keeps_the_machine_for_its_figure(tmp_path):
    """As `clothbench report` draws them: the rows read back from the CSVs the studies write."""
    from clothbench.harness.study_csv import cells
    from clothbench.reports.results_files import analysis_rows, read_results
    from conftest import drawn_text

    for figure, make in (("stability", _small_stability), ("speed", _small_accuracy)):
        rows = [cells(r.as_dict()) for r in make(MACHINE_A)]
        path = tmp_path / f"{figure}.csv"
        with path.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        assert LINE_A in drawn_text(_chart(figure, analysis_rows(read_results(path))).figure), figure


def test_a_committed_accuracy_csv_with_only_a_cpu_column_names_the_cpu_alone(tmp_path):
    from clothbench.reports.results_files import analysis_rows, read_results
    from conftest import drawn_text

    committed = Path(__file__).resolve().parents[1] / "results" / "accuracy-drape.csv"
    with committed.open(newline="") as f:
        reader = csv.DictReader(f)
        header, rows = reader.fieldnames, list(reader)[:10]  # two lines of five dts: small, and quick to draw
    assert "cpu" in header and "timestamp" not in header  # written before the other machine columns
    path = tmp_path / "acc.csv"
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=header)
        w.writeheader()
        w.writerows(rows)
    text = drawn_text(_chart("speed", analysis_rows(read_results(path))).figure)
    assert rows[0]["cpu"] in text.splitlines() and "commit" not in text
