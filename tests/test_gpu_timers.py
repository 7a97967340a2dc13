"""The device's own clock beside the wall clock (docs/timing.md): every row names the device
timer of its device_ms_median or has neither, GL timestamps are trusted per driver (never on
a software rasteriser such as llvmpipe), and files older than the device_timer column load.

The CUDA events are tested over the stand-in cupy in tests/test_cuda.py (2b)."""

from __future__ import annotations

import gc
import json
from pathlib import Path

import pytest

from clothbench.backends import BackendOptions, availability, create_backend
from clothbench.backends.gl import context as gl_context
from clothbench.backends.numpy.verlet import NumpyBackend
from clothbench.cli import main
from clothbench.harness import run_timed
from clothbench.harness.sweep_csv import COLUMNS, read_sweep
from clothbench.harness.timing import DEVICE_TIMERS
from clothbench.reports import sweep_rows
from clothbench.model.scene import load_setup

from conftest import VERLET, require, sphere
from test_sweep import read_csv, register_fake_backends

pytestmark = pytest.mark.serial  # holds a GL context and reads its timers: one xdist worker

RESULTS = Path(__file__).resolve().parents[1] / "results"
PBD = load_setup("curtain").solver_for("pbd-jacobi")
# (backend, solver) of every GL backend: the fragment step, the compute step, the PBD solver
GL_BACKENDS = {"glsl": VERLET, "glsl-compute": VERLET, "glsl-compute-pbd": PBD}
STEPS, CHUNK = 12, 3  # four timed chunks


def gl_backend(name: str, grid: int = 32):
    backend = name.removesuffix("-pbd")
    require(backend)
    return create_backend(backend, sphere(grid), GL_BACKENDS[name], BackendOptions(strict=True))


@pytest.fixture
def trusted_gl_timestamps(monkeypatch):
    """GL timestamps taken as a device's clock even on a software rasteriser: llvmpipe's are
    the host's CPU clock when it carried out the command, real elapsed times of the same work,
    so the GL clock's own code (queries, pool, per-step division) runs here."""
    monkeypatch.setattr(gl_context, "SOFTWARE_RENDERERS", ())


# --- GL: trusted per driver ------------------------------------------------------------------


@pytest.mark.parametrize("name", GL_BACKENDS)
def test_a_gl_row_has_a_device_time_exactly_where_the_driver_clock_is_trusted(name):
    with gl_backend(name) as b:
        trusted, why = b.gl.timer_queries()
        software = any(s in b.device.lower() for s in gl_context.SOFTWARE_RENDERERS)
        result = run_timed(b, STEPS, chunk=CHUNK)
    assert trusted != software, b.device  # llvmpipe and its kind: never a device clock
    assert bool(why) == software and "\n" not in why
    if trusted:
        assert result.device_timer == "gl-timer-query" and len(result.device_ms_per_step) == STEPS // CHUNK
        assert all(ms > 0 for ms in result.device_ms_per_step)
    else:
        assert result.device_timer == "" and result.device_ms_per_step == []
        assert why.startswith(b.device.split()[0]) and "no device clock" in why


@pytest.mark.parametrize("name", GL_BACKENDS)
def test_gl_timestamps_fall_inside_the_wall_clock_of_the_same_chunk(name, trusted_gl_timestamps):
    # The harness synchronises before reading the clock and after the steps, so both
    # timestamps lie between its two perf_counter reads: a device time above the wall time
    # would be a wrong unit or a timestamp of other work, on any driver. 1 us is the rounding.
    with gl_backend(name) as b:
        assert b.device_elapsed_ms() is None  # nothing advanced yet
        result = run_timed(b, STEPS, chunk=CHUNK)
    assert result.device_timer == "gl-timer-query"
    assert len(result.device_ms_per_step) == len(result.chunk_ms_per_step) == STEPS // CHUNK
    for device_ms, wall_ms in zip(result.device_ms_per_step, result.chunk_ms_per_step):
        assert 0 < device_ms <= wall_ms + 1e-3, (device_ms, wall_ms)


def test_gl_clocks_reuse_their_queries_across_backends(trusted_gl_timestamps):
    # a sweep builds hundreds of backends on one shared context: each one's query pair goes
    # back to the context when it is collected, so the next one takes it instead of new ones
    pairs = set()
    for _ in range(4):
        with gl_backend("glsl-compute", grid=8) as b:
            b.upload(*b.initial_state())
            b.advance(2)
            b.synchronize()
            assert b.device_elapsed_ms() > 0
            pairs.add((b._gl_clock.start, b._gl_clock.end))
        del b
        gc.collect()
    assert len(pairs) == 1, pairs


def test_gl_timestamps_do_not_disturb_an_outer_time_elapsed_query(trusted_gl_timestamps):
    # the viewer's profiler wraps advance() in a GL_TIME_ELAPSED query (one may be active per
    # context); the backend's own clock is timestamps, so both measure and neither errs
    with gl_backend("glsl") as b:
        b.upload(*b.initial_state())
        with b.gl:
            _ = b.gl.ctx.error  # reading it clears a flag an earlier backend on the shared context left
            query = b.gl.ctx.query(time=True)
            with query:
                b.advance(5)
            b.synchronize()
            outer_ns, error = query.elapsed, b.gl.ctx.error  # (moderngl's Query has no release())
    assert error == "GL_NO_ERROR"
    assert b.device_elapsed_ms() > 0 and outer_ns > 0


