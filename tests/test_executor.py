"""Every row in a worker process: a crash, an out-of-memory kill or a hang costs that row
(crashed / timeout, with what happened), never the sweep; --resume leaves such rows alone
unless --retry-failed; the local executor runs timed tasks alone and the others in parallel."""

from __future__ import annotations

import multiprocessing
import os
import signal
import time

import pytest

from clothbench.backends import Capabilities
from clothbench.backends.numpy.verlet import NumpyBackend
from clothbench.cli import main
from clothbench.harness.executor import LocalExecutor, run_isolated
from clothbench.harness.sweep_csv import MEASUREMENT_COLUMNS, row_key

from test_sweep import TINY, read_csv, register_fake_backends
from conftest import NOT_THE_RESULT


def _fake(name: str) -> type:
    return type(name.replace("-", "_"), (NumpyBackend,), {"name": name, "capabilities": Capabilities()})


FAKES = [_fake(n) for n in ("fake-abort", "fake-hang", "fake-segv", "fake-oom", "fake-memory", "fake-fine")]
FAULT = "fake-abort:abort,fake-hang:hang,fake-segv:segv,fake-oom:kill,fake-memory:memory"
BACKENDS = ",".join(c.name for c in FAKES) + ",numpy"


@pytest.fixture
def faulty(monkeypatch):
    register_fake_backends(monkeypatch, *FAKES)
    monkeypatch.setenv("CLOTHBENCH_FAULT", FAULT)


def test_crashes_and_hangs_are_rows_and_every_other_row_is_measured(tmp_path, faulty, capsys):
    out = tmp_path / "s.csv"
    args = ["sweep", "--backends", BACKENDS, "--grids", "8", *TINY, "--row-timeout", "3", "--out", str(out)]
    assert main(args) == 0  # the hang cost its row its limit (the timeout status below), not the sweep
    rows = {r["backend"] + r["precision"]: r for r in read_csv(out)}
    assert len(rows) == 8  # 6 fakes + numpy f32 and f64
    assert rows["fake-abortf32"]["status"] == "crashed" and "SIGABRT" in rows["fake-abortf32"]["note"]
    assert rows["fake-segvf32"]["status"] == "crashed" and "SIGSEGV" in rows["fake-segvf32"]["note"]
    oom = rows["fake-oomf32"]
    assert oom["status"] == "crashed" and "SIGKILL" in oom["note"] and "out-of-memory" in oom["note"]
    assert rows["fake-memoryf32"]["status"] == "crashed" and "out of memory" in rows["fake-memoryf32"]["note"]
    assert rows["fake-hangf32"]["status"] == "timeout" and "3 s limit" in rows["fake-hangf32"]["note"]
    for bad in ("fake-abort", "fake-hang", "fake-segv", "fake-oom", "fake-memory"):
        r = rows[bad + "f32"]
        assert all(r[c] in ("", "false") for c in MEASUREMENT_COLUMNS), r
        assert r["grid"] == "8" and r["cpu"] and r["timestamp"]  # what and where, all the same
    for good in ("fake-finef32", "numpyf32", "numpyf64"):
        assert rows[good]["status"] == "ok" and float(rows[good]["ms_median"]) > 0
    assert float(rows["numpyf32"]["err_rms_m"]) > 0  # the f64 row's reference came back from its worker
    assert "not ok" in capsys.readouterr().err


def test_resume_keeps_crashed_rows_unless_retry_failed(tmp_path, faulty, monkeypatch, capsys):
    out = tmp_path / "s.csv"
    args = [
        "sweep",
        "--backends",
        "fake-abort,fake-fine",
        "--grids",
        "8",
        *TINY,
        "--row-timeout",
        "20",
        "--out",
        str(out),
    ]
    assert main(args) == 0
    assert [r["status"] for r in read_csv(out)] == ["crashed", "ok"]
    assert main([*args, "--resume"]) == 0  # nothing to measure: the crashed row stays as it is
    assert [r["status"] for r in read_csv(out)] == ["crashed", "ok"]
    assert "0 rows to measure" in capsys.readouterr().err
    monkeypatch.delenv("CLOTHBENCH_FAULT")  # the driver fixed
    assert main([*args, "--retry-failed"]) == 0
    rows = read_csv(out)
    assert sorted(r["status"] for r in rows) == ["ok", "ok"]
    assert len({row_key(r) for r in rows}) == len(rows) == 2  # measured again, not added twice
    assert not list(tmp_path.glob("*.retry-tmp"))


def test_bad_row_timeout_is_one_line(capsys):
    assert main(["sweep", "--backends", "numpy", "--row-timeout", "0"]) == 2
    assert "--row-timeout must be > 0" in capsys.readouterr().err


def _sleep_then(value, seconds):
    time.sleep(seconds)
    return value, os.getpid(), time.monotonic()


def _raise():
    raise ValueError("from the child")


def test_run_isolated_returns_raises_and_times_out():
    outcome = run_isolated(_sleep_then, ("x", 0))
    assert outcome.ok and outcome.value[0] == "x" and outcome.value[1] != os.getpid()
    with pytest.raises(ValueError, match="from the child"):
        run_isolated(_raise)
    assert run_isolated(_sleep_then, ("x", 30), timeout=0.5).status == "timeout"


