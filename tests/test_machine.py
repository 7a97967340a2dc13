"""`clothbench machine` (clothbench/machine_fitness.py): whether the machine is fit to benchmark
now, from a fake /proc and /sys and recorded /proc/stat lines: no real load, no real clock."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import pytest

from clothbench import machine_fitness
from clothbench.cli import main
from clothbench.harness.noise import row_doubts
from clothbench.machine_load import LoadSampler

TICKS = 100  # /proc/stat's ticks per second in these recordings


def recorded_sampler(other_cores: float, steal_share: float = 0.0, cores: int = 2) -> LoadSampler:
    """A sampler whose two /proc/stat snapshots, one second apart, hold `other_cores` cores'
    worth of others' busy time (this process used none) and `steal_share` of the machine stolen."""
    total = cores * TICKS
    busy, steal = round(other_cores * TICKS), round(steal_share * total)
    lines = iter(
        [
            "cpu 1000 0 0 9000 0 0 0 0 0 0",
            f"cpu {1000 + busy} 0 0 {9000 + total - busy - steal} 0 0 0 {steal} 0 0",
        ]
    )
    clock = itertools.chain([0.0], itertools.repeat(1.0))  # the window opens at 0 and is 1 s long
    return LoadSampler(lambda: next(lines), lambda: next(clock), lambda: 0.0, cores, lambda s: None, TICKS)


def fake_proc(root: Path, ticks: dict[int, int]) -> Path:
    """root/proc with a loadavg and a process per pid whose utime is its ticks (stime 0)."""
    proc = root / "proc"
    proc.mkdir(parents=True, exist_ok=True)
    (proc / "loadavg").write_text("1.50 1.20 0.90 2/300 4242\n")
    for pid, used in ticks.items():
        (proc / str(pid)).mkdir(exist_ok=True)
        # pid (comm) state ppid ... utime(14) stime(15): fields 4-13 are placeholders
        (proc / str(pid) / "stat").write_text(f"{pid} (hog {pid}) R 1 1 1 0 -1 0 0 0 0 0 {used} 0 0 0 20 0 1 0\n")
    return proc


def fake_sys(
    root: Path, governor: str | None = None, no_turbo: str | None = None, siblings: dict | None = None
) -> Path:
    sys_root = root / "sys"
    for cpu in (0, 1):
        base = sys_root / f"devices/system/cpu/cpu{cpu}"
        (base / "topology").mkdir(parents=True, exist_ok=True)
        (base / "topology/thread_siblings_list").write_text((siblings or {}).get(cpu, str(cpu)) + "\n")
        if governor is not None:
            (base / "cpufreq").mkdir(exist_ok=True)
            (base / "cpufreq/scaling_governor").write_text(governor + "\n")
    if no_turbo is not None:
        (sys_root / "devices/system/cpu/intel_pstate").mkdir(parents=True, exist_ok=True)
        (sys_root / "devices/system/cpu/intel_pstate/no_turbo").write_text(no_turbo + "\n")
    return sys_root


class GrowingProc:
    """A sampler whose sleep advances the fake processes' CPU ticks, as the window would."""

    def __init__(self, sampler: LoadSampler, proc: Path, ticks_after: dict[int, int]):
        self.inner, self.proc, self.after = sampler, proc, ticks_after
        self.ticks_per_s = sampler.ticks_per_s

    def sample(self, seconds):
        for pid, ticks in self.after.items():
            fake_proc(self.proc.parent, {pid: ticks})
        return self.inner.sample(seconds)


def test_a_quiet_machine_with_the_performance_governor_is_fit(tmp_path):
    proc = fake_proc(tmp_path, {})
    f = machine_fitness.check(recorded_sampler(0.02), 1.0, proc, fake_sys(tmp_path, "performance", "1"), [0, 1])
    assert f.fit is True and f.problems == [], f.problems
    assert f.verdict.startswith("quiet (other processes 0.02 of 2 cores")
    assert f.turbo is False and f.governors == {"performance": 2} and f.loadavg == "1.50 1.20 0.90"


