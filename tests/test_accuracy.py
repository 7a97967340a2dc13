"""Accuracy and stability machinery: order fitting, the lattice bound, bisection, energy, CLI."""

import csv
import math

import numpy as np
import pytest

from clothbench.accuracy import (
    Variant,
    backend_variants,
    converged_reference,
    dt_limit,
    dynamical_matrix,
    finite_grid_omega2,
    fit_order,
    lattice_omega2,
    measure_stability_limit,
    stability_scene,
)
from clothbench.backends import BackendOptions
from clothbench.cli import main
from clothbench.harness import simulate
from clothbench.harness.energy import energy_problem, total_energy
from clothbench.scene import Scene, load_scene

F64 = Variant("numpy", BackendOptions(precision="f64"), (("precision", "f64"),))


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
    scene = load_scene("drape").replace(grid=8)
    ref = converged_reference(scene, 0.02, 2.5e-4)
    assert ref.converged and ref.order == pytest.approx(1.0, abs=0.1)  # start = rest
    assert ref.uncertainty < 1e-8


def test_energy_of_free_fall_is_constant_and_a_blow_up_is_caught():
    # flat sheet, b = 0, no pins: no spring stretches, gravity is linear, so the averaged
    # potential makes Verlet's energy exact to float64 rounding
    scene = Scene(grid=8, damping=0.0)
    e0 = total_energy(*scene.initial_state(), scene).total
    pos, prev = simulate("numpy", scene, 300, BackendOptions(precision="f64"))
    assert total_energy(pos, prev, scene).total == pytest.approx(e0, abs=1e-9)
    assert energy_problem(pos, prev, scene, 300) is None
    pos = pos.copy()
    pos[5, :3] += 10.0  # one particle 10 m off in one step: 2e4 m/s, springs torn
    assert "total energy grew" in energy_problem(pos, prev, scene, 300)


def test_numpy_variants_are_f32_and_f64():
    variants, _ = backend_variants(["numpy"])
    assert [v.options.precision for v in variants] == ["f32", "f64"]


def test_accuracy_cli_writes_a_csv_and_both_plots(tmp_path, capsys):
    out = tmp_path / "acc.csv"
    argv = ["accuracy", "--backends", "numpy", "--grid", "8", "--time", "0.02", "--levels", "3",
            "--out", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "fitted convergence order: numpy f64: 1.0" in text  # start = rest: first order
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2 * 3 and {r["label"] for r in rows} == {"numpy f32", "numpy f64"}
    assert all(float(r["disc_rms"]) > 0 and float(r["ms_per_sim_s"]) > 0 for r in rows)
    for png in ("acc-speed.png", "acc-convergence.png"):
        assert (tmp_path / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_stability_cli_prints_measured_beside_predicted(tmp_path, capsys):
    out = tmp_path / "stab.csv"
    argv = ["stability", "--backends", "numpy", "--stiffness", "1000", "--scenes", "flat",
            "--grid", "10", "--steps", "300", "--out", str(out)]
    assert main(argv) == 0
    rows = list(csv.DictReader(open(out)))
    assert len(rows) == 2
    for r in rows:
        assert abs(float(r["ratio"]) - 1) < 0.1
    assert (tmp_path / "stab.png").exists()
    assert "numpy f64" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["accuracy", "--backends", "numpy", "--time", "0.0123"], "not a whole number of steps"),
        (["accuracy", "--backends", "numpy", "--dts", "1e-3,x"], "--dts must be comma-separated"),
        (["stability", "--backends", "numpy", "--stiffness", "-5"], "--stiffness must be positive"),
        (["stability", "--backends", "numpy", "--scenes", "wavy"], "unknown stability scene 'wavy'"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
