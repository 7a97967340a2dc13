"""Plots and comparisons read a sweep CSV and say clearly when it is not one."""

from __future__ import annotations

import subprocess
from pathlib import Path
import sys

import pytest
from PIL import Image

from clothbench.cli import main
from clothbench.harness.sweep_csv import COLUMNS, csv_line
from clothbench.reports.plots import FILES, plot_sweep, scaling_exponent

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def row(**values) -> dict[str, str]:
    """A plausible ok sweep row; ms_median defaults to 1e-4 ms per particle (time ∝ N^1)."""
    n = int(values.pop("grid", 32))
    ms = float(values.pop("ms", 1e-4 * n * n))
    r = dict.fromkeys(COLUMNS, "")
    r.update(
        backend="numpy", peer="false", solver="verlet", mode="f32", precision="f32", strict="false",
        generic="false", device="Test CPU", scene="sphere", grid=str(n), particles=str(n * n),
        springs="0", dt="0.0005", steps="10", repeats="5", simulated_s="0.025", status="ok",
        ms_median=str(ms), ms_min=str(ms * 0.9), ms_max=str(ms * 1.2), ms_iqr=str(ms * 0.1),
        particles_per_s=str(n * n * 1e3 / ms), ms_per_sim_s=str(ms / 5e-4), finite="true",
        err_rms_m="1e-6", err_max_m="2e-6", timed_region="steps", cpu="Test CPU", cores="2",
        git_commit="abc123", timestamp="2026-01-01T00:00:00+00:00",
    )  # fmt: skip
    r.update({k: str(v) for k, v in values.items()})
    return r


def write_csv(path, rows, columns=COLUMNS):
    path.write_text(csv_line(columns) + "".join(csv_line(r.get(c, "") for c in columns) for r in rows))
    return path


def sample_rows() -> list[dict[str, str]]:
    grids = (16, 32, 64)
    rows = [row(grid=n) for n in grids]
    rows += [row(grid=n, mode="f64", precision="f64", ms=2e-4 * n * n, err_rms_m=0, err_max_m=0) for n in grids]
    rows += [row(grid=n, backend="glsl", mode="strict", strict="true", device="llvmpipe", ms=0.05 + 1e-5 * n * n)
             for n in grids]  # fmt: skip
    rows += [row(grid=n, backend="taichi", peer="true", mode="default", ms=0.2 + 2e-5 * n * n) for n in grids]
    # a backend whose mode names its local size: still one line across sizes
    rows += [row(grid=64, backend="opencl", mode=f"fast/resident/ls={ls}", device="pthread-Test", local_size=ls,
                 ms=0.3 + ls / 200) for ls in (16, 32, 64, 128)]  # fmt: skip
    rows.append(row(grid=64, backend="opencl", mode="fast/resident/ls=auto", device="pthread-Test", ms=0.35))
    bad = row(grid=64, backend="cuda", mode="swap", status="failed", note="CUDARuntimeError: no device")
    bad.update(dict.fromkeys(("ms_median", "ms_min", "ms_max", "particles_per_s", "err_rms_m"), ""))
    rows.append(bad)
    return rows


def test_scaling_exponent_of_linear_cost_is_one():
    assert scaling_exponent([1024, 4096, 16384], [1.0, 4.0, 16.0]) == pytest.approx(1.0)
    assert scaling_exponent([1024, 1024], [1.0, 2.0]) is None  # one size: nothing to fit