def test_a_busy_machine_names_the_process_that_used_it_and_what_to_do(tmp_path):
    proc = fake_proc(tmp_path, {4242: 500, 4343: 10})
    sampler = GrowingProc(recorded_sampler(1.2), proc, {4242: 620, 4343: 11})  # 1.2 cores, and 0.01
    f = machine_fitness.check(sampler, 1.0, proc, fake_sys(tmp_path), [0, 1])
    assert f.fit is False
    assert [(h.pid, round(h.cores, 2)) for h in f.heavy] == [(4242, 1.2)]  # 4343's 0.01 is background
    (busy,) = f.problems
    assert busy.what.startswith("busy (other processes 1.20 of 2 cores") and "hog 4242 (pid 4242" in busy.fix
    assert f.verdict == busy.what


def test_steal_alone_makes_it_busy(tmp_path):
    f = machine_fitness.check(
        recorded_sampler(0.0, steal_share=0.2), 1.0, fake_proc(tmp_path, {}), fake_sys(tmp_path, "performance"), [0, 1]
    )
    assert f.fit is False and "steal 20%" in f.verdict


def test_a_powersave_governor_is_a_problem_and_turbo_siblings_and_unreadable_cpufreq_are_notes(tmp_path):
    f = machine_fitness.check(
        recorded_sampler(0.0),
        1.0,
        fake_proc(tmp_path, {}),
        fake_sys(tmp_path, "powersave", "0", siblings={0: "0-1", 1: "0-1"}),
        [0, 1],
    )
    assert f.fit is False and f.verdict == "frequency governor powersave"
    assert "performance" in f.problems[0].fix
    assert f.turbo is True and any("turbo boost is on" in n for n in f.notes)
    assert f.smt_shared == [(0, 1)] and any("0+1 are hyperthreads of one core" in n for n in f.notes)
    bare = machine_fitness.check(
        recorded_sampler(0.0), 1.0, fake_proc(tmp_path / "b", {}), fake_sys(tmp_path / "b"), [0, 1]
    )
    assert bare.fit is True and bare.turbo is None and bare.governors == {}
    assert any("governor not readable" in n for n in bare.notes)


def test_without_proc_stat_the_verdict_is_unknown_not_a_guess(tmp_path):
    blind = LoadSampler(lambda: None, lambda: 0.0, lambda: 0.0, 2, lambda s: None, TICKS)
    f = machine_fitness.check(blind, 1.0, tmp_path / "no-proc", tmp_path / "no-sys", [0])
    assert f.fit is None and f.verdict.startswith("unknown (load not measured")
    assert f.heavy == [] and f.loadavg is None


@pytest.mark.parametrize("text, cpus", [("0", [0]), ("0-3", [0, 1, 2, 3]), ("0,2-3,8", [0, 2, 3, 8])])
def test_cpu_lists_are_read_as_the_kernel_writes_them(text, cpus):
    assert machine_fitness.parse_cpu_list(text) == cpus


def test_the_command_prints_a_verdict_and_its_json_is_the_whole_state(monkeypatch, capsys, tmp_path):
    proc = fake_proc(tmp_path, {})
    real_check = machine_fitness.check

    def check(window_s):
        assert window_s == machine_fitness.WINDOW_S
        return real_check(recorded_sampler(0.9), window_s, proc, fake_sys(tmp_path, "performance"), [0, 1])

    monkeypatch.setattr(machine_fitness, "check", check)
    assert main(["machine"]) == 0
    out = capsys.readouterr().out
    assert "verdict     NOT fit to benchmark now: busy (other processes 0.90 of 2 cores" in out
    assert "PROBLEM     busy" in out and "governor    performance x2" in out
    assert main(["machine", "--json"]) == 0
    state = json.loads(capsys.readouterr().out)
    assert (
        state["fit"] is False
        and state["load"]["other_cores"] == 0.9
        and state["problems"][0]["what"].startswith("busy")
    )


