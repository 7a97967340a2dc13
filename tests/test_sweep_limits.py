"""What a sweep row says about limits: the per-row time budget that bounds slow rows, the
machine's bound beside every row, and the ratio to the native c line of the same run."""

from __future__ import annotations

import csv

import pytest

from clothbench.backends import availability
from clothbench.cli import main
from clothbench.harness.timing import MIN_BUDGET_CHUNKS, fit_budget
from clothbench.model.scene import count_springs

TINY = ["--steps", "3", "--repeat", "4"]


def rows_of(path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open()))


# --- fit_budget: the arithmetic of a shortened run -----------------------------------------


def test_a_run_that_fits_its_budget_is_unchanged():
    assert fit_budget(500, 50, step_s=0.001, budget_s=1.0) == (500, 50)


def test_the_chunk_shrinks_first_keeping_the_number_of_chunks():
    # 500 steps at 0.1 s = 50 s; 10 s left: 10 chunks of 10 steps
    assert fit_budget(500, 50, step_s=0.1, budget_s=10.0) == (100, 10)


def test_then_the_chunks_but_never_below_the_minimum():
    steps, chunk = fit_budget(500, 50, step_s=2.0, budget_s=10.0)
    assert (steps, chunk) == (5, 1)  # 5 one-step chunks fill the 10 s
    steps, chunk = fit_budget(500, 50, step_s=100.0, budget_s=10.0)
    assert (steps, chunk) == (MIN_BUDGET_CHUNKS, 1)  # over budget, but a median needs chunks


# --- the sweep ----------------------------------------------------------------------------


def test_a_row_past_its_budget_runs_fewer_steps_and_says_so(tmp_path):
    out = tmp_path / "s.csv"
    assert (
        main(["sweep", "--backends", "numpy", "--grids", "16", *TINY, "--row-budget", "1e-9", "--out", str(out)]) == 0
    )
    rows = rows_of(out)
    assert len(rows) == 2
    for r in rows:
        assert r["status"] == "ok" and r["budget_s"] == "1e-09"
        assert (r["steps"], r["repeats"]) == ("1", str(MIN_BUDGET_CHUNKS))
        assert len(r["chunk_ms"].split()) == MIN_BUDGET_CHUNKS
        assert "time budget" in r["note"] and "instead of 4 of 3" in r["note"]
        assert float(r["simulated_s"]) == pytest.approx(MIN_BUDGET_CHUNKS * float(r["dt"]))
    # the error is taken against the float64 run of the steps that ran (not the f64 row's
    # shortened state mistaken for the 12-step one): f32 rounding only after 3 steps
    f32 = next(r for r in rows if r["precision"] == "f32")
    assert 0 < float(f32["err_rms_m"]) < 1e-6


def test_a_budgeted_file_can_be_resumed_with_the_same_settings(tmp_path):
    out = tmp_path / "s.csv"
    args = ["sweep", "--backends", "numpy", *TINY, "--row-budget", "1e-9", "--out", str(out)]
    assert main([*args, "--grids", "16"]) == 0
    assert main([*args, "--grids", "16,20", "--resume"]) == 0
    assert sorted(r["grid"] for r in rows_of(out)) == ["16", "16", "20", "20"]


def test_a_budget_that_is_not_positive_is_one_line_exit_2(tmp_path, capsys):
    code = main(
        ["sweep", "--backends", "numpy", "--grids", "16", "--row-budget", "0", "--out", str(tmp_path / "s.csv")]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--row-budget" in err
    assert not (tmp_path / "s.csv").exists()


def test_every_row_has_the_machines_bound_and_its_fraction(tmp_path):
    from clothbench.native import compiler

    if compiler() is None:
        pytest.skip("no C compiler: the bound is not measured (the columns stay empty)")
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "16,32", *TINY, "--out", str(out)]) == 0
    rows = rows_of(out)
    for r in rows:
        assert float(r["bound_ms"]) > 0 and r["bound_kind"] in ("memory", "arithmetic")
        assert float(r["bound_fraction"]) == pytest.approx(float(r["bound_ms"]) / float(r["ms_median"]), rel=1e-4)
    # one machine measurement per sweep, written on every row
    assert len({(r["bandwidth_gb_s"], r["sqrt_gops"]) for r in rows}) == 1 and float(rows[0]["bandwidth_gb_s"]) > 0
    # so the bound scales with the work: 4x the particles and their bytes; a little more than
    # 4x the springs (6n^2 - 14n + 10: the edge's missing springs weigh less on the larger
    # grid), which the arithmetic part counts exactly: 4.316x from 16^2 to 32^2, the springs'
    # ratio, where both rows are arithmetic-bound.
    by_grid = {(r["grid"], r["precision"]): r for r in rows}
    small, large = by_grid[("16", "f32")], by_grid[("32", "f32")]
    ratio = float(large["bound_ms"]) / float(small["bound_ms"])
    if small["bound_kind"] == large["bound_kind"] == "memory":
        assert ratio == pytest.approx(4.0, rel=1e-4)
    else:
        assert 4.0 - 1e-4 < ratio < count_springs(32) / count_springs(16) + 1e-4


