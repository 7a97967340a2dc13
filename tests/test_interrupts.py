"""Ctrl-C (SIGINT) or SIGTERM in the middle of a row of a real `clothbench sweep` process:
exit 130, every finished row kept, no partial one, and --resume completes the sweep to the
same rows as one never interrupted."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys

import pytest

from clothbench.harness.sweep_csv import row_key

from conftest import NOT_THE_RESULT, lines_in, wait_until
from test_sweep import read_csv

# --no-bound: each child would otherwise measure the machine's limits first (1-5 s), which
# these rows do not read
ARGS = ["sweep", "--backends", "numpy", "--grids", "8,12", "--steps", "3", "--repeat", "2", "--no-bound"]


def _clothbench(*args, env=None, **kw):
    return [sys.executable, "-c", "import sys; from clothbench.cli import main; sys.exit(main(sys.argv[1:]))", *args]


def _data_rows(path) -> int:
    try:
        return max(0, path.read_text().count("\n") - 1)
    except FileNotFoundError:
        return 0


@pytest.mark.parametrize(
    "sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.full)], ids=["SIGINT", "SIGTERM"]
)  # one handler takes both (harness/faults.py): SIGTERM's copy in the full tier
def test_a_signal_mid_row_keeps_finished_rows_and_resume_completes(tmp_path, sig):
    out, started = tmp_path / "s.csv", tmp_path / "started"
    # the first row runs; the second hangs in its worker and says so: the signal comes mid-row
    env = dict(
        os.environ, CLOTHBENCH_FAULT="numpy:hang", CLOTHBENCH_FAULT_AFTER="1", CLOTHBENCH_FAULT_READY=str(started)
    )
    proc = subprocess.Popen(_clothbench(*ARGS, "--out", str(out)), env=env, stderr=subprocess.PIPE, text=True)
    wait_until(lambda: lines_in(started) >= 2 and _data_rows(out) >= 1, proc, "the second row to start")
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "--resume" in err
    rows = read_csv(out)  # whole lines only (read_csv checks), the finished row kept
    assert len(rows) == 1 and rows[0]["status"] == "ok"

    done = subprocess.run(_clothbench(*ARGS, "--out", str(out), "--resume"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    whole = tmp_path / "whole.csv"
    assert subprocess.run(_clothbench(*ARGS, "--out", str(whole)), capture_output=True).returncode == 0
    resumed, uninterrupted = read_csv(out), read_csv(whole)
    assert len(resumed) == len(uninterrupted) == 4
    assert sorted(map(row_key, resumed)) == sorted(map(row_key, uninterrupted))
    assert all(r["status"] == "ok" for r in resumed)


def _children(pid: int) -> list[str]:
    """Every child of `pid`, whichever of its threads started it."""
    found = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                found += f.read().split()
        except OSError:
            pass
    return found


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("command", ["accuracy", "stability"])
def test_a_signal_in_accuracy_or_stability_exits_130_and_writes_no_partial_row(tmp_path, command, sig):
    out = tmp_path / "out.csv"
    args = {
        "accuracy": ["accuracy", "--backends", "numpy", "--grid", "6", "--levels", "2", "--time", "0.02", "--jobs", "2"],
        "stability": ["stability", "--backends", "numpy", "--grid", "16", "--steps", "20000", "--scenes", "flat",
                      "--stiffness", "1000,10000,100000"],
    }[command]  # fmt: skip
    started = tmp_path.parent / f"{tmp_path.name}-started"  # outside tmp_path: the test lists it
    # accuracy rows never end, and each says when it started; stability is long anyway, and its
    # bisection's workers are running once the parent has children
    env = dict(os.environ, CLOTHBENCH_FAULT="numpy:hang", CLOTHBENCH_FAULT_READY=str(started))
    proc = subprocess.Popen(
        _clothbench(*args, "--out", str(out)), env=env, stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    if command == "accuracy":
        wait_until(lambda: lines_in(started) >= 1, proc, "a row to start")
    wait_until(lambda: bool(_children(proc.pid)), proc, "its rows' worker processes")
    workers = _children(proc.pid)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == [out]  # the CSV (its header, any finished row), nothing else
    text = out.read_text()
    assert text.endswith("\n") and len({len(r) for r in csv.reader(text.splitlines())}) == 1  # whole rows
    wait_until(lambda: not _alive(workers), what="the workers to be gone", bound_s=60)


def _catches(pid: int, sig: signal.Signals) -> bool:
    """Whether process `pid` has a handler for `sig` (the SigCgt mask of /proc/PID/status)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            mask = next(int(line.split()[1], 16) for line in f if line.startswith("SigCgt:"))
    except (OSError, StopIteration):
        return False
    return bool(mask >> (sig - 1) & 1)


