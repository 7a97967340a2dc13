"""The sweep's float64 references shared between rows (harness/sweep.py, check_errors;
harness/simulate.py, reference_states): one run gives every step count the rows need, with
the bits a separate run to each gives, so a row's error is the same as when it ran its own."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from clothbench.backends import BackendOptions
from clothbench.cli import main
from clothbench.harness.simulate import position_error, reference, reference_states, simulate
from clothbench.harness.sweep import reference_errors, check_errors, measure_row, plan_sweep
from clothbench.harness.timing import MIN_BUDGET_CHUNKS
from tests.conftest import setup

SPECS = ("verlet", "pbd-jacobi", "pbd-coloured", "vbd")
IN_PROCESS = SimpleNamespace(isolate=False, row_timeout=None)  # check_errors' settings: no worker


@pytest.mark.parametrize("scene", ("sphere", "carried"))  # carried: a moving body and pins that follow it
@pytest.mark.parametrize("spec", SPECS)
def test_one_reference_run_gives_the_bits_of_a_run_to_each_step_count(spec, scene):
    s = setup(scene, 10)
    solver = s.solver_for(spec)
    states = reference_states(s.scene, solver, (7, 2, 5))
    assert sorted(states) == [2, 5, 7]
    for count, (pos, prev) in states.items():
        # numpy float64 from the start to `count` in one advance: bit for bit (the c reference
        # of a Verlet run is held to NumPy's bits by tests/test_c_backend.py)
        alone = simulate("numpy", s.scene, solver, count, BackendOptions(precision="f64"))
        np.testing.assert_array_equal(pos, alone[0])
        np.testing.assert_array_equal(prev, alone[1])


@pytest.mark.parametrize("spec", SPECS)
def test_a_budget_cut_rows_error_is_what_its_own_reference_gave(spec):
    """A budget of 1e-9 s cuts every row to MIN_BUDGET_CHUNKS one-step chunks, so two runs of a
    row end in the same state: its error from its own reference run (the sweep's way before)
    and from the shared one are the same float64 numbers, bit for bit."""
    s = setup("sphere", 10)
    solver = s.solver_for(spec)
    rows = [r for r in plan_sweep(["numpy"], [10], [solver]).rows if not r.variant.is_reference]
    assert rows
    waiting = []
    for row in rows:
        own = measure_row(row, s, 4, 3, {}, budget_s=1e-9)  # runs reference(scene, solver, 3) itself
        unchecked: dict = {}
        shared = measure_row(row, s, 4, 3, {}, budget_s=1e-9, unchecked=unchecked)
        assert own["steps"] == "1" and own["err_rms_m"] and not shared["err_rms_m"]
        ((key, pos),) = unchecked.items()
        assert key == (s.scene, solver, MIN_BUDGET_CHUNKS)
        waiting.append((own, shared, key, pos))
    runs = check_errors([(shared, {key: pos}) for _, shared, key, pos in waiting], {}, IN_PROCESS)
    assert runs == 1  # every row of the scene and solver from one run
    positions = {MIN_BUDGET_CHUNKS: [pos for *_, pos in waiting]}
    shared_errors = reference_errors(s.scene, solver, positions)[MIN_BUDGET_CHUNKS]
    for (own, shared, key, pos), error in zip(waiting, shared_errors):
        assert (shared["err_rms_m"], shared["err_max_m"]) == (own["err_rms_m"], own["err_max_m"])
        assert error == position_error(pos, reference(*key)[0])  # the float64 numbers, ==


def test_a_budget_cut_sweep_runs_no_reference_beside_the_f64_row(tmp_path, monkeypatch):
    """The numpy f64 row cut to the same steps as the others is their reference: no other run."""
    from clothbench.harness import sweep

    runs = []
    real = sweep.check_errors
    monkeypatch.setattr(sweep, "check_errors", lambda *a: runs.append(real(*a)) or runs[-1])
    out = tmp_path / "s.csv"
    args = ["sweep", "--backends", "numpy", "--grids", "8,10", "--steps", "3", "--repeat", "4"]
    assert main([*args, "--row-budget", "1e-9", "--out", str(out)]) == 0
    assert sum(runs) == 0 and len(runs) == 2  # one check per grid, nothing to run
    import csv

    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 4 and all(r["err_rms_m"] for r in rows)
    assert [r["grid"] for r in rows] == ["8", "8", "10", "10"]  # still in plan order


def test_rows_without_the_f64_row_share_one_reference_run_in_a_worker(tmp_path, monkeypatch, capsys):
    """--backends c plans no numpy f64 row: one float64 run in a worker (the isolated sweep's
    way), before the grid's first row, gives every row its error as it comes; none waits."""
    from clothbench.backends import availability
    from clothbench.harness import sweep

    if not availability("c").usable:
        pytest.skip(f"c unavailable: {availability('c').reason}")
    runs = []
    real = sweep.check_errors
    monkeypatch.setattr(sweep, "check_errors", lambda *a: runs.append(real(*a)) or runs[-1])
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "c", "--grids", "8", "--steps", "3", "--repeat", "2", "--out", str(out)]) == 0
    import csv

    rows = list(csv.DictReader(out.open()))
    assert len(rows) >= 2 and not any(r["precision"] == "f64" and r["backend"] == "numpy" for r in rows)
    assert runs == [0]  # nothing left for the end of the grid
    assert "; 1 float64 reference runs beside the rows" in capsys.readouterr().err
    assert all(r["status"] == "ok" and float(r["err_rms_m"]) < 1e-6 for r in rows), [r["note"] for r in rows]


def test_a_rows_process_checks_its_energy_from_the_start_the_sweep_gives_it(monkeypatch):
    """The sweep computes each scene's float64 start energy once (energy.start_energy) and gives
    it to every row's process, which would otherwise compute it again (1.5-2 s at 2048^2): the
    row's blow-up check measures from the given start, and computes none of its own."""
    from clothbench.harness import energy, sweep

    s = setup("sphere", 10)
    row = next(r for r in plan_sweep(["numpy"], [10], [s.solver]).rows if not r.variant.is_reference)
    given = sweep._start_energy(s.scene, row.solver)
    assert given == energy._start(s.scene, row.solver)
    monkeypatch.setattr(energy, "_given", {})
    monkeypatch.setattr(energy, "_start", lambda *a: pytest.fail("the row computed its own start"))
    out, _, _ = sweep._measure_in_child(row, s, 4, 2, None, start=given)
    assert out["status"] == "ok"
    monkeypatch.setattr(energy, "_given", {})
    # a start a gigajoule below the real one, and a scale of 1 J: the run is past its bound
    out, _, _ = sweep._measure_in_child(row, s, 4, 2, None, start=(given[0] - 1e9, 1.0))
    assert out["status"] != "ok" and "total energy grew" in out["note"]