def test_rows_are_compared_with_the_c_row_of_the_same_grid_and_arithmetic(tmp_path):
    if not availability("c").usable:
        pytest.skip(f"c unavailable: {availability('c').reason}")
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "c,numpy", "--grids", "16", *TINY, "--out", str(out)]) == 0
    rows = rows_of(out)
    c_fast = next(r for r in rows if r["backend"] == "c" and r["strict"] == "false" and r["precision"] == "f32")
    assert float(c_fast["vs_c"]) == pytest.approx(1.0)
    assert c_fast["driver"]  # the compiler that built it
    numpy_f32 = next(r for r in rows if r["backend"] == "numpy" and r["precision"] == "f32")
    c_same = next(
        r for r in rows if r["backend"] == "c" and r["precision"] == "f32" and r["strict"] == numpy_f32["strict"]
    )
    assert float(numpy_f32["vs_c"]) == pytest.approx(
        float(numpy_f32["ms_median"]) / float(c_same["ms_median"]), rel=1e-4
    )


def test_limits_that_cannot_be_measured_are_tried_once_and_the_rows_say_nothing(tmp_path, monkeypatch, capsys):
    from clothbench.harness import bounds

    calls = []
    monkeypatch.setattr(bounds, "machine_or_reason", lambda *a: calls.append(a) or (None, "no C compiler found"))
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "16,20", *TINY, "--out", str(out)]) == 0
    assert len(calls) == 1  # once for the sweep, not again for each of its 4 rows
    rows = rows_of(out)
    assert len(rows) == 4 and all(r["bound_ms"] == "" and r["bandwidth_gb_s"] == "" for r in rows)
    assert "no machine bound measured: no C compiler found" in capsys.readouterr().err


def test_no_bound_measures_no_limits_and_says_the_columns_are_empty(tmp_path, monkeypatch, capsys):
    from clothbench.harness import bounds

    calls = []
    monkeypatch.setattr(bounds, "machine_or_reason", lambda *a: calls.append(a) or (None, "not asked"))
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "16", *TINY, "--no-bound", "--out", str(out)]) == 0
    assert calls == []
    rows = rows_of(out)
    assert len(rows) == 2 and all(r["bound_ms"] == r["bound_fraction"] == r["bandwidth_gb_s"] == "" for r in rows)
    assert all(float(r["ms_median"]) > 0 for r in rows)
    assert "no machine bound measured (--no-bound)" in capsys.readouterr().err


def test_every_solver_row_has_a_bound(tmp_path):
    from clothbench.native import compiler

    if compiler() is None:
        pytest.skip("no C compiler: the bound is not measured (the columns stay empty)")
    out = tmp_path / "s.csv"
    solvers = "verlet,pbd-jacobi,pbd-coloured,vbd"
    args = ["sweep", "--backends", "numpy", "--grids", "16", "--solvers", solvers, *TINY, "--out", str(out)]
    assert main(args) == 0
    rows = rows_of(out)
    specs = {r["solver"] + (f"-{r['pbd_method']}" if r["pbd_method"] else "") for r in rows}
    assert specs == set(solvers.split(","))
    for r in rows:
        assert r["status"] == "ok", r["note"]
        assert float(r["bound_ms"]) > 0 and r["bound_kind"] in ("memory", "arithmetic"), r["solver"]
        assert float(r["bound_fraction"]) == pytest.approx(float(r["bound_ms"]) / float(r["ms_median"]), rel=1e-4)


def test_the_columns_doc_says_what_the_bound_is_for_each_solver(capsys):
    from clothbench.model.solver import SOLVER_SPECS

    assert main(["sweep", "--columns"]) == 0
    bound = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("bound_ms "))
    for spec in SOLVER_SPECS:
        if spec != "pbd":  # pbd alone is the scene file's method, one of the two named
            assert spec in bound, spec
