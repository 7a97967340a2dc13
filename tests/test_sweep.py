"""The sweep: one complete CSV row per backend variant and grid, written as measured, and
nothing lost or duplicated when a sweep is killed and resumed."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shlex
import signal
import subprocess
import sys
import types

import numpy as np
import pytest

from clothbench.backends import BACKENDS, PEERS, Availability, BackendEntry, Capabilities, availability
from clothbench.backends.numpy.verlet import NumpyBackend
from clothbench import environment
from clothbench.cli import main
from clothbench.harness import sweep as sweep_module
from clothbench.harness.sweep_csv import COLUMNS, MEASUREMENT_COLUMNS, row_key
from clothbench.viewer.keys import BACKEND_KEY_NAMES
from clothbench.model.scene import count_springs
from clothbench.model.solver import Pbd

from conftest import VERLET, lines_in, wait_until

pytestmark = pytest.mark.serial  # times sweep rows: one xdist worker

# Columns every row must have (the file has more).
ISSUE_COLUMNS = (
    "backend",
    "peer",
    "mode",
    "strict",
    "transfer",
    "local_size",
    "precision",
    "device",
    "scene",
    "grid",
    "particles",
    "springs",
    "steps",
    "repeats",
    "dt",
    "ms_median",
    "ms_min",
    "ms_max",
    "ms_iqr",
    "particles_per_s",
    "warmup_s",
    "finite",
    "status",
    "note",
    "err_rms_m",
    "err_max_m",
    "simulated_s",
    "cpu",
    "cores",
    "python",
    "packages",
    "git_commit",
    "timestamp",
    "timed_region",
    "solver",
    "generic",
)
TINY = ["--steps", "3", "--repeat", "2"]


def read_csv(path) -> list[dict[str, str]]:
    """The rows, after checking the file is whole lines of exactly the header's width."""
    text = path.read_text()
    assert text.endswith("\n"), "the file ends in a partial line"
    records = list(csv.reader(text.splitlines()))
    assert tuple(records[0]) == COLUMNS
    assert all(len(r) == len(COLUMNS) for r in records[1:]), "a line has the wrong number of fields"
    return [dict(zip(COLUMNS, r)) for r in records[1:]]


# --- fake backends, registered for one test: the sweep must not care which backend it runs


class LocalSizeBackend(NumpyBackend):
    """The numpy step, claiming a work-group size and strict/fast variants."""

    name = "fake-local"
    capabilities = Capabilities(local_size=True, sweep_variants=({"strict": True}, {"strict": False}))


class ExplodingBackend(NumpyBackend):
    """Raises as a driver would when a launch fails."""

    name = "fake-explode"
    capabilities = Capabilities()

    def advance(self, steps: int) -> None:
        raise RuntimeError("kernel launch failed: CL_OUT_OF_RESOURCES")


class NaNBackend(NumpyBackend):
    """Turns a particle into NaN on every step: a blow-up."""

    name = "fake-nan"
    capabilities = Capabilities()

    def advance(self, steps: int) -> None:
        super().advance(steps)
        self.pos[0, 0, 0] = np.nan


class InterruptedBackend(NumpyBackend):
    """Stands for a Ctrl-C in the middle of a row."""

    name = "fake-interrupt"
    capabilities = Capabilities()

    def advance(self, steps: int) -> None:
        raise KeyboardInterrupt


class PeerBackend(NumpyBackend):
    name = "fake-peer"
    capabilities = Capabilities()


class GenericBackend(NumpyBackend):
    """Has a generic kernel beside its specialised one: the generic one is slower."""

    name = "fake-generic"
    capabilities = Capabilities(generic=True)

    def advance(self, steps: int) -> None:
        super().advance(steps * (3 if self.options.generic else 1))


