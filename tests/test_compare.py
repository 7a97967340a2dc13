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
from clothbench.cli.plot import MIN_CHUNKS, ratio_interval
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
    # resampled medians of 20 far less than those of 6
    a = numpy_sweep(tmp_path / "a.csv", repeat=20)
    code, out = compare(capsys, a, a, "--fail-above", "1.10")
    assert code == 0 and "significant changes: none (of 2 rows tested)" in out
    slow = edited(a, tmp_path / "slow.csv", factor=2.0)
    code, out = compare(capsys, a, slow, "--fail-above", "1.10")
    assert code == 1 and "2 slower (of 2 rows tested)" in out
    assert out.count("numpy f64 sphere n=8: B/A 2.00") + out.count("numpy f32 sphere n=8: B/A 2.00") == 2


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
