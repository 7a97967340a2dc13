"""`clothbench machine` (clothbench/machine_fitness.py): whether the machine is fit to benchmark
now, from a fake /proc and /sys and recorded /proc/stat lines: no real load, no real clock."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest

from clothbench import machine_fitness
from clothbench.cli import main
from clothbench.machine_load import LoadSampler

TICKS = 100  # /proc/stat's ticks per second in these recordings


def recorded_sampler(other_cores: float, steal_share: float = 0.0, cores: int = 2) -> LoadSampler:
    """A sampler whose two /proc/stat snapshots, one second apart, hold `other_cores` cores'
    worth of others' busy time (this process used none) and `steal_share` of the machine stolen."""
    total = cores * TICKS
    busy, steal = round(other_cores * TICKS), round(steal_share * total)
    lines = iter([
        "cpu 1000 0 0 9000 0 0 0 0 0 0",
        f"cpu {1000 + busy} 0 0 {9000 + total - busy - steal} 0 0 0 {steal} 0 0",
    ])  # fmt: skip
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
    f = machine_fitness.check(recorded_sampler(0.0, steal_share=0.2), 1.0, fake_proc(tmp_path, {}),
                              fake_sys(tmp_path, "performance"), [0, 1])  # fmt: skip
    assert f.fit is False and "steal 20%" in f.verdict


def test_a_powersave_governor_is_a_problem_and_turbo_siblings_and_unreadable_cpufreq_are_notes(tmp_path):
    f = machine_fitness.check(recorded_sampler(0.0), 1.0, fake_proc(tmp_path, {}),
                              fake_sys(tmp_path, "powersave", "0", siblings={0: "0-1", 1: "0-1"}), [0, 1])  # fmt: skip
    assert f.fit is False and f.verdict == "frequency governor powersave"
    assert "performance" in f.problems[0].fix
    assert f.turbo is True and any("turbo boost is on" in n for n in f.notes)
    assert f.smt_shared == [(0, 1)] and any("0+1 are hyperthreads of one core" in n for n in f.notes)
    bare = machine_fitness.check(recorded_sampler(0.0), 1.0, fake_proc(tmp_path / "b", {}), fake_sys(tmp_path / "b"),
                                 [0, 1])  # fmt: skip
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
    # resumed with nothing left to measure: no row, so nothing to say of the machine
    assert main([*argv, "--resume"]) == 0
    assert not any(x.startswith("machine: ") for x in capsys.readouterr().err.splitlines())