def fake_entry(name: str, target: str, peer: bool = False) -> BackendEntry:
    """A registry entry for a fake: numpy's facts (a fake is numpy's step, fork-safe as it is),
    its own name, class and display name, a peer's platform where it is one, and the first view
    key no registered backend has (every command's --help lists them, one backend a key)."""
    numpy = BACKENDS["numpy"]
    key = next(k for k in BACKEND_KEY_NAMES if k not in {e.view_key for e in BACKENDS.values()})
    return dataclasses.replace(
        numpy,
        name=name,
        verlet=target,
        pbd=None,
        peer=peer,
        display=name,
        platform=PEERS if peer else numpy.platform,
        view_key=key,
    )


def register_fake_backends(monkeypatch, *classes: type, peers: tuple[str, ...] = ()) -> None:
    """Register each Backend class under its `name` for one test, usable on a "fake device"."""
    usable = types.ModuleType("clothbench.backends._fake_usable")
    usable.probe = lambda: Availability(True, device="fake device")
    monkeypatch.setitem(sys.modules, usable.__name__, usable)
    for cls in classes:
        setattr(usable, cls.__name__, cls)
        entry = fake_entry(cls.name, f"{usable.__name__}:{cls.__name__}", peer=cls.name in peers)
        monkeypatch.setitem(BACKENDS, cls.name, entry)
    availability.cache_clear()


@pytest.fixture
def fake_backends(monkeypatch):
    absent = types.ModuleType("clothbench.backends._fake_absent")
    absent.probe = lambda: Availability(False, "no fake device on this machine")
    monkeypatch.setitem(sys.modules, absent.__name__, absent)
    monkeypatch.setitem(BACKENDS, "fake-absent", fake_entry("fake-absent", f"{absent.__name__}:Nothing"))
    register_fake_backends(
        monkeypatch,
        LocalSizeBackend,
        ExplodingBackend,
        NaNBackend,
        PeerBackend,
        GenericBackend,
        InterruptedBackend,
        peers=("fake-peer",),
    )
    yield
    availability.cache_clear()


# --- tests ---------------------------------------------------------------------------


def test_sweep_of_two_tiny_grids_writes_every_column_and_one_row_per_variant_and_grid(tmp_path):
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "8,12", *TINY, "--out", str(out)]) == 0
    rows = read_csv(out)
    assert set(ISSUE_COLUMNS) <= set(COLUMNS)
    # numpy sweeps f32 and f64: 2 variants x 2 grids
    assert sorted((r["grid"], r["precision"]) for r in rows) == [
        ("12", "f32"),
        ("12", "f64"),
        ("8", "f32"),
        ("8", "f64"),
    ]
    assert len({row_key(r) for r in rows}) == len(rows)
    for r in rows:
        n = int(r["grid"])
        assert r["status"] == "ok" and r["note"] == "" and r["finite"] == "true"
        assert (int(r["particles"]), int(r["springs"])) == (n * n, count_springs(n))
        assert (r["steps"], r["repeats"], r["solver"], r["timed_region"]) == ("3", "2", "verlet", "steps")
        assert float(r["simulated_s"]) == pytest.approx(6 * VERLET.dt)
        assert 0 < float(r["ms_min"]) <= float(r["ms_median"]) <= float(r["ms_max"])
        chunks = [float(v) for v in r["chunk_ms"].split()]  # the R chunks, as measured
        assert len(chunks) == 2 and (min(chunks), max(chunks)) == (float(r["ms_min"]), float(r["ms_max"]))
        assert float(r["ms_median"]) == pytest.approx(np.median(chunks), rel=1e-5)
        assert float(r["particles_per_s"]) == pytest.approx(n * n * 1e3 / float(r["ms_median"]), rel=1e-5)
        assert r["cpu"] and r["python"] and "numpy=" in r["packages"] and r["timestamp"]
        # f64 is the reference itself; f32 differs from it by rounding only (6 steps, < 1 µm)
        if r["precision"] == "f64":
            assert float(r["err_rms_m"]) == 0.0
        else:
            assert 0 < float(r["err_rms_m"]) <= float(r["err_max_m"]) < 1e-6