def test_plot_writes_every_figure_as_a_non_empty_png_and_svg(tmp_path):
    csv_path = write_csv(tmp_path / "sweep.csv", sample_rows())
    report = plot_sweep(csv_path, tmp_path / "plots")
    for name in FILES:
        png = tmp_path / "plots" / f"{name}.png"
        assert png in report.files and png.read_bytes()[:8] == PNG_SIGNATURE, name
        with Image.open(png) as im:
            lo, hi = im.convert("L").getextrema()
            assert im.width >= 800 and hi - lo > 100, f"{name}.png looks blank"
        assert "<svg" in (tmp_path / "plots" / f"{name}.svg").read_text()[:1000]
    # one line per variant, peers marked; local sizes of one variant make one line per grid
    assert report.series["time_vs_grid"] == [
        "CPU (numpy) f32", "CPU (numpy) f64", "GLSL strict", "Taichi (peer)", "OpenCL",
    ]  # fmt: skip
    assert report.series["local_size"] == ["OpenCL, n=64"]
    # numpy was made linear in N, GLSL mostly constant: the fitted exponents say so
    assert report.exponents["CPU (numpy) f32"] == pytest.approx(1.0)
    assert report.exponents["GLSL strict"] < 0.5
    assert report.notes == ["left out 1 row of cuda, failed: CUDARuntimeError: no device (swap n=64)"]


def test_plot_command_prints_exponents_and_what_it_left_out(tmp_path, capsys):
    csv_path = write_csv(tmp_path / "s.csv", [row(grid=n) for n in (16, 32)])
    assert main(["plot", str(csv_path)]) == 0
    out = capsys.readouterr().out
    assert "CPU (numpy)  p = 1.00" in out
    assert "--local-sizes" in out  # why there is no local-size plot
    folder = tmp_path / "s"  # default: beside the CSV, named after it
    assert f"wrote {folder / 'time_vs_grid.png'}" in out
    assert (folder / "time_vs_grid.png").stat().st_size > 10_000
    assert not (folder / "local_size.png").exists()


def test_plot_of_a_csv_missing_columns_fails_in_one_line_with_exit_2(tmp_path):
    bad = write_csv(tmp_path / "bad.csv", [row()], columns=("backend", "grid", "status"))
    r = subprocess.run([sys.executable, "-m", "clothbench", "plot", str(bad)], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
    assert "lacks columns" in r.stderr and "ms_median" in r.stderr and "clothbench sweep" in r.stderr
    assert not (tmp_path / "bad").exists()


def test_compare_prints_the_ratio_of_matching_rows(tmp_path, capsys):
    a = [row(grid=32, ms=2.0), row(grid=64, ms=8.0), row(grid=32, backend="glsl", mode="strict", strict="true", ms=1.0)]
    b = [row(grid=32, ms=1.0), row(grid=64, ms=4.0), row(grid=32, backend="glsl", mode="strict", strict="true", ms=3.0)]
    b.append(row(grid=128, ms=30.0))  # only in B
    assert main(["compare", str(write_csv(tmp_path / "a.csv", a)), str(write_csv(tmp_path / "b.csv", b))]) == 0
    out = capsys.readouterr().out
    assert out.count("0.50") >= 2 and "3.00" in out
    assert "numpy: geometric mean B/A 0.50 over 2 rows" in out
    assert "only in B: 1" in out


def test_compare_of_unrelated_files_fails_in_one_line(tmp_path, capsys):
    a = write_csv(tmp_path / "a.csv", [row(grid=32)])
    b = write_csv(tmp_path / "b.csv", [row(grid=64)])
    assert main(["compare", str(a), str(b)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no row in common" in err


def test_the_committed_sweep_plots_every_figure(tmp_path):
    # the machine's own sweep: local sizes at some grids only, generic rows, peers
    committed = Path(__file__).resolve().parent.parent / "results" / "cpu-llvmpipe-pocl.csv"
    if not committed.exists():
        pytest.skip("no committed sweep in this checkout")
    assert main(["plot", str(committed), "--out", str(tmp_path)]) == 0
    for name in ("time_vs_grid", "throughput", "speed_vs_error", "local_size"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000, name


def test_readme_peer_table_matches_the_committed_sweep():
    import csv

    from clothbench.reports.tables import peer_ratio_markdown

    root = Path(__file__).resolve().parent.parent
    committed = root / "results" / "cpu-llvmpipe-pocl.csv"
    if not committed.exists():
        pytest.skip("no committed sweep in this checkout")
    table = peer_ratio_markdown(list(csv.DictReader(committed.open())))
    assert table.count("\n") >= 3, "the committed sweep has no grid with both kinds"
    assert table in (root / "README.md").read_text()
