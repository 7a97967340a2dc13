"""Kernel shapes chosen by measurement (clothbench/backends/tuning.py): measured once per key,
remembered on disk, measured again on --retune, never measured with tuning off; a choice made
on a busy machine, or between candidates within their noise, is provisional and measured again
at the next quiet meeting. Every timing and every load here is recorded, never
measured: the clock is a fake one that moves only when asked."""

from __future__ import annotations

import json

import pytest

from clothbench import machine_load
from clothbench.backends import tuning
from clothbench.cli import main
from clothbench.errors import ClothbenchError

KEY = {"device": "test device", "driver": "1.0", "grid": "64"}


class Machine:
    """A recorded machine: /proc/stat's first line and a clock that moves only when the
    sampler sleeps (or a test says so), with `other_cores` of other processes' load."""

    def __init__(self, other_cores: float = 0.0, cores: int = 2, steal_share: float = 0.0):
        self.other_cores, self.cores, self.steal_share = other_cores, cores, steal_share
        self.t, self.busy, self.steal, self.total = 0.0, 0.0, 0.0, 0.0

    def pass_time(self, seconds: float) -> None:
        self.t += seconds
        self.busy += self.other_cores * seconds * 100
        self.steal += self.steal_share * self.cores * seconds * 100
        self.total += self.cores * seconds * 100

    def stat(self) -> str:
        idle = self.total - self.busy - self.steal
        return f"cpu {int(self.busy)} 0 0 {int(idle)} 0 0 0 {int(self.steal)} 0 0"

    def sampler(self) -> machine_load.LoadSampler:
        return machine_load.LoadSampler(self.stat, lambda: self.t, lambda: 0.0, self.cores, self.pass_time, 100)


@pytest.fixture
def machine(monkeypatch):
    """The machine tuning watches: quiet unless a test loads it."""
    m = Machine()
    monkeypatch.setattr(tuning, "sampler", m.sampler())
    monkeypatch.setattr(tuning, "_measured_here", set())
    monkeypatch.setattr(tuning, "_met", {})
    return m


@pytest.fixture
def tuning_on(tmp_path, monkeypatch, machine):
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    return tmp_path


def later_process():
    """What a new process starts with: no key measured by it, no choice met."""
    tuning._measured_here.clear()
    tuning._met.clear()


def stored(cache, backend="x") -> dict:
    (entry,) = json.loads((cache / "tuning" / f"{backend}.json").read_text()).values()
    return entry


def timer(times: dict[str, float | list[float]]):
    """A time_candidate that returns `times` (a list: one value per turn) and counts its calls."""
    calls: list[str] = []

    def time_candidate(name: str) -> float:
        turn = calls.count(name)
        calls.append(name)
        if times[name] is None:
            raise ClothbenchError(f"{name} does not fit this device")
        return times[name][turn] if isinstance(times[name], list) else times[name]

    return time_candidate, calls


ROUNDS = tuning.TUNING_ROUNDS


def test_the_fastest_candidate_wins_and_is_remembered(tuning_on):
    measure, calls = timer({"a": 3.0, "b": 1.0, "c": 2.0})
    assert tuning.choose_shape("x", KEY, ["a", "b", "c"], measure) == "b"
    assert calls == ["a", "b", "c"] * ROUNDS  # the candidates take turns
    stored = json.loads((tuning_on / "tuning" / "x.json").read_text())
    (entry,) = stored.values()
    assert entry["choice"] == "b" and entry["ms"] == {"a": 3000.0, "b": 1000.0, "c": 2000.0}
    # a second backend with the same key reads the choice back without measuring
    again, calls_again = timer({"a": 0.1, "b": 1.0, "c": 2.0})
    assert tuning.choose_shape("x", KEY, ["a", "b", "c"], again) == "b" and calls_again == []


def test_retune_measures_again_and_replaces_the_choice(tuning_on):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    measure, calls = timer({"a": 0.5, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure, retune=True) == "a" and len(calls) == 2 * ROUNDS
    assert tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 9.0, "b": 1.0})[0]) == "a"


def test_another_key_is_measured_on_its_own(tuning_on):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    measure, calls = timer({"a": 1.0, "b": 2.0})
    assert tuning.choose_shape("x", {**KEY, "grid": "128"}, ["a", "b"], measure) == "a" and len(calls) == 2 * ROUNDS


def test_a_load_that_slows_one_turn_does_not_decide(tuning_on):
    # b is the faster shape, but the other core was busy during its first turn
    measure, calls = timer({"a": [2.0, 2.1, 2.0], "b": [3.5, 1.0, 1.1]})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b"
    (entry,) = json.loads((tuning_on / "tuning" / "x.json").read_text()).values()
    assert entry["ms"] == {"a": 2000.0, "b": 1000.0}  # each candidate's fastest turn