# --- rows and the run command ------------------------------------------------------------------


class ClockedBackend(NumpyBackend):
    """The numpy step, claiming a device clock that times its advance() on the host."""

    name = "fake-clocked"
    device_timer = "cuda-events"

    def advance(self, steps: int) -> None:
        import time

        t0 = time.perf_counter()
        super().advance(steps)
        self._elapsed_ms = 1e3 * (time.perf_counter() - t0)

    def device_elapsed_ms(self) -> float | None:
        return getattr(self, "_elapsed_ms", None)


class UnnamedClockBackend(ClockedBackend):
    """Device times from a backend that does not say which clock: the row still says it has one."""

    name = "fake-unnamed-clock"
    device_timer = ""


def test_sweep_rows_name_the_device_timer_of_their_device_time(tmp_path, monkeypatch):
    register_fake_backends(monkeypatch, ClockedBackend, UnnamedClockBackend)
    out = tmp_path / "s.csv"
    argv = ["sweep", "--backends", "numpy,fake-clocked,fake-unnamed-clock", "--grids", "8"]
    assert main([*argv, "--steps", "3", "--repeat", "2", "--out", str(out)]) == 0
    assert COLUMNS.index("device_timer") == COLUMNS.index("device_ms_median") + 1
    by_backend = {}
    for row in read_csv(out):
        by_backend.setdefault(row["backend"], []).append(row)
    assert {r["device_timer"] for r in by_backend["fake-clocked"]} == {"cuda-events"}
    assert {r["device_timer"] for r in by_backend["fake-unnamed-clock"]} == {"device-events"}
    for name in ("fake-clocked", "fake-unnamed-clock"):
        assert all(float(r["device_ms_median"]) > 0 for r in by_backend[name])
    assert all(r["device_timer"] == r["device_ms_median"] == "" for r in by_backend["numpy"])


def test_every_device_backend_row_names_a_documented_timer(tmp_path):
    # OpenCL on PoCL and the GL backends run here: wherever a row has a device time its
    # device_timer is one docs/timing.md describes, and wherever it has none, neither
    names = [n for n in ("opencl", "glsl", "glsl-compute") if availability(n).usable]
    if not names:
        pytest.skip("no OpenCL or GL backend runs here")
    out = tmp_path / "s.csv"
    argv = ["sweep", "--backends", ",".join(names), "--grids", "8", "--steps", "2", "--repeat", "2"]
    assert main([*argv, "--out", str(out)]) == 0
    rows = [r for r in read_csv(out) if r["status"] == "ok" and r["backend"] in names]
    assert {r["backend"] for r in rows} == set(names)
    for r in rows:
        assert bool(r["device_timer"]) == bool(r["device_ms_median"]), r
        assert r["device_timer"] == "" or (r["device_timer"] in DEVICE_TIMERS and float(r["device_ms_median"]) > 0)


@pytest.mark.parametrize("name", ["glsl", "glsl-compute"])
def test_run_json_has_the_device_time_or_says_why_not(name, capsys):
    require(name)
    assert main(["run", "--backend", name, "--grid", "16", "--steps", "8", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    trusted, why = gl_context.get_device("egl").timer_queries()
    if trusted:
        assert out["device_timer"] == "gl-timer-query" and out["device_ms_per_step"] > 0
    else:
        assert "device_ms_per_step" not in out and out["device_timer_note"] == why


def test_run_table_says_which_device_clock_and_what_it_includes(trusted_gl_timestamps, capsys):
    require("glsl-compute")
    assert main(["run", "--backend", "glsl-compute", "--grid", "16", "--steps", "8"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last == f"device clock: gl-timer-query: {DEVICE_TIMERS['gl-timer-query']}"


# --- files from before the column --------------------------------------------------------------


def old_sweeps() -> list[Path]:
    """The sweep CSVs in results/ written before the device_timer column."""
    headers = {p: p.read_text().partition("\n")[0].split(",") for p in sorted(RESULTS.glob("*.csv"))}
    return [p for p, header in headers.items() if "ms_median" in header and "device_timer" not in header]


def test_sweeps_older_than_the_device_timer_column_still_load():
    files = old_sweeps()
    if not files:
        pytest.skip("every sweep in results/ has the device_timer column")
    for path in files:
        ok, _ = sweep_rows.load(path)
        raw = read_sweep(path)
        assert ok and all(r.device_timer == "" for r in ok), path
        with_device_ms = [r for r in ok if r.raw.get("device_ms_median")]
        assert all(r.device_ms == float(r.raw["device_ms_median"]) for r in with_device_ms), path
        assert len(raw) >= len(ok)


def test_every_documented_timer_is_described_in_docs():
    text = (Path(__file__).resolve().parents[1] / "docs" / "timing.md").read_text()
    for name in DEVICE_TIMERS:
        assert f"`{name}`" in text, name