def _alive(pids: list[str]) -> list[str]:
    """Those of `pids` that still run (a zombie has ended, its parent not yet told)."""
    alive = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().split()[2] != "Z":
                    alive.append(pid)
        except OSError:
            pass
    return alive


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_in_run_exits_130_and_saves_nothing_partial(tmp_path, sig):
    save = tmp_path / "s.npz"
    args = ["run", "--backend", "numpy", "--grid", "32", "--steps", "100000000", "--save", str(save)]
    proc = subprocess.Popen(_clothbench(*args), stderr=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    # the command is past its imports once it catches SIGTERM (cli/args.py sigterm_interrupts): the
    # kernel lists caught signals in /proc/PID/status, so no guess at how long the imports take
    wait_until(lambda: _catches(proc.pid, signal.SIGTERM), proc, "the command to take SIGTERM")
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert not list(tmp_path.iterdir())


# Small studies of a few rows each: a resumed study is compared with a whole one of the same
# settings, so how long a probe runs does not matter (stability at 1,500 steps took this test
# 25-34 s of the full tier on the Zen 3, 2026-12-06; at 300 both studies take 17 s)
STUDIES = {
    "accuracy": ["accuracy", "--backends", "numpy", "--grid", "6", "--levels", "2", "--time", "0.02"],
    "stability": ["stability", "--backends", "numpy", "--grid", "12", "--steps", "300", "--scenes", "flat",
                  "--stiffness", "1000,3000,10000"],
}  # fmt: skip
TIMED = NOT_THE_RESULT  # tests/conftest.py


def _study_rows(path):
    with open(path, newline="") as f:
        return [{k: v for k, v in r.items() if k not in TIMED} for r in csv.DictReader(f)]


@pytest.mark.full  # three studies each
@pytest.mark.parametrize("command", ["accuracy", "stability"])
def test_an_interrupted_study_keeps_its_finished_rows_and_resume_completes_it(tmp_path, command):
    from clothbench.cli import main

    out, started = tmp_path / "part.csv", tmp_path / "started"
    # the first row to start runs, every later one hangs in its worker: the signal comes after one
    # finished row and before the study could end, however fast or slow the machine is
    env = dict(
        os.environ, CLOTHBENCH_FAULT="numpy:hang", CLOTHBENCH_FAULT_AFTER="1", CLOTHBENCH_FAULT_READY=str(started)
    )
    proc = subprocess.Popen(
        _clothbench(*STUDIES[command], "--out", str(out)),
        env=env,
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    wait_until(lambda: _data_rows(out) >= 1, proc, "a finished row")  # the header and a finished row
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "--resume" in err and "Traceback" not in err
    kept = _study_rows(out)
    text = out.read_text()
    assert text.endswith("\n") and len({len(r) for r in csv.reader(text.splitlines())}) == 1
    assert main([*STUDIES[command], "--out", str(out)]) == 2  # an existing file wants --resume
    assert main([*STUDIES[command], "--out", str(out), "--resume"]) == 0
    whole = tmp_path / "whole.csv"
    assert main([*STUDIES[command], "--out", str(whole)]) == 0
    resumed, expected = _study_rows(out), _study_rows(whole)
    assert 1 <= len(kept) < len(expected)
    assert resumed == expected  # every row once, in the plan's order, derived columns included
    other = [*STUDIES[command], "--out", str(out), "--resume", "--grid", "13"]
    assert main(other) == 2  # measured with other settings: refused


@pytest.mark.full  # accuracy's copy (three studies) of the sweep's: tests/test_executor.py, quick
def test_accuracy_resume_keeps_crashed_rows_and_retry_failed_measures_them_again(tmp_path, monkeypatch):
    from clothbench.cli import main

    out = tmp_path / "acc.csv"
    args = [*STUDIES["accuracy"], "--out", str(out)]
    monkeypatch.setenv("CLOTHBENCH_FAULT", "numpy:abort")  # every row's worker aborts
    assert main(args) == 0
    assert {r["status"].split(":")[0] for r in _study_rows(out)} == {"crashed"}
    monkeypatch.delenv("CLOTHBENCH_FAULT")
    assert main([*args, "--resume"]) == 0
    assert {r["status"].split(":")[0] for r in _study_rows(out)} == {"crashed"}  # left alone
    assert main([*args, "--retry-failed"]) == 0
    rows = _study_rows(out)
    assert len(rows) == 4 and {r["status"] for r in rows} == {"ok"} and all(r["order"] != "" for r in rows)