def test_a_candidate_that_fails_is_dropped_unless_all_do(tuning_on):
    measure, calls = timer({"a": None, "b": 5.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b"
    assert calls.count("a") == 1  # not tried again in the later turns
    with pytest.raises(ClothbenchError, match="no kernel shape runs here"):
        tuning.choose_shape("y", KEY, ["a", "b"], timer({"a": None, "b": None})[0])


def test_a_damaged_cache_file_is_measured_again_not_fatal(tuning_on):
    (tuning_on / "tuning").mkdir()
    (tuning_on / "tuning" / "x.json").write_bytes(b"\x00\xffnot json")
    assert tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0]) == "b"


def test_with_tuning_off_the_default_runs_and_nothing_is_measured(tmp_path, monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.setenv("CLOTHBENCH_TUNING", "off")
    measure, calls = timer({"a": 2.0, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "a" and calls == []
    assert not (tmp_path / "tuning" / "x.json").exists()


def test_a_bad_tuning_setting_is_one_line(monkeypatch):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "maybe")
    with pytest.raises(ClothbenchError, match="CLOTHBENCH_TUNING must be on or off"):
        tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])


# --- the machine's load (clothbench/machine_load.py) -------------------------------------------


def test_proc_stat_line_parses_to_busy_steal_and_total_ticks():
    # a recorded first line of /proc/stat: user nice system idle iowait irq softirq steal guest guest_nice
    line = "cpu  4705 150 1120 16250 520 0 40 30 200 0\n"
    assert machine_load.parse_cpu_line(line) == (4705 + 150 + 1120 + 40, 30, 4705 + 150 + 1120 + 40 + 16250 + 520 + 30)
    assert machine_load.parse_cpu_line("intr 1 2 3") is None and machine_load.parse_cpu_line(None) is None


def test_other_processes_share_leaves_out_our_own_cpu_time():
    # 1 s on 2 cores: 150 busy ticks of 200, of which our own process used 1.0 s: others 0.5 core
    stats = iter(["cpu 1000 0 0 1000 0 0 0 0 0 0", "cpu 1150 0 0 1050 0 0 0 0 0 0"])
    clock, own = iter([10.0, 11.0]), iter([3.0, 4.0])
    s = machine_load.LoadSampler(lambda: next(stats), lambda: next(clock), lambda: next(own), cores=2, ticks_per_s=100)
    load = s.between(s.snapshot(), s.snapshot())
    assert load.other_cores == pytest.approx(0.5) and load.other_share == pytest.approx(0.25)
    assert load.busy is True, "half a core of others is BUSY_CORES"
    stats = iter(["cpu 1000 0 0 1000 0 0 0 0 0 0", "cpu 1110 0 0 1090 0 0 0 0 0 0"])
    clock, own = iter([10.0, 11.0]), iter([3.0, 4.0])
    assert s.between(s.snapshot(), s.snapshot()).busy is False, "0.1 core of others is quiet"


def test_steal_makes_a_window_busy_and_a_short_or_unreadable_one_is_unknown():
    m = Machine(other_cores=0.0, steal_share=0.2)
    load = m.sampler().sample(1.0)
    assert load.busy is True and load.steal_share == pytest.approx(0.2, abs=0.01)
    assert Machine().sampler().sample(0.1).busy is None, "a window too short to tell"
    blind = machine_load.LoadSampler(lambda: None, lambda: 0.0, lambda: 0.0, 2, lambda s: None, 100)
    assert blind.sample(1.0).busy is None and "no /proc/stat" in blind.sample(1.0).why


def test_a_short_tuning_waits_out_the_window_to_get_a_verdict(tuning_on, machine):
    machine.other_cores = 1.9
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    assert machine.t == pytest.approx(machine_load.MIN_WINDOW_S) and stored(tuning_on)["load"]["busy"] is True


# --- provisional and final -----------------------------------------------------------------


