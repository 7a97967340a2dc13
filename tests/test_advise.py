"""`clothbench advise`: the configuration it names, run, meets the error; the runners-up;
what has to give when nothing qualifies; refusals of input that cannot answer the question."""

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

import clothbench.analysis.advise as advise_module
import clothbench.environment
from clothbench.analysis.advise import (
    RUNNERS_UP,
    advise,
    check_matches,
    configuration_for,
    read_accuracy_csv,
)
from clothbench.analysis.convergence import converged_reference
from clothbench.backends import availability
from clothbench.cli import main
from clothbench.cli.advise import NONE_QUALIFIES
from clothbench.harness.simulate import position_error, simulate
from clothbench.model.scene import load_setup

REPO = Path(__file__).resolve().parents[1]
# a frozen accuracy CSV (the AMD EPYC run of 2026-11-22, then results/accuracy-drape.csv): the
# tests below read facts of that run, so a re-measured results/ file does not move them
CSV = REPO / "tests" / "data" / "accuracy-drape-epyc-2026-11-22.csv"
E = 1e-3


def records(path=CSV) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def write(path: Path, rows: list[dict]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return path


def advise_json(capsys, *args) -> tuple[int, dict]:
    code = main(["advise", "--scene", "drape", *args, "--json"])
    return code, json.loads(capsys.readouterr().out)


def test_the_configuration_advise_names_for_drape_meets_the_error_when_run(tmp_path, capsys, monkeypatch):
    # as a user types it, from the repository root: the committed CSV
    monkeypatch.chdir(REPO)
    assert main(["advise", "--scene", "drape", "--max-error", str(E)]) == 0
    text = capsys.readouterr().out
    assert "choice:" in text and "ms of compute per simulated second" in text and "run it: clothbench run" in text
    code, out = advise_json(capsys, "--max-error", str(E))
    assert code == 0
    choice = out["choice"]
    assert choice["ms_per_sim_s"] > 0 and choice["error"] <= E and out["time_s"] == 0.1
    assert choice["steps"] * choice["dt"] == pytest.approx(out["time_s"])

    # the same choice as a Configuration, stepped by the harness to T
    setup = load_setup("drape")
    picked = advise(read_accuracy_csv(CSV), setup, E).choice
    config = picked.config
    assert " ".join(config.run_args("drape")) == choice["command"]
    scene = setup.scene.replace(grid=config.grid)
    pos, _ = simulate(config.backend, scene, config.solver, config.steps, config.options)
    # against the converged float64 answer of the same model at the same time, refined
    # below the choice's own dt (0.4 s for Verlet at 1 ms on 32 x 32)
    ref = converged_reference(scene, config.solver, out["time_s"], config.solver.dt)
    assert ref.converged
    err = position_error(pos, ref.pos)[1]  # max: advise's default metric
    assert err + ref.uncertainty <= E
    assert err == pytest.approx(choice["error"], rel=0.05)  # and the CSV's number reproduces here

    # and the printed command itself, run, lands on the same state
    saved = tmp_path / "state.npz"
    assert main(choice["argv"] + ["--save", str(saved)]) == 0
    capsys.readouterr()
    run_err = position_error(np.load(saved)["pos"], ref.pos)[1]
    assert run_err + ref.uncertainty <= E
    assert run_err == pytest.approx(err, rel=1e-3)


def usable_here(row: dict) -> bool:
    return availability(row["backend"]).usable


def test_runners_up_are_the_next_cheapest_and_all_meet_the_error(capsys):
    code, out = advise_json(capsys, "--max-error", str(E), "--csv", str(CSV))
    assert code == 0
    shown = [out["choice"], *out["runners_up"]]
    costs = [p["ms_per_sim_s"] for p in shown]
    assert costs == sorted(costs) and len(out["runners_up"]) == RUNNERS_UP
    assert all(p["error_bound"] <= E and p["disc_max"] <= E for p in shown)
    # independently, from the CSV: the cheapest rows that qualify, among backends usable here
    ok = sorted(
        float(r["ms_per_sim_s"])
        for r in records()
        if r["status"] == "ok" and usable_here(r) and float(r["disc_max"]) + float(r["ref_uncertainty"]) <= E
    )
    assert costs == ok[: len(costs)]
    # the cheapest of each other solver and backend meet E too, and cost at least the choice's
    for group in out["by_model"] + out["by_backend"]:
        if group["cheapest"]:
            assert group["cheapest"]["error_bound"] <= E
            assert group["cheapest"]["ms_per_sim_s"] >= costs[0]
    assert {g["name"] for g in out["by_model"]} == {"pbd-jacobi/10it, relaxation 1.5", "pbd-coloured/10it"}


def test_the_rms_metric_reads_the_rms_column(capsys):
    _, out = advise_json(capsys, "--max-error", "1e-4", "--metric", "rms", "--csv", str(CSV))
    assert out["column"] == "disc_rms" and out["choice"]["error"] == out["choice"]["disc_rms"] <= 1e-4
    assert out["choice"]["disc_max"] > 1e-4  # max would not have let it through


def test_when_nothing_qualifies_it_says_what_would_have_to_give(capsys):
    assert main(["advise", "--scene", "drape", "--max-error", "2e-5", "--csv", str(CSV)]) == NONE_QUALIFIES
    text = capsys.readouterr().out
    assert "nothing measured stays under E = 2e-05 m" in text
    smallest = min(float(r["disc_max"]) for r in records() if r["status"] == "ok" and usable_here(r))
    assert f"the smallest error measured is {smallest:.3g} m" in text
    assert "measure it: clothbench accuracy" in text
    code, out = advise_json(capsys, "--max-error", "2e-5", "--csv", str(CSV))
    assert code == NONE_QUALIFIES and out["choice"] is None and out["runners_up"] == []
    assert out["closest"]["error"] == smallest
    # a smaller dt than measured, predicted from the line's order: cheaper first, and dearer
    # than what that line was measured at
    assert out["predictions"]
    costs = [p["ms_per_sim_s"] for p in out["predictions"]]
    assert costs == sorted(costs)
    for p in out["predictions"]:
        assert p["dt"] < p["from"]["dt"] and p["ms_per_sim_s"] > p["from"]["ms_per_sim_s"]
        assert p["steps"] * p["dt"] == pytest.approx(out["time_s"])


def test_a_bound_under_the_references_uncertainty_is_said_to_be_unmeasurable(capsys):
    assert main(["advise", "--scene", "drape", "--max-error", "1e-9", "--csv", str(CSV)]) == NONE_QUALIFIES
    assert "under the reference's own uncertainty" in capsys.readouterr().out


def test_the_machine_the_costs_are_from_is_said_and_another_one_flagged(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(clothbench.environment, "cpu_model", lambda: "Some Other CPU")
    main(["advise", "--scene", "drape", "--max-error", str(E), "--csv", str(CSV)])
    text = capsys.readouterr().out
    assert "measured on AMD EPYC (the numpy rows' device" in text and "NOT this machine (Some Other CPU)" in text
    monkeypatch.setattr(clothbench.environment, "cpu_model", lambda: "AMD EPYC")
    main(["advise", "--scene", "drape", "--max-error", str(E), "--csv", str(CSV)])
    assert "the same CPU model as this machine" in capsys.readouterr().out
    rows = [dict(r, cpu="Vendor CPU 9000") for r in records()]
    main(["advise", "--scene", "drape", "--max-error", str(E), "--csv", str(write(tmp_path / "c.csv", rows))])
    assert "measured on Vendor CPU 9000 (the CSV's cpu column)" in capsys.readouterr().out


def test_a_renamed_variant_of_an_older_csv_is_matched_by_its_mode():
    setup = load_setup("drape")
    rows = {(r.label, r.dt): r for r in read_accuracy_csv(CSV).rows}
    for label, today in (("glsl-compute strict/wg=64", "glsl-compute strict/ls=auto"), ("warp default", "warp fast")):
        backend = label.split()[0]
        if not availability(backend).usable:
            continue
        config = configuration_for(rows[(label, 0.001)], setup)
        assert config.label == today
    config = configuration_for(rows[("opencl fast/per-step/ls=auto", 0.001)], setup)
    if not isinstance(config, str):  # opencl usable here
        assert config.options.transfer == "per-step" and not config.options.strict


def refused(capsys, *args) -> str:
    code = main(["advise", *args])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    return captured.err


@pytest.fixture
def no_work(monkeypatch):
    """Fails the test if advise gets as far as choosing."""

    def fail(*a, **k):
        raise AssertionError("advise ran on input it should have refused")

    monkeypatch.setattr(advise_module, "advise", fail)


def test_a_csv_of_another_scene_is_refused(tmp_path, capsys, no_work):
    other = write(tmp_path / "sphere.csv", [dict(r, scene="sphere") for r in records()])
    assert "an accuracy run of scene 'sphere', not 'drape'" in refused(
        capsys, "--scene", "drape", "--max-error", str(E), "--csv", str(other)
    )
    assert "not 'sphere'" in refused(capsys, "--scene", "sphere", "--max-error", str(E), "--csv", str(CSV))
    stiff = write(tmp_path / "k.csv", [dict(r, stiffness="100000") for r in records()])
    assert "stiffness 100000" in refused(capsys, "--scene", "drape", "--max-error", str(E), "--csv", str(stiff))
    relaxed = [dict(r, ref_model=r["ref_model"].replace("1.5", "1.2")) for r in records()]
    assert "relaxation 1.2" in refused(
        capsys, "--scene", "drape", "--max-error", str(E), "--csv", str(write(tmp_path / "r.csv", relaxed))
    )


@pytest.mark.parametrize("bad", ["0", "-1e-3", "nan", "inf", "one"])
def test_an_error_bound_that_is_not_a_positive_number_is_refused(bad, capsys, no_work):
    assert "--max-error" in refused(capsys, "--scene", "drape", "--max-error", bad, "--csv", str(CSV))


def test_unreadable_or_foreign_input_is_refused(tmp_path, capsys, no_work):
    args = ["--scene", "drape", "--max-error", str(E), "--csv"]
    assert "unknown scene" in refused(capsys, "--scene", "nowhere", "--max-error", str(E))
    assert "cannot read" in refused(capsys, *args, str(tmp_path / "missing.csv"))
    assert "cannot read" in refused(capsys, *args, str(tmp_path))
    sweep = REPO / "results" / "cpu-llvmpipe-pocl.csv"
    assert "not an accuracy CSV" in refused(capsys, *args, str(sweep))
    garbled = write(tmp_path / "g.csv", [dict(records()[0], dt="fast")])
    assert "line 2" in refused(capsys, *args, str(garbled))
    (tmp_path / "empty.csv").write_text(",".join(records()[0]) + "\n")
    assert "no rows" in refused(capsys, *args, str(tmp_path / "empty.csv"))
    assert "--run" in refused(capsys, *args, str(CSV), "--time", "0.2")  # cannot answer T; offers to run
    assert "unknown backend" in refused(capsys, *args, str(CSV), "--backends", "nonesuch")


def test_backends_limit_the_choice(capsys):
    _, out = advise_json(capsys, "--max-error", str(E), "--csv", str(CSV), "--backends", "numpy")
    assert out["choice"]["backend"] == "numpy"
    assert all(p["backend"] == "numpy" for p in out["runners_up"])
    assert [g["name"] for g in out["by_backend"]] == []


def test_run_measures_here_at_the_time_asked(capsys):
    # a small accuracy run (numpy Verlet, 8 x 8, to 0.05 s): what --run does at its full size
    code, out = advise_json(
        capsys, "--max-error", str(E), "--run", "--backends", "numpy", "--solvers", "verlet",
        "--grid", "8", "--time", "0.05",
    )  # fmt: skip
    assert code == 0
    assert out["source"] == "measured here" and out["costs_from_this_machine"] is True
    assert out["grid"] == 8 and out["time_s"] == 0.05 and out["choice"]["time_s"] == 0.05
    assert out["choice"]["backend"] == "numpy" and out["choice"]["error_bound"] <= E
    assert math.isfinite(out["choice"]["ms_per_sim_s"])


def test_check_matches_takes_the_committed_run():
    run = read_accuracy_csv(CSV)
    check_matches(run, load_setup("drape"))
    assert run.time_s == 0.1 and run.grid == 32 and run.cpu == "AMD EPYC"


def test_readme_advise_line_answers_from_another_folder(tmp_path, monkeypatch, capsys):
    # the committed results are found from the package, as its kernels are
    from pathlib import Path

    monkeypatch.chdir(tmp_path)
    assert main(["advise", "--scene", "drape", "--max-error", "1e-3"]) == 0
    committed = Path(__file__).resolve().parents[1] / "results" / "accuracy-drape.csv"
    assert f"from {committed}" in capsys.readouterr().out


def test_advise_without_any_run_says_what_to_pass(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["advise", "--scene", "sphere", "--max-error", "1e-3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "give --csv FILE, or --run" in err, err