def _meet(folder, me, other, bound_s=120.0):
    """Say "I run" in `folder` and wait for `other` to say it too: True if both ran at once.
    The bound only ends a wait that cannot succeed (tasks one at a time); it is not a speed claim."""
    (folder / me).touch()
    end = time.monotonic() + bound_s
    while not (folder / other).exists():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def _interval(seconds):
    start = time.monotonic()  # CLOCK_MONOTONIC: one clock for every process of the machine
    time.sleep(seconds)
    return start, time.monotonic()


_signal_in_fork_hook = False


def _raise_sigint_if_armed() -> None:
    if _signal_in_fork_hook:
        signal.raise_signal(signal.SIGINT)


os.register_at_fork(after_in_parent=_raise_sigint_if_armed)  # for good: armed only in the test below


def test_a_ctrl_c_during_the_childs_start_is_raised_not_lost():
    """A Ctrl-C that comes while the parent runs its at-fork hooks (logging's lock is one): raised
    inside such a hook, Python reports it as ignored and the run goes on as if none had come
    (a hung row then held `sweep` for ever). Here it comes inside one on every fork: the call
    must end in KeyboardInterrupt, with its child killed, not return the child's value."""
    global _signal_in_fork_hook
    children = set(multiprocessing.active_children())
    _signal_in_fork_hook = True
    try:
        with pytest.raises(KeyboardInterrupt):  # lost, the call would wait out its 10 s timeout
            run_isolated(time.sleep, (60,), method="fork", timeout=10)
    finally:
        _signal_in_fork_hook = False
    assert set(multiprocessing.active_children()) <= children  # the sleeping child killed and reaped
    assert run_isolated(os.getpid, method="fork").ok  # disarmed: as before


def test_local_executor_runs_untimed_tasks_together_and_timed_ones_alone(tmp_path):
    with LocalExecutor(jobs=2) as ex:
        untimed = [ex.submit(_meet, tmp_path, f"{i}", f"{1 - i}") for i in range(2)]
        assert [f.result().value for f in untimed] == [True, True]  # each saw the other running
        timed = [ex.submit(_interval, 0.2, timing=True) for i in range(2)]
        first, second = sorted(f.result().value for f in timed)
    assert first[1] <= second[0]  # one after the other: the second started after the first ended


# --- accuracy and stability rows through the executor ------------------------------------------


def _accuracy_inputs():
    from clothbench.harness.plan import plan_variants
    from clothbench.model.scene import load_setup

    setup = load_setup("drape").replace(grid=6)
    variants, _ = plan_variants(["numpy"], [setup.solver])
    return setup.scene, variants, [2 * setup.solver.dt, setup.solver.dt]


def test_accuracy_over_two_jobs_gives_the_numbers_of_one_process():
    from clothbench.analysis.convergence import run_accuracy

    scene, variants, dts = _accuracy_inputs()
    plain = run_accuracy(scene, variants, dts, 0.02)
    with LocalExecutor(jobs=2) as ex:
        spread = run_accuracy(scene, variants, dts, 0.02, executor=ex)
    timing = NOT_THE_RESULT
    # NaN (a column a row does not have, such as a Verlet row's vs_exact_*) is unequal to
    # itself once a row has crossed a process: compared as its text
    same = lambda v: "nan" if isinstance(v, float) and v != v else v  # noqa: E731
    strip = lambda rows: [{k: same(v) for k, v in r.as_dict().items() if k not in timing} for r in rows]  # noqa: E731
    assert strip(plain.rows) == strip(spread.rows)
    assert all(r.status == "ok" for r in spread.rows)


def test_an_accuracy_row_that_crashes_says_so_and_the_others_are_measured(faulty):
    from clothbench.analysis.convergence import run_accuracy
    from clothbench.harness.plan import plan_variants

    from clothbench.model.scene import load_setup

    scene, _, dts = _accuracy_inputs()
    variants, _ = plan_variants(["fake-abort", "fake-fine"], [load_setup("drape").solver])
    with LocalExecutor(jobs=2) as ex:
        result = run_accuracy(scene, variants, dts, 0.02, executor=ex)
    status = {(r.backend, r.dt): r.status for r in result.rows}
    assert all(s.startswith("crashed") and "SIGABRT" in s for (b, _), s in status.items() if b == "fake-abort")
    assert all(s == "ok" for (b, _), s in status.items() if b == "fake-fine")
    assert len(status) == 4


def test_accuracy_and_stability_cli_take_jobs(tmp_path, capsys):
    acc = tmp_path / "a.csv"
    assert main(["accuracy", "--backends", "numpy", "--grid", "6", "--levels", "2", "--time", "0.02", "--jobs", "2",
                 "--out", str(acc)]) == 0  # fmt: skip
    assert acc.read_text().count("\n") == 1 + 4  # f32 and f64 at 2 dts
    st = tmp_path / "s.csv"
    assert main(["stability", "--backends", "numpy", "--grid", "8", "--steps", "100", "--scenes", "flat",
                 "--stiffness", "1000,10000", "--jobs", "2", "--out", str(st)]) == 0  # fmt: skip
    assert st.read_text().count("\n") == 1 + 4
    assert main(["accuracy", "--backends", "numpy", "--jobs", "0"]) == 2
    assert "--jobs must be >= 1" in capsys.readouterr().err