def test_a_clear_quiet_choice_is_final_and_met_again_without_measuring(tuning_on):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": [2.0, 2.1, 2.0], "b": [1.0, 1.1, 1.0]})[0])
    entry = stored(tuning_on)
    assert entry["status"] == "final" and entry["turns_ms"]["b"] == [1000.0, 1100.0, 1000.0]
    later_process()
    measure, calls = timer({"a": 0.1, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b" and calls == []


def test_the_issue_36_case_busy_tuning_is_provisional_and_the_next_quiet_run_replaces_it(tuning_on, machine):
    # docs/timing.md's case, "Kernel shapes chosen on a busy machine": under other jobs
    # threads=1 looked faster; quiet, threads=2 is
    shapes = ["threads=2", "threads=1"]
    machine.other_cores = 1.4
    busy = {"threads=2": [0.61e-3, 0.55e-3, 0.58e-3], "threads=1": [0.42e-3, 0.41e-3, 0.43e-3]}
    assert tuning.choose_shape("c", KEY, shapes, timer(busy)[0]) == "threads=1"
    entry = stored(tuning_on, "c")
    assert entry["status"] == "provisional" and entry["why"].startswith("busy: other processes 1.4")
    later_process()
    machine.other_cores = 0.02
    quiet = {"threads=2": [0.256e-3, 0.26e-3, 0.257e-3], "threads=1": [0.419e-3, 0.42e-3, 0.421e-3]}
    measure, calls = timer(quiet)
    assert tuning.choose_shape("c", KEY, shapes, measure) == "threads=2" and len(calls) == 2 * ROUNDS
    entry = stored(tuning_on, "c")
    assert entry["status"] == "final" and entry["replaced"]["choice"] == "threads=1"
    assert entry["replaced"]["status"] == "provisional"
    later_process()
    again, calls = timer(busy)
    assert tuning.choose_shape("c", KEY, shapes, again) == "threads=2" and calls == [], "final now"


def test_overlapping_candidates_are_provisional_and_a_quiet_recheck_settles_them(tuning_on):
    # b's fastest turn beats a's by 0.02, less than either's noise (second turn less first: 0.05)
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": [1.02, 1.07, 1.3], "b": [1.0, 1.05, 1.2]})[0])
    entry = stored(tuning_on)
    assert entry["status"] == "provisional" and "within their noise" in entry["why"]
    later_process()
    # the re-measure ties again: on a quiet machine a tie is a tie, final, not re-measured forever
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": [1.0, 1.05, 1.0], "b": [1.01, 1.0, 1.04]})[0])
    assert stored(tuning_on)["status"] == "final"


def test_a_recheck_measures_only_the_best_two_and_the_default(tuning_on, machine):
    machine.other_cores = 1.0
    busy = {"d0": 9.0, "d1": 5.0, "d2": 1.0, "d3": 2.0, "d4": 3.0}
    tuning.choose_shape("x", KEY, list(busy), timer(busy)[0])
    later_process()
    machine.other_cores = 0.0
    measure, calls = timer({"d0": 0.5, "d1": 5.0, "d2": 1.0, "d3": 2.0, "d4": 3.0})
    assert tuning.choose_shape("x", KEY, list(busy), measure) == "d0"
    assert sorted(set(calls)) == ["d0", "d2", "d3"], "the two best by the busy times, and the default"
    assert set(stored(tuning_on)["ms"]) == {"d0", "d2", "d3"}


def test_a_busy_meeting_keeps_the_provisional_choice_and_measures_nothing(tuning_on, machine):
    machine.other_cores = 1.5
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    later_process()
    measure, calls = timer({"a": 0.1, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b" and calls == []
    assert stored(tuning_on)["status"] == "provisional"


def test_the_process_that_measured_does_not_recheck_a_moment_later(tuning_on, machine):
    machine.other_cores = 1.5
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    machine.other_cores = 0.0
    measure, calls = timer({"a": 0.1, "b": 1.0})
    assert tuning.choose_shape("x", KEY, ["a", "b"], measure) == "b" and calls == []


def test_a_recheck_the_load_comes_back_to_changes_nothing(tuning_on, machine):
    machine.other_cores = 1.5
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    before = stored(tuning_on)
    later_process()
    machine.other_cores = 0.0

    def loaded_again(name):  # quiet at the look, busy while re-measuring
        machine.other_cores = 1.5
        return {"a": 0.1, "b": 1.0}[name]

    assert tuning.choose_shape("x", KEY, ["a", "b"], loaded_again) == "b" and stored(tuning_on) == before


def test_a_busy_retune_is_provisional_too(tuning_on, machine):
    tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 2.0, "b": 1.0})[0])
    machine.other_cores = 1.2
    assert tuning.choose_shape("x", KEY, ["a", "b"], timer({"a": 0.5, "b": 1.0})[0], retune=True) == "a"
    assert stored(tuning_on)["status"] == "provisional"


def test_an_entry_from_before_statuses_is_provisional_and_rechecked_when_quiet(tuning_on):
    (tuning_on / "tuning").mkdir()
    old = {"choice": "threads=1", "ms": {"threads=1": 0.419, "threads=2": 0.61}, "failed": {}, "measured_at": "x"}
    (tuning_on / "tuning" / "c.json").write_text(json.dumps({json.dumps(KEY, sort_keys=True): old}))
    assert tuning.listing()[0]["status"] == "provisional"
    measure, calls = timer({"threads=2": 0.26e-3, "threads=1": 0.42e-3})
    assert tuning.choose_shape("c", KEY, ["threads=2", "threads=1"], measure) == "threads=2" and calls
    assert stored(tuning_on, "c")["status"] == "final"


# --- a row against its tuning (the sweep's note) ---------------------------------------------


def test_a_row_from_a_provisional_choice_says_so(tuning_on, machine):
    machine.other_cores = 1.5
    tuning.choose_shape("c", KEY, ["threads=2", "threads=1"], timer({"threads=2": 2e-3, "threads=1": 1e-3})[0])
    note = tuning.check_row("c", "threads=1", 1.0, quiet=False)
    assert note.startswith("kernel shape threads=1 from a provisional tuning (busy:")
    assert tuning.check_row("c", "threads=2", 1.0, quiet=False) == "", "a --shape run is not the tuned one"
    tuning.forget_met()
    assert tuning.check_row("c", "threads=1", 1.0, quiet=False) == "", "nothing met: tuning off or --shape"


def test_a_quiet_row_far_off_its_tuning_sends_the_choice_back_once(tuning_on):
    shapes = ["threads=2", "threads=1"]
    tuning.choose_shape("c", KEY, shapes, timer({"threads=2": 1e-3, "threads=1": 2e-3})[0])  # 1 ms recorded
    assert tuning.check_row("c", "threads=2", 1.4, quiet=True) == "", "within FAR_OFF"
    assert tuning.check_row("c", "threads=2", 3.0, quiet=False) == "", "a busy row says nothing of the tuning"
    assert "3.0x its tuning" in tuning.check_row("c", "threads=2", 3.0, quiet=True)
    assert stored(tuning_on, "c")["status"] == "provisional"
    later_process()
    measure, calls = timer({"threads=2": 1e-3, "threads=1": 2e-3})
    assert tuning.choose_shape("c", KEY, shapes, measure) == "threads=2" and calls, "re-measured, quiet"
    entry = stored(tuning_on, "c")
    assert entry["status"] == "final" and entry["row_rechecked"] is True
    assert tuning.check_row("c", "threads=2", 3.0, quiet=True) == "", "asked and answered: not again"
    assert stored(tuning_on, "c")["status"] == "final"


# --- clothbench tuning ---------------------------------------------------------------------


def test_the_tuning_listing_shows_status_when_load_and_closeness(tuning_on, machine, capsys):
    machine.other_cores = 1.5
    tuning.choose_shape(
        "c",
        {**KEY, "cpu": "a long cpu name"},
        ["threads=2", "threads=1"],
        timer({"threads=2": [2e-3, 2.1e-3, 2e-3], "threads=1": [1e-3, 1.05e-3, 1.1e-3]})[0],
    )
    assert main(["tuning", "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert (row["backend"], row["choice"], row["status"], row["next_best"]) == (
        "c",
        "threads=1",
        "provisional",
        "threads=2",
    )
    assert row["apart"] == pytest.approx(1.0) and row["noise"] == pytest.approx(0.05) and row["other_share"] > 0.5
    assert main(["tuning"]) == 0
    out = capsys.readouterr().out
    assert "threads=1" in out and "provisional" in out and "threads=2 +100%" in out and "a long cpu name" not in out


def test_the_tuning_listing_refuses_an_unknown_backend_in_one_line(tuning_on, capsys):
    assert main(["tuning", "--backend", "nosuch"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no cached choice for 'nosuch'" in err


def test_a_timed_turn_is_a_fixed_amount_of_work_within_its_limits():
    # about TURN_PARTICLE_STEPS particle-steps: fewer steps as the grid grows, never below
    # `least` nor above `most`, and a whole number of multi-step launches
    work = tuning.TURN_PARTICLE_STEPS
    assert tuning.turn_steps(256 * 256) == work // (256 * 256) < 50
    assert tuning.turn_steps(2048 * 2048) == 1 and tuning.turn_steps(2048 * 2048, least=2) == 2
    assert tuning.turn_steps(32 * 32) == 50 and tuning.turn_steps(32 * 32, most=256) == 256
    assert tuning.turn_steps(64 * 64, most=8) == 8
    assert tuning.turn_steps(64 * 64, least=2, most=64, work=1 << 16) == 16  # OpenCL PBD's own work
    steps = tuning.turn_steps(128 * 128, most=256, multiple=16)
    assert steps % 16 == 0 and work // (128 * 128) <= steps < work // (128 * 128) + 16
