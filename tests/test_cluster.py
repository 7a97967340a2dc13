"""A sweep on a Dask distributed cluster (a LocalCluster of two worker processes on
loopback): a worker killed mid-sweep has its rows rescheduled, and the CSV, written by the
client alone, holds every planned row exactly once, each with the host it ran on."""

from __future__ import annotations

import os
import signal
import threading
import time

import pytest

from clothbench.cli import main
from clothbench.environment import host_name
from clothbench.harness.sweep_csv import row_key

from test_sweep import read_csv
from conftest import NOT_THE_RESULT

distributed = pytest.importorskip("distributed")
dask = pytest.importorskip("dask")

ARGS = ["sweep", "--backends", "numpy", "--grids", "8,12,16", "--steps", "3", "--repeat", "2"]


@pytest.fixture
def cluster(monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_FAULT", "numpy:slow")  # every row takes >= 2 s (the workers inherit it)
    monkeypatch.setenv("DASK_DISTRIBUTED__WORKER__DAEMON", "False")
    # Dask's nanny writes its workers' thread settings (OMP_NUM_THREADS=1, MKL_..., OPENBLAS_...)
    # into this process's environment before it spawns them, and leaves them: every later test in
    # this xdist worker would run c on one thread and record them in its rows' env column
    environ = dict(os.environ)
    with dask.config.set({"distributed.worker.daemon": False}):
        with (
            distributed.LocalCluster(
                n_workers=2,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
                resources={"timing": 1},
                silence_logs=40,
            ) as c,
            distributed.Client(c) as client,
        ):
            yield c, client
    os.environ.clear()
    os.environ.update(environ)


def _rows(path) -> int:
    try:
        return max(0, path.read_text().count("\n") - 1)
    except FileNotFoundError:
        return 0


@pytest.mark.full  # a fault on the cluster; its rows asking for the timing resource stay quick
def test_a_worker_killed_mid_sweep_has_its_rows_rescheduled_and_each_row_is_written_once(tmp_path, cluster):
    c, client = cluster
    out = tmp_path / "s.csv"
    killed = []

    def kill_one_worker():
        deadline = time.monotonic() + 90
        while _rows(out) < 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # both workers are mid-row now
        pids = client.run(os.getpid)
        victim = sorted(pids.values())[0]
        os.kill(victim, signal.SIGKILL)
        killed.append(victim)

    killer = threading.Thread(target=kill_one_worker)
    killer.start()
    assert main([*ARGS, "--out", str(out), "--scheduler", c.scheduler_address]) == 0
    killer.join()
    assert killed
    rows = read_csv(out)
    assert len(rows) == 6  # 3 grids x (f32, f64)
    assert len({row_key(r) for r in rows}) == 6
    assert all(r["status"] == "ok" for r in rows), [(r["status"], r["note"]) for r in rows]
    assert all(r["host"] == host_name() for r in rows)
    assert killed[0] not in client.run(os.getpid).values()  # it died; its nanny started another

    # --resume across the cluster: nothing is missing, nothing is measured again
    assert main([*ARGS, "--out", str(out), "--scheduler", c.scheduler_address, "--resume"]) == 0
    assert len(read_csv(out)) == 6


def test_timed_rows_ask_for_the_timing_resource_and_error_rows_do_not(cluster):
    from clothbench.harness.executor import DaskExecutor

    c, client = cluster
    ex = DaskExecutor(c.scheduler_address, client=client)
    timed = ex.submit(os.getpid, timing=True)
    free = ex.submit(os.getpid)
    assert timed.result().ok and free.result().ok and timed.result().host == host_name()
    wanted = client.run_on_scheduler(
        lambda dask_scheduler: {k: dict(t.resource_restrictions or {}) for k, t in dask_scheduler.tasks.items()}
    )
    assert {"timing": 1} in wanted.values() and {} in wanted.values()


@pytest.mark.full  # two studies on a cluster; the sweep's rescheduling stays quick
def test_accuracy_and_stability_on_the_cluster_give_the_local_numbers(tmp_path, cluster, monkeypatch):
    c, _ = cluster
    monkeypatch.delenv("CLOTHBENCH_FAULT")  # here; the workers keep theirs: slower rows, the same numbers
    args = ["accuracy", "--backends", "numpy", "--grid", "6", "--levels", "2", "--time", "0.02"]
    assert main([*args, "--out", str(tmp_path / "local.csv")]) == 0
    assert main([*args, "--out", str(tmp_path / "dask.csv"), "--scheduler", c.scheduler_address]) == 0
    import csv

    timing = NOT_THE_RESULT
    read = lambda p: [{k: v for k, v in r.items() if k not in timing} for r in csv.DictReader(open(p))]  # noqa: E731
    assert read(tmp_path / "local.csv") == read(tmp_path / "dask.csv")
    st = [
        "stability",
        "--backends",
        "numpy",
        "--grid",
        "8",
        "--steps",
        "100",
        "--scenes",
        "flat",
        "--stiffness",
        "1000",
    ]
    assert main([*st, "--out", str(tmp_path / "st.csv"), "--scheduler", c.scheduler_address]) == 0
    assert (tmp_path / "st.csv").read_text().count("\n") == 1 + 2
