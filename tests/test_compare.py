"""`clothbench compare A B [--fail-above R]`: a ratio per matching row, a confidence interval
from the timed chunks, only significant changes flagged, and exit 1 on a significant
slowdown past the threshold, so that a CI job can fail on one.

The sweeps compared here are timed on a fake clock (a backend that takes a set time per
step, times a seeded jitter), or are real sweeps whose copy is made slower by editing its
numbers: no assertion depends on how fast this machine is."""

from __future__ import annotations

import csv
import types

import numpy as np
import pytest

from clothbench.backends import availability
from clothbench.backends.base import Capabilities
from clothbench.backends.numpy.verlet import NumpyBackend
from clothbench.cli import main
from clothbench.cli.plot import MIN_CHUNKS, ratio_interval, runs_ratio_interval
from clothbench.harness.noise import robust_spread, row_doubts
from clothbench.harness import timing

from test_sweep import register_fake_backends

JITTER = 0.03  # the fake clock's noise: each chunk takes 1 +- 3 % of its nominal time


class ClockBackend(NumpyBackend):
    """The numpy step, taking `ms_per_step` per step (times a jitter) on the fake clock."""

    name = "fake-clock"
    capabilities = Capabilities()
    clock = types.SimpleNamespace(now=0.0)
    ms_per_step = 1.0
    rng = np.random.default_rng(0)

    def advance(self, steps: int) -> None:
        super().advance(steps)
        self.clock.now += 1e-3 * steps * self.ms_per_step * self.rng.uniform(1 - JITTER, 1 + JITTER)


@pytest.fixture
def fake_clock(monkeypatch):
    register_fake_backends(monkeypatch, ClockBackend)
    monkeypatch.setattr(timing, "time", types.SimpleNamespace(perf_counter=lambda: ClockBackend.clock.now))
    yield
    availability.cache_clear()


def clocked_sweep(path, monkeypatch, ms_per_step: float, seed: int, repeat: int = 8):
    monkeypatch.setattr(ClockBackend, "ms_per_step", ms_per_step)
    monkeypatch.setattr(ClockBackend, "rng", np.random.default_rng(seed))
    argv = ["sweep", "--backends", "fake-clock", "--grids", "8,12", "--steps", "2", "--repeat", str(repeat)]
    assert main([*argv, "--out", str(path)]) == 0
    return path


def numpy_sweep(path, repeat: int = 6):
    argv = ["sweep", "--backends", "numpy", "--grids", "8", "--steps", "3", "--repeat", str(repeat)]
    assert main([*argv, "--out", str(path)]) == 0
    return path