@pytest.mark.parametrize("window", ["0.1", "100", "nan"])
def test_a_window_out_of_range_is_one_line_and_exit_2(window, capsys):
    assert main(["machine", "--window", window]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--window takes 0.25 to 60 seconds" in err


def test_a_sweep_says_at_its_start_whether_the_machine_is_fit(monkeypatch, capsys, tmp_path):
    proc = fake_proc(tmp_path, {})
    real_check = machine_fitness.check
    busy = lambda window_s: real_check(recorded_sampler(1.5), window_s, proc, fake_sys(tmp_path), [0, 1])  # noqa: E731
    monkeypatch.setattr(machine_fitness, "check", busy)
    out = tmp_path / "s.csv"
    argv = ["sweep", "--backends", "numpy", "--grids", "8", "--steps", "2", "--repeat", "2", "--out", str(out)]
    assert main(argv) == 0
    err = capsys.readouterr().err.splitlines()
    line = next(x for x in err if x.startswith("machine: "))
    assert line.startswith("machine: NOT fit to benchmark now: busy (other processes 1.50 of 2 cores")
    assert err.index(line) < next(i for i, x in enumerate(err) if "rows measured" in x)
    # and every row of the run records that verdict, measured once
    import csv

    states = {r["machine_state"] for r in csv.DictReader(out.open())}
    assert len(states) == 1 and states.pop().startswith("busy (other processes 1.50 of 2 cores")
    # resumed with nothing left to measure: no row, so nothing to say of the machine
    assert main([*argv, "--resume"]) == 0
    assert not any(x.startswith("machine: ") for x in capsys.readouterr().err.splitlines())


# --- the machine's state in every row -----------------------------------------------


class FixedLoad(LoadSampler):
    """A sampler whose every window saw `other_cores` of 2 cores used by others: recorded
    /proc/stat lines, one second apart, on a clock that moves only when read."""

    def __init__(self, other_cores: float):
        busy = round(other_cores * TICKS)  # of 2 cores x 100 ticks in the second
        self.lines = itertools.cycle(
            ["cpu 1000 0 0 9000 0 0 0 0 0 0", f"cpu {1000 + busy} 0 0 {9000 + 2 * TICKS - busy} 0 0 0 0 0 0"]
        )
        self.t = 0.0
        super().__init__(lambda: next(self.lines), self._tick, lambda: 0.0, 2, lambda s: None, TICKS)

    def _tick(self) -> float:
        self.t += 0.5  # each snapshot half a second after the last: a 1 s window from start to stop
        return self.t


@pytest.fixture
def machine_seen_as(monkeypatch):
    """machine_seen_as(cores): every LoadSampler clothbench makes from now on sees that load."""
    from clothbench import machine_load

    def seen(other_cores: float) -> None:
        monkeypatch.setattr(machine_load, "LoadSampler", lambda *a, **k: FixedLoad(other_cores))

    return seen


@pytest.mark.parametrize("other_cores, busy", [(1.2, True), (0.02, False)])
def test_a_sweep_row_records_how_busy_the_machine_was_and_a_busy_one_says_so(
    machine_seen_as, tmp_path, capsys, other_cores, busy
):
    import csv

    machine_seen_as(other_cores)
    out = tmp_path / "s.csv"
    argv = ["sweep", "--backends", "numpy", "--grids", "8", "--steps", "2", "--repeat", "4", "--out", str(out)]
    assert main(argv) == 0
    rows = list(csv.DictReader(out.open()))
    assert {r["busy"] for r in rows} == {"true" if busy else "false"}
    assert all(r["load"].startswith(f"other processes {other_cores:.2f} of 2 cores") for r in rows)
    printed = capsys.readouterr().out
    noted = [r for r in rows if "the figure may not hold: busy (other processes" in r["note"]]
    if busy:
        assert len(noted) == len(rows) and printed.count("ok, busy") == len(rows)
        assert f"{len(rows)} rows may not hold" in printed
    else:  # quiet: no row is busy; one may still be unstable, from its own (real) chunks
        assert noted == [] and "ok, busy" not in printed
        unstable = [r for r in rows if row_doubts(r, [float(v) for v in r["chunk_ms"].split()])]
        assert ("may not hold" in printed) == bool(unstable), printed


def test_run_warns_in_one_line_when_the_machine_was_busy_and_not_when_quiet(machine_seen_as, capsys):
    argv = ["run", "--backend", "numpy", "--grid", "8", "--steps", "40", "--json"]
    machine_seen_as(1.5)
    assert main(argv) == 0
    out, err = capsys.readouterr()
    warnings = [line for line in err.splitlines() if "may not hold" in line]
    assert warnings == [w for w in warnings if w.startswith("clothbench: warning: the result may not hold: busy (")]
    assert len(warnings) == 1 and json.loads(out)["busy"] is True
    machine_seen_as(0.0)
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert "busy (" not in err and json.loads(out)["busy"] is False


def test_the_report_lists_the_rows_whose_figure_may_not_hold_and_why(tmp_path):
    import csv

    src = Path(__file__).resolve().parent.parent / "results" / "xeon-2026-12-01.csv"
    with open(src, newline="") as f:
        reader = csv.DictReader(f)
        rows = [r for r in reader if r["grid"] == "32" and r["backend"] in ("numpy", "c") and r["status"] == "ok"]
        columns = [*reader.fieldnames, "busy", "load"]
    steady = " ".join(["1.0"] * 8)
    for r in rows:  # steady chunks: only the busy column can put a row in the table
        r.update(busy="false", load="other processes 0.01 of 2 cores", chunk_ms=steady)
    rows[0].update(busy="true", load="other processes 1.3 of 2 cores, steal 0% over 2.0 s")
    rows[1].update(chunk_ms="0.5 1.5 0.7 1.3 0.6 1.4 1.0 1.0")  # spread wide: unstable
    path = tmp_path / "sweep.csv"
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, columns, lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    out = tmp_path / "r.html"
    assert main(["report", str(path), "--out", str(out)]) == 0
    page = out.read_text(encoding="utf-8")
    section = page[page.index("<h3>Rows whose figure may not hold</h3>") :].split("</table>")[0]
    listed = re.findall(r"<tr><td>(.*?)</td><td>(.*?)</td>", section)
    assert listed == [(rows[0]["backend"], rows[0]["mode"]), (rows[1]["backend"], rows[1]["mode"])], listed
    assert "busy (other processes 1.3 of 2 cores, steal 0% over 2.0 s)" in section
    assert "unstable (spread" in section


def test_a_rows_load_names_the_cpus_it_may_run_on_and_their_clock_where_readable(tmp_path, monkeypatch):
    from clothbench import machine_load

    monkeypatch.setattr(machine_load.os, "sched_getaffinity", lambda pid: {0, 1})
    for cpu, khz in ((0, 2_900_000), (1, 3_100_000)):
        folder = tmp_path / f"devices/system/cpu/cpu{cpu}/cpufreq"
        folder.mkdir(parents=True)
        (folder / "scaling_cur_freq").write_text(f"{khz}\n")
    assert machine_load.cpu_context(str(tmp_path)) == "CPUs 0,1, clock 3.00 GHz"
    assert machine_load.cpu_context(str(tmp_path / "no-sys")) == "CPUs 0,1, clock not readable"
    monkeypatch.setattr(machine_load.os, "sched_getaffinity", lambda pid: {1})  # taskset -c 1
    assert machine_load.cpu_context(str(tmp_path)) == "CPUs 1, clock 3.10 GHz"
