"""`clothbench pbd-study` (analysis/pbd_study.py): substeps against iterations at equal cost."""

from __future__ import annotations

import csv

import pytest

from clothbench.analysis import pbd_study
from clothbench.analysis.pbd_study import how_busy, measure_pair, pairs_at, study_reference
from clothbench.cli import main
from clothbench.machine_load import Load
from clothbench.model.scene import load_scene

SMALL = ["--grid", "8", "--time", "0.1", "--cost-backends", "none"]  # 6 frames of 1/60 s, error only


def test_pairs_at_a_cost_are_every_divisor_pair():
    assert pairs_at(20) == [(1, 20), (2, 10), (4, 5), (5, 4), (10, 2), (20, 1)]
    assert all(s * i == 12 for s, i in pairs_at(12))


def test_small_steps_beat_many_iterations_at_equal_cost():
    # Macklin et al. 2019, measured here (docs/pbd-study.md): with Gauss-Seidel, 8 substeps of one
    # iteration are closer to the converged mass-spring answer than one step of 8 iterations
    scene = load_scene("curtain").replace(grid=8, damping=0.0)
    ref = study_reference(scene, 0.1)
    few = measure_pair(scene, "coloured", 1, 8, 0.1, ref, cost_backends=())
    small = measure_pair(scene, "coloured", 8, 1, 0.1, ref, cost_backends=())
    assert small.rms < 0.5 * few.rms, (small.rms, few.rms)
    assert few.strain > small.strain, "one big step under-resolves the springs: a softer, stretched cloth"


class Recorded:
    """A LoadSampler whose every window saw `load`."""

    def __init__(self, load: Load):
        self.load = load

    def start(self):
        return self

    def stop(self, min_window_s: float = 0.0) -> Load:
        return self.load


@pytest.mark.parametrize("busy", [True, False], ids=["busy", "quiet"])
def test_a_row_says_how_busy_the_machine_was_while_its_ms_were_timed(busy, monkeypatch):
    # a study's ms, like a sweep row's, are marked when other processes ran beside them
    # (machine_load), and the figure's title says so; a row that timed nothing knows nothing
    why = f"other processes {1.5 if busy else 0.0:.2f} of 2 cores, steal 0% over 2.00 s"
    load = Load(2.0, 2, 1.5 if busy else 0.0, 0.75 if busy else 0.0, 0.0, busy, why)
    monkeypatch.setattr(pbd_study, "LoadSampler", lambda: Recorded(load))
    scene = load_scene("curtain").replace(grid=8, damping=0.0)
    ref = study_reference(scene, 0.1)
    timed = measure_pair(scene, "coloured", 2, 1, 0.1, ref, cost_backends=("numpy",))
    assert timed.ms_numpy > 0 and timed.busy is busy and timed.load == why
    untimed = measure_pair(scene, "coloured", 2, 1, 0.1, ref, cost_backends=())
    assert untimed.busy is None and untimed.load == ""
    assert how_busy([untimed]) == "how busy not recorded"
    if busy:
        assert how_busy([timed, timed, untimed]) == "2 of 3 runs timed on a busy machine"
    else:
        assert how_busy([timed, timed]) == "the machine quiet throughout"
        assert how_busy([timed, untimed]) == "the machine quiet for 1 of 2 runs, not recorded for the rest"


@pytest.mark.parametrize(
    "bad, says",
    [
        (["--costs", "0"], "--costs must all be >= 1"),
        (["--methods", "gauss"], "--methods takes"),
        (["--time", "0.51"], "not a whole number of steps"),
        (["--damping", "-1"], "--damping must be >= 0"),
        (["--scenes", "nowhere"], "unknown scene"),
        (["--cost-backends", "glsl"], "--cost-backends takes"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(bad, says, tmp_path, capsys):
    assert main(["pbd-study", *bad, "--out", str(tmp_path / "s.csv")]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err
    assert not (tmp_path / "s.csv").exists()


def test_rows_are_kept_and_resume_measures_only_the_missing(tmp_path):
    out = tmp_path / "study.csv"
    common = ["pbd-study", "--scenes", "drape", "--methods", "coloured", *SMALL, "--out", str(out)]
    assert main([*common, "--costs", "2"]) == 0
    first = list(csv.DictReader(out.open()))
    assert [(r["substeps"], r["iterations"]) for r in first] == [("1", "2"), ("2", "1")]
    assert main([*common, "--costs", "2,3", "--resume"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert [(r["substeps"], r["iterations"]) for r in rows] == [("1", "2"), ("2", "1"), ("1", "3"), ("3", "1")]
    assert rows[:2] == first, "rows already in the file are kept as they were, not measured again"
    assert (tmp_path / "study.png").stat().st_size > 0
    # another grid would mix two studies in one file: refused before anything is measured
    other_grid = ["pbd-study", "--scenes", "drape", "--methods", "coloured", "--grid", "9", "--time", "0.1",
                  "--cost-backends", "none", "--costs", "2", "--out", str(out), "--resume"]  # fmt: skip
    assert main(other_grid) == 2
    assert list(csv.DictReader(out.open())) == rows