def edited(src, dst, factor: float = 1.0, drop=()):
    """A copy of sweep CSV `src` with every time multiplied by `factor` and columns `drop` left out."""
    with open(src, newline="") as f:
        reader = csv.DictReader(f)
        rows, columns = list(reader), [c for c in reader.fieldnames if c not in drop]
    for r in rows:
        r["ms_median"] = f"{float(r['ms_median']) * factor:.6g}"
        r["chunk_ms"] = " ".join(f"{float(v) * factor:.6g}" for v in r["chunk_ms"].split())
    with open(dst, "w", newline="") as f:
        writer = csv.DictWriter(f, columns, extrasaction="ignore", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    return dst


def compare(capsys, *argv) -> tuple[int, str]:
    capsys.readouterr()
    code = main(["compare", *map(str, argv)])
    return code, capsys.readouterr().out


# --- the gate ------------------------------------------------------------------------


def test_a_rerun_of_the_same_sweep_passes_the_gate(tmp_path, monkeypatch, capsys, fake_clock):
    a = clocked_sweep(tmp_path / "a.csv", monkeypatch, 1.0, seed=1)
    b = clocked_sweep(tmp_path / "b.csv", monkeypatch, 1.0, seed=2)  # the same, other noise
    code, out = compare(capsys, a, b, "--fail-above", "1.10")
    assert code == 0, out
    assert "slower than --fail-above" not in out
    assert "(of 2 rows tested)" in out


def test_a_slower_sweep_fails_the_gate_naming_the_rows(tmp_path, monkeypatch, capsys, fake_clock):
    a = clocked_sweep(tmp_path / "a.csv", monkeypatch, 1.0, seed=1)
    b = clocked_sweep(tmp_path / "b.csv", monkeypatch, 1.5, seed=2)
    code, out = compare(capsys, a, b, "--fail-above", "1.10")
    assert code == 1
    failing = [line for line in out.splitlines() if line.startswith("slower than --fail-above 1.1")]
    assert len(failing) == 2 and all("fake-clock" in line for line in failing)
    assert {line.split(" n=")[1].split(":")[0] for line in failing} == {"8", "12"}
    assert "2 slower (of 2 rows tested)" in out

    # significant, but within the threshold: flagged, not failed; without a threshold no gate
    assert compare(capsys, a, b, "--fail-above", "2")[0] == 0
    code, out = compare(capsys, a, b)
    assert code == 0 and "2 slower" in out
    # faster is never a failure
    code, out = compare(capsys, b, a, "--fail-above", "1.10")
    assert code == 0 and "2 faster" in out


def test_a_real_sweep_against_itself_passes_and_against_a_copy_made_twice_as_slow_fails(tmp_path, capsys):
    # 20 chunks: a chunk the machine stalled (here one can take 10x the others) moves the
    # resampled medians of 20 far less than those of 6, and leaves the row stable (noise.py)
    a = numpy_sweep(tmp_path / "a.csv", repeat=20)
    code, out = compare(capsys, a, a, "--fail-above", "1.10")
    assert code == 0 and "significant changes: none (of 2 rows tested)" in out
    slow = edited(a, tmp_path / "slow.csv", factor=2.0)
    code, out = compare(capsys, a, slow, "--fail-above", "1.10")
    # a real row whose chunks spread wide on this machine is inconclusive, not a regression
    # (rows spread alike in the copy); every other row is a slowdown that fails the gate
    with open(a, newline="") as f:
        rows = list(csv.DictReader(f))
    shaky = [r for r in rows if row_doubts(r, [float(v) for v in r["chunk_ms"].split()])]
    assert code == (1 if len(shaky) < 2 else 0), out
    for r in rows:
        name = f"numpy {r['mode']} sphere n=8: B/A 2.00"
        verdict = "inconclusive" if r in shaky else "slower than --fail-above 1.1"
        assert f"{verdict}: {name}" in out, (verdict, name, out)


def test_rows_that_spread_wide_are_inconclusive_and_fail_only_a_strict_gate(tmp_path, monkeypatch, capsys, fake_clock):
    monkeypatch.setattr(ClockBackend, "advance", _wide_advance)  # each chunk 1 +- 50 %: unstable
    a = clocked_sweep(tmp_path / "a.csv", monkeypatch, 1.0, seed=1)
    b = clocked_sweep(tmp_path / "b.csv", monkeypatch, 3.0, seed=2)  # three times as slow: significant
    code, out = compare(capsys, a, b, "--fail-above", "1.10")
    assert code == 0, out  # neither a pass nor a fail: said so
    assert "2 rows inconclusive (unstable: 2)" in out
    assert out.count("inconclusive: fake-clock") == 2 and "spread" in out
    assert "slower than --fail-above" not in out
    code, out = compare(capsys, a, b, "--fail-above", "1.10", "--strict-gate")
    assert code == 1 and out.count("inconclusive under --strict-gate") == 2


def _wide_advance(self, steps: int) -> None:
    NumpyBackend.advance(self, steps)
    self.clock.now += 1e-3 * steps * self.ms_per_step * self.rng.uniform(0.5, 1.5)


def test_a_row_the_machine_was_busy_for_is_inconclusive_and_says_why(tmp_path, monkeypatch, capsys, fake_clock):
    a = clocked_sweep(tmp_path / "a.csv", monkeypatch, 1.0, seed=1)
    b = clocked_sweep(tmp_path / "b.csv", monkeypatch, 1.5, seed=2)
    with open(b, newline="") as f:
        reader = csv.DictReader(f)
        rows, columns = list(reader), [*reader.fieldnames, "busy", "load"]
    rows[0].update(busy="true", load="other processes 1.4 of 2 cores")
    busy = tmp_path / "busy.csv"
    with open(busy, "w", newline="") as f:
        writer = csv.DictWriter(f, columns, restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    code, out = compare(capsys, a, busy, "--fail-above", "1.10")
    assert code == 1, out  # the quiet row's slowdown still fails the gate
    assert "1 rows inconclusive (busy: 1)" in out and "B busy (other processes 1.4 of 2 cores)" in out
    assert out.count("slower than --fail-above") == 1


def test_several_runs_a_side_put_the_spread_between_runs_in_the_interval(tmp_path, monkeypatch, capsys, fake_clock):
    # two runs of A a fifth apart (a machine that changed between runs) and B between them: one
    # run against one is a significant change, the runs together are not
    a1 = clocked_sweep(tmp_path / "a1.csv", monkeypatch, 1.0, seed=1)
    a2 = clocked_sweep(tmp_path / "a2.csv", monkeypatch, 1.2, seed=3)
    b = clocked_sweep(tmp_path / "b.csv", monkeypatch, 1.1, seed=2)
    code, out = compare(capsys, a1, b)
    assert "2 slower (of 2 rows tested)" in out
    code, out = compare(capsys, f"{a1},{a2}", b, "--fail-above", "1.05")
    assert code == 0 and "significant changes: none (of 2 rows tested)" in out, out
    assert f"A: {a1},{a2}" in out.replace("\n", "")


def test_the_runs_interval_holds_the_ratio_and_widens_with_the_spread_between_runs():
    rng = np.random.default_rng(5)
    a = [list(1.0 + 0.02 * rng.standard_normal(10)) for _ in range(3)]
    b = [list(1.3 + 0.02 * rng.standard_normal(10)) for _ in range(3)]
    assert runs_ratio_interval(a, b, seed=7) == runs_ratio_interval(a, b, seed=7)
    lo, hi = runs_ratio_interval(a, b, seed=7)
    assert 1 < lo < 1.3 < hi
    apart = [a[0], [x * 1.25 for x in a[1]], a[2]]  # one run of A a quarter slower
    wide_lo, wide_hi = runs_ratio_interval(apart, b, seed=7)
    assert wide_hi - wide_lo > 2 * (hi - lo)


def test_one_stalled_chunk_leaves_a_row_stable_and_a_wide_middle_does_not():
    steady = [1.0, 1.01, 0.99, 1.0, 1.02, 0.98, 1.0, 1.01]
    assert robust_spread(steady) < 0.05 and row_doubts({}, steady) == []
    assert row_doubts({}, [*steady, 10.0]) == []  # one stall: the median and IQR barely move
    wide = [0.6, 0.8, 1.0, 1.2, 1.4, 0.7, 1.3, 1.0]
    assert robust_spread(wide) > 0.1 and row_doubts({}, wide) == [
        f"unstable (spread {robust_spread(wide):.0%} of the median)"
    ]
    assert robust_spread([1.0, 2.0, 3.0]) is None  # too few chunks to tell
    assert row_doubts({"busy": "true", "load": "x"}, steady) == ["busy (x)"]


# --- rows that cannot be tested ------------------------------------------------------


def test_rows_without_chunk_ms_are_compared_but_untested(tmp_path, capsys):
    a = numpy_sweep(tmp_path / "a.csv")
    old_a = edited(a, tmp_path / "old-a.csv", drop=("chunk_ms",))  # as the committed CSVs
    old_slow = edited(a, tmp_path / "old-slow.csv", factor=2.0, drop=("chunk_ms",))
    code, out = compare(capsys, old_a, old_slow, "--fail-above", "1.10")
    assert code == 0  # a ratio of 2, but no evidence it is more than noise
    assert "2 rows untested for significance" in out and "(of 0 rows tested)" in out
    untested = [line for line in out.splitlines() if "numpy" in line and "untested" in line]
    assert len(untested) == 2 and all(" 2.00 " in line for line in untested)  # the ratios are still shown
    # one old file is enough to leave a row untested
    assert compare(capsys, a, old_slow, "--fail-above", "1.10")[0] == 0


def test_too_few_chunks_are_untested(tmp_path, capsys):
    a = numpy_sweep(tmp_path / "a.csv", repeat=MIN_CHUNKS - 1)
    code, out = compare(capsys, a, edited(a, tmp_path / "slow.csv", factor=2.0), "--fail-above", "1.10")
    assert code == 0 and "2 rows untested" in out


# --- the interval --------------------------------------------------------------------


def test_the_interval_is_reproducible_and_holds_the_ratio():
    rng = np.random.default_rng(5)
    a = list(1.0 + 0.05 * rng.standard_normal(10))
    b = list(1.3 + 0.05 * rng.standard_normal(10))
    assert ratio_interval(a, b, seed=7) == ratio_interval(a, b, seed=7)
    lo, hi = ratio_interval(a, b, seed=7)
    assert 1 < lo < np.median(b) / np.median(a) < hi
    lo, hi = ratio_interval(a, a[::-1], seed=7)  # the same samples: no change
    assert lo < 1 < hi


# --- bad input -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--fail-above", "fast"], "invalid float value"),
        (["--fail-above", "0.9"], "--fail-above must be a ratio >= 1"),
        (["--fail-above", "nan"], "--fail-above must be a ratio >= 1"),
        (["--strict-gate"], "--strict-gate applies to the gate: give --fail-above"),
    ],
)
def test_bad_threshold_is_one_line_exit_2(tmp_path, capsys, extra, message):
    path = tmp_path / "x.csv"
    path.write_text("backend\n")
    assert main(["compare", str(path), str(path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_unreadable_chunks_are_one_line_exit_2(tmp_path, capsys):
    a = numpy_sweep(tmp_path / "a.csv")
    text = a.read_text().splitlines()
    columns = text[0].split(",")
    row = next(csv.reader([text[1]]))
    row[columns.index("chunk_ms")] = "0.1 fast 0.2"
    bad = tmp_path / "bad.csv"
    with open(bad, "w", newline="") as f:
        csv.writer(f, lineterminator="\n").writerows([columns, row])
    capsys.readouterr()
    assert main(["compare", str(a), str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "chunk_ms '0.1 fast 0.2'" in err


def test_an_empty_name_in_a_list_of_runs_is_one_line_exit_2(tmp_path, capsys):
    path = tmp_path / "x.csv"
    path.write_text("backend\n")
    assert main(["compare", f"{path},", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "names an empty file (runs are comma-separated" in err