def test_every_row_is_one_complete_line_in_one_write_and_synced(tmp_path, monkeypatch):
    writes, syncs = [], []
    real_write, real_fsync = os.write, os.fsync

    def spy_write(fd, data):
        writes.append(bytes(data))
        return real_write(fd, data)

    def spy_fsync(fd):
        syncs.append(fd)
        return real_fsync(fd)

    monkeypatch.setattr(sweep_module.os, "write", spy_write)
    monkeypatch.setattr(sweep_module.os, "fsync", spy_fsync)
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]) == 0
    assert len(writes) == 1 + 2  # the header, then one per row
    assert all(w.endswith(b"\n") and w.count(b"\n") == 1 for w in writes)
    assert len(syncs) >= len(writes)


def test_failures_are_rows_with_the_reason_and_the_sweep_goes_on(tmp_path, capsys, fake_backends):
    out = tmp_path / "s.csv"
    backends = "fake-explode,fake-nan,fake-absent,fake-peer,numpy"
    assert main(["sweep", "--backends", backends, "--grids", "8", *TINY, "--out", str(out)]) == 0
    rows = {r["backend"]: r for r in read_csv(out)}
    err = capsys.readouterr().err
    # unusable: listed once with the reason, no row
    assert err.count("skipped fake-absent: no fake device on this machine") == 1
    assert "fake-absent" not in rows
    # raised: failed, the reason in the note, nothing presented as a measurement
    assert rows["fake-explode"]["status"] == "failed"
    assert "CL_OUT_OF_RESOURCES" in rows["fake-explode"]["note"]
    # blew up: unstable, with the step and what went wrong
    assert rows["fake-nan"]["status"] == "unstable"
    assert "blew up at step 1" in rows["fake-nan"]["note"] and "not finite" in rows["fake-nan"]["note"]
    for bad in ("fake-explode", "fake-nan"):
        assert all(rows[bad][c] in ("", "false") for c in MEASUREMENT_COLUMNS), rows[bad]
    # the rows after them were measured
    assert rows["fake-peer"]["status"] == "ok" and rows["fake-peer"]["peer"] == "true"
    assert rows["numpy"]["status"] == "ok" and rows["numpy"]["peer"] == "false"


def test_local_sizes_add_rows_only_for_backends_that_have_one(tmp_path, fake_backends):
    out = tmp_path / "s.csv"
    args = ["--backends", "fake-local,numpy", "--grids", "8", "--local-sizes", "16,32", *TINY, "--out", str(out)]
    assert main(["sweep", *args]) == 0
    rows = read_csv(out)
    local = sorted((r["mode"], r["local_size"]) for r in rows if r["backend"] == "fake-local")
    assert local == [
        ("fast/ls=16", "16"), ("fast/ls=32", "32"), ("fast/ls=auto", ""),
        ("strict/ls=16", "16"), ("strict/ls=32", "32"), ("strict/ls=auto", ""),
    ]  # fmt: skip
    assert {r["local_size"] for r in rows if r["backend"] == "numpy"} == {""}
    assert len({row_key(r) for r in rows}) == len(rows) == 8


def test_a_file_that_is_not_this_sweep_is_never_changed(tmp_path, capsys):
    out = tmp_path / "s.csv"
    out.write_text("precious\nno newline at the end")
    args = ["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--resume" in err
    assert main([*args, "--resume"]) == 2  # not a sweep CSV: its last line is not "torn"
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a clothbench sweep CSV" in err
    assert out.read_text() == "precious\nno newline at the end"


def test_resume_refuses_rows_timed_with_other_settings(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]) == 0
    before = out.read_text()
    args = ["--backends", "numpy", "--grids", "8,12", "--steps", "4", "--repeat", "2", "--out", str(out)]
    assert main(["sweep", *args, "--resume"]) == 2
    assert "--steps 3 --repeat 2" in capsys.readouterr().err
    assert out.read_text() == before


def test_resume_of_a_complete_sweep_measures_nothing(tmp_path, capsys):
    out = tmp_path / "s.csv"
    args = ["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]
    assert main(args) == 0
    before = out.read_text()
    assert main([*args, "--resume"]) == 0
    assert "0 rows measured, 2 in" in capsys.readouterr().err
    assert out.read_text() == before


def test_bad_grid_list_is_one_line_exit_2(capsys):
    assert main(["sweep", "--grids", "8,twelve"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'twelve'" in err


def test_resume_after_a_kill_measures_only_the_missing_rows_and_leaves_no_partial_line(tmp_path):
    out, started = tmp_path / "s.csv", tmp_path / "started"
    # 8 rows; the first runs, the second hangs in its worker (the fault switch, after one row), and
    # the kill comes once that second row has said it started: exactly one finished row, every time
    # (--no-bound: these rows' bound is not read, and measuring it would cost each child 1-5 s)
    cmd = [sys.executable, "-m", "clothbench", "sweep", "--backends", "numpy", "--grids", "8,10,12,14",
           *TINY, "--no-bound", "--out", str(out)]  # fmt: skip
    env = dict(
        os.environ, CLOTHBENCH_FAULT="numpy:hang", CLOTHBENCH_FAULT_AFTER="1", CLOTHBENCH_FAULT_READY=str(started)
    )
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        wait_until(lambda: lines_in(started) >= 2 and lines_in(out) >= 2, proc, "the second row to start")
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
        for line in started.read_text().splitlines() if started.exists() else []:
            try:  # the hung row's worker, orphaned by the kill
                os.kill(int(line.split()[1]), signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert proc.returncode == -signal.SIGKILL
    finished = out.read_text().splitlines()[1:]
    assert len(finished) == 1
    with open(out, "a") as f:  # a write torn by the crash
        f.write("numpy,false,verlet,f32,f32,fal")

    resumed = subprocess.run([*cmd, "--resume"], capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr
    assert "dropped a partial last line" in resumed.stderr
    assert "7 rows measured, 8 in" in resumed.stderr
    rows = read_csv(out)  # whole lines only
    assert out.read_text().splitlines()[1:2] == finished  # kept, not re-measured
    assert len(rows) == 8 and len({row_key(r) for r in rows}) == 8
    assert all(r["status"] == "ok" for r in rows)


def test_generic_both_measures_each_kernel_and_reports_the_specialised_speedup(tmp_path, fake_backends):
    out = tmp_path / "g.csv"
    assert (
        main(
            [
                "sweep",
                "--backends",
                "fake-generic,numpy",
                "--grids",
                "12",
                *TINY,
                "--generic",
                "both",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = read_csv(out)
    generic = [r for r in rows if r["backend"] == "fake-generic" and r["generic"] == "true"]
    special = [r for r in rows if r["backend"] == "fake-generic" and r["generic"] == "false"]
    assert len(generic) == 1 and len(special) == 1
    # the speed-up is the two kernels' measured medians, not assumed (and no timed assertion:
    # on a loaded machine a fake's three times the work need not take three times as long)
    ratio = float(generic[0]["ms_median"]) / float(special[0]["ms_median"])
    assert float(generic[0]["specialised_speedup"]) == pytest.approx(ratio, rel=1e-5)  # 6 digits in the CSV
    assert special[0]["specialised_speedup"] == ""
    assert all(r["generic"] == "false" for r in rows if r["backend"] == "numpy")  # numpy has one kernel


def test_solvers_add_pbd_rows_where_a_backend_has_that_solver(tmp_path, capsys):
    out = tmp_path / "s.csv"
    assert (
        main(
            [
                "sweep",
                "--backends",
                "numpy",
                "--grids",
                "8",
                *TINY,
                "--solvers",
                "verlet,pbd",
                "--scene",
                "curtain",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = read_csv(out)
    assert {(r["solver"], r["precision"]) for r in rows} == {
        ("verlet", "f32"),
        ("verlet", "f64"),
        ("pbd", "f32"),
        ("pbd", "f64"),
    }
    pbd = [r for r in rows if r["solver"] == "pbd"]
    assert all(
        r["pbd_method"] == "jacobi" and r["iterations"] == str(Pbd().iterations) and r["status"] == "ok" for r in pbd
    )
    assert len({row_key(r) for r in rows}) == len(rows)


def test_pbd_methods_are_rows_of_their_own(tmp_path):
    out = tmp_path / "m.csv"
    argv = ["sweep", "--backends", "numpy", "--grids", "6", *TINY, "--scene", "curtain", "--out", str(out)]
    assert main([*argv, "--solvers", "pbd-jacobi,pbd-coloured"]) == 0
    rows = read_csv(out)
    assert {r["pbd_method"] for r in rows} == {"jacobi", "coloured"}
    assert len({row_key(r) for r in rows}) == len(rows) == 4
    assert all(r["status"] == "ok" and r["solver"] == "pbd" for r in rows)
    # each method is compared with the float64 run of its own method: both are exact there
    assert {r["err_max_m"] for r in rows if r["precision"] == "f64"} == {"0"}


def test_unknown_solver_is_one_line_exit_2(capsys):
    assert main(["sweep", "--solvers", "rk4", "--out", "x.csv"]) == 2
    assert "--solvers takes verlet, pbd, pbd-jacobi, pbd-coloured" in capsys.readouterr().err


# --- the env column, the commit ------------------------------------------------------


def test_env_records_every_variable_that_changes_results_in_name_order(tmp_path, monkeypatch):
    for name in list(os.environ):
        if name.startswith(environment.ENV_PREFIXES) or name in environment.ENV_VARS:
            monkeypatch.delenv(name)
    wanted = {
        "OMP_NUM_THREADS": "1", "KMP_AFFINITY": "compact", "GOMP_SPINCOUNT": "0", "NUMBA_NUM_THREADS": "2",
        "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "LP_NUM_THREADS": "4", "GALLIUM_DRIVER": "llvmpipe",
        "MESA_GLSL_CACHE_DISABLE": "true", "POCL_DEBUG": "all", "OCL_ICD_VENDORS": "/etc/OpenCL/vendors",
        "PYOPENCL_CTX": "0:0", "CUDA_VISIBLE_DEVICES": "", "CUPY_CACHE_DIR": "/tmp/cupy cache", "TI_ARCH": "cpu",
        "WARP_CACHE_PATH": "/tmp/w",
    }  # fmt: skip
    for name, value in wanted.items():
        monkeypatch.setenv(name, value)
    monkeypatch.setenv("CLOTHBENCH_UNRELATED", "x")  # changes nothing: not recorded
    monkeypatch.setenv("TI_SKIP_VERSION_CHECK", "ON")  # set by clothbench itself: not recorded
    recorded = environment.driver_env()
    names = [item.split("=", 1)[0] for item in shlex.split(recorded)]
    assert names == sorted(wanted)
    assert dict(item.split("=", 1) for item in shlex.split(recorded)) == wanted  # spaces and empties survive

    environment.machine.cache_clear()  # the sweep reads the environment once per process
    monkeypatch.setattr(environment, "git_commit", lambda: "abc")  # (and need not ask git here)
    try:
        out = tmp_path / "s.csv"
        assert main(["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]) == 0
    finally:
        environment.machine.cache_clear()
    assert {r["env"] for r in read_csv(out)} == {recorded}


def test_git_commit_names_the_checkout():
    if not (environment.Path(environment.__file__).resolve().parents[1] / ".git").exists():
        pytest.skip("clothbench is not run from a git checkout")
    commit = environment.git_commit()
    assert commit != "unknown" and len(commit.removesuffix("+dirty")) == 12


def test_resuming_a_file_from_before_chunk_ms_says_why_not(tmp_path, capsys):
    out = tmp_path / "old.csv"
    assert main(["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out)]) == 0
    rows = read_csv(out)
    old_columns = [c for c in COLUMNS if c != "chunk_ms"]
    with open(out, "w", newline="") as f:
        writer = csv.DictWriter(f, old_columns, extrasaction="ignore", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    before = out.read_text()
    capsys.readouterr()
    assert main(["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "lacks chunk_ms" in err and "new --out" in err
    assert out.read_text() == before


# --- --json: Google Benchmark's format -----------------------------------------------


def test_json_holds_every_row_in_google_benchmarks_format(tmp_path):
    out, js = tmp_path / "s.csv", tmp_path / "s.json"
    argv = ["sweep", "--backends", "numpy", "--grids", "8,12", "--steps", "3", "--repeat", "4"]
    assert main([*argv, "--out", str(out), "--json", str(js)]) == 0
    rows = read_csv(out)
    doc = json.loads(js.read_text())
    ctx = doc["context"]
    assert {"date", "host_name", "num_cpus", "library_build_type"} <= set(ctx)
    assert ctx["num_cpus"] == int(rows[0]["cores"]) and ctx["clothbench"]["cpu"] == rows[0]["cpu"]
    assert ctx["clothbench"]["repeats"] == 4
    runs = [b for b in doc["benchmarks"] if b["run_type"] == "iteration"]
    medians = {b["run_name"]: b for b in doc["benchmarks"] if b["run_type"] == "aggregate"}
    assert len(runs) == len(rows) == 4 and len({b["name"] for b in runs}) == 4
    for run, row in zip(runs, rows):
        assert (run["backend"], run["mode"], run["status"]) == (row["backend"], row["mode"], "ok")
        assert run["grid"] == int(row["grid"])
        assert run["time_unit"] == "ms" and run["iterations"] == 12 and run["threads"] == 1
        assert "cpu_time" not in run  # not measured: left out rather than made up
        chunks = [float(v) for v in row["chunk_ms"].split()]
        assert run["chunk_ms"] == chunks and run["real_time"] == pytest.approx(np.mean(chunks))
        assert run["err_rms_m"] == float(row["err_rms_m"]) and run["device"] == row["device"]
        median = medians[run["name"]]
        assert median["name"] == run["name"] + "_median" and median["aggregate_name"] == "median"
        assert median["repetitions"] == 4 and median["real_time"] == pytest.approx(float(row["ms_median"]), rel=1e-5)


def test_json_of_an_interrupted_sweep_is_valid_and_holds_the_finished_rows(tmp_path, fake_backends):
    out, js = tmp_path / "s.csv", tmp_path / "s.json"
    argv = ["sweep", "--backends", "numpy,fake-interrupt,fake-explode", "--grids", "8", *TINY]
    assert main([*argv, "--out", str(out), "--json", str(js)]) == 130
    finished = read_csv(out)
    runs = [b for b in json.loads(js.read_text())["benchmarks"] if b["run_type"] == "iteration"]
    assert [b["mode"] for b in runs] == [r["mode"] for r in finished] == ["f64", "f32"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.csv", "s.json"]  # no temporary file left

    # resumed: the JSON again holds every row of the CSV, a failed one as GB writes an error
    argv = ["sweep", "--backends", "numpy,fake-explode", "--grids", "8", *TINY, "--resume"]
    assert main([*argv, "--out", str(out), "--json", str(js)]) == 0
    runs = [b for b in json.loads(js.read_text())["benchmarks"] if b["run_type"] == "iteration"]
    assert [b["backend"] for b in runs] == ["numpy", "numpy", "fake-explode"]
    assert runs[2]["error_occurred"] is True and "CL_OUT_OF_RESOURCES" in runs[2]["error_message"]


@pytest.mark.parametrize("where", ["a-file/s.json", ".", "s.csv"])
def test_bad_json_path_is_one_line_exit_2_before_anything_is_measured(tmp_path, capsys, where):
    (tmp_path / "a-file").write_text("")
    out = tmp_path / "s.csv"
    argv = ["sweep", "--backends", "numpy", "--grids", "8", *TINY, "--out", str(out), "--json", str(tmp_path / where)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--json" in err
    assert not out.exists()
