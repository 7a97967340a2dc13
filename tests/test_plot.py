"""Plots and comparisons read a sweep CSV and say clearly when it is not one."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib.text import Annotation, Text
from PIL import Image

from clothbench.cli import main
from clothbench.harness.sweep_csv import COLUMNS, csv_line
from clothbench.reports.figures_common import (
    LABEL_MARGIN,
    MAX_SERIES,
    PNG_DPI,
    draw_front,
    figure_svg,
    fit_labels,
    new_figure,
    pareto_front,
    save_figure,
)
from clothbench.reports.plots import FILES, PlotReport, draw_sweep, plot_sweep, plot_time_vs_grid, scaling_exponent
from clothbench.reports.sweep_rows import load

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def row(**values) -> dict[str, str]:
    """A plausible ok sweep row; ms_median defaults to 1e-4 ms per particle (time ∝ N^1)."""
    n = int(values.pop("grid", 32))
    ms = float(values.pop("ms", 1e-4 * n * n))
    r = dict.fromkeys(COLUMNS, "")
    r.update(
        backend="numpy",
        peer="false",
        solver="verlet",
        mode="f32",
        precision="f32",
        strict="false",
        generic="false",
        device="Test CPU",
        scene="sphere",
        grid=str(n),
        particles=str(n * n),
        springs="0",
        dt="0.0005",
        steps="10",
        repeats="5",
        simulated_s="0.025",
        status="ok",
        ms_median=str(ms),
        ms_min=str(ms * 0.9),
        ms_max=str(ms * 1.2),
        ms_iqr=str(ms * 0.1),
        particles_per_s=str(n * n * 1e3 / ms),
        ms_per_sim_s=str(ms / 5e-4),
        finite="true",
        err_rms_m="1e-6",
        err_max_m="2e-6",
        timed_region="steps",
        cpu="Test CPU",
        cores="2",
        git_commit="abc123",
        timestamp="2026-01-01T00:00:00+00:00",
    )
    r.update({k: str(v) for k, v in values.items()})
    return r


def write_csv(path, rows, columns=COLUMNS):
    path.write_text(csv_line(columns) + "".join(csv_line(r.get(c, "") for c in columns) for r in rows))
    return path


def sample_rows() -> list[dict[str, str]]:
    grids = (16, 32, 64)
    rows = [row(grid=n) for n in grids]
    rows += [row(grid=n, mode="f64", precision="f64", ms=2e-4 * n * n, err_rms_m=0, err_max_m=0) for n in grids]
    rows += [
        row(grid=n, backend="glsl", mode="strict", strict="true", device="llvmpipe", ms=0.05 + 1e-5 * n * n)
        for n in grids
    ]
    rows += [row(grid=n, backend="taichi", peer="true", mode="default", ms=0.2 + 2e-5 * n * n) for n in grids]
    # a backend whose mode names its local size: still one line across sizes
    rows += [
        row(
            grid=64,
            backend="opencl",
            mode=f"fast/resident/ls={ls}",
            device="pthread-Test",
            local_size=ls,
            ms=0.3 + ls / 200,
        )
        for ls in (16, 32, 64, 128)
    ]
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
        "CPU (numpy) f32",
        "CPU (numpy) f64",
        "GLSL strict",
        "Taichi (peer)",
        "OpenCL",
    ]
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


def many_variant_rows(grids=(32, 64, 128), **extra) -> list[dict[str, str]]:
    """Every platform, 26 variants in all: OpenCL alone has 12 (8 Verlet, 4 PBD), GL 8."""
    rows = []
    for n in grids:
        base = 1e-4 * n * n
        for p in ("f32", "f64"):
            rows.append(
                row(
                    grid=n,
                    mode=p,
                    precision=p,
                    ms=base * (2 if p == "f64" else 1),
                    err_rms_m=0 if p == "f64" else 1e-6,
                    **extra,
                )
            )
        for strict in ("true", "false"):
            for transfer in ("resident", "per-step"):
                for generic in ("false", "true"):
                    rows.append(
                        row(
                            grid=n,
                            backend="opencl",
                            device="pthread",
                            strict=strict,
                            transfer=transfer,
                            generic=generic,
                            mode=f"{strict}/{transfer}/{generic}",
                            err_rms_m=1.01e-6,
                            ms=base / (3 if strict == "false" else 2) * (2 if generic == "true" else 1),
                            **extra,
                        )
                    )
            for method in ("jacobi", "coloured"):
                rows.append(
                    row(
                        grid=n,
                        backend="opencl",
                        device="pthread",
                        strict=strict,
                        solver="pbd",
                        pbd_method=method,
                        mode=f"{strict}/pbd",
                        ms=base * 10,
                        **extra,
                    )
                )
        for backend in ("glsl", "glsl-compute"):
            for strict in ("true", "false"):
                for generic in ("false", "true"):
                    rows.append(
                        row(
                            grid=n,
                            backend=backend,
                            device="llvmpipe",
                            strict=strict,
                            generic=generic,
                            mode=f"{strict}/{generic}",
                            ms=base / 1.5,
                            err_rms_m=0.9e-6,
                            **extra,
                        )
                    )
        rows.append(row(grid=n, backend="cuda", device="GPU", mode="swap", ms=base / 50, err_rms_m=1.2e-6, **extra))
        for backend in ("taichi", "warp", "numba"):
            rows.append(row(grid=n, backend=backend, peer="true", mode="default", ms=base / 1.2, **extra))
    return rows


def legend_lines(ax) -> dict:
    """label -> the Line2D drawn for it (an errorbar's data line)."""
    handles, labels = ax.get_legend_handles_labels()
    return {label: getattr(h, "lines", (h,))[0] for h, label in zip(handles, labels)}


def test_pareto_front_is_exactly_the_points_no_other_point_beats():
    rng = np.random.default_rng(7)
    points = [(float(c), float(e)) for c, e in rng.integers(1, 12, size=(60, 2))]  # ties on purpose
    points += [(math.nan, 1.0), (1.0, math.inf)]  # not numbers: never on the front
    front = pareto_front(points, cost=lambda p: p[0], error=lambda p: p[1])
    finite = [p for p in points if all(map(math.isfinite, p))]
    beaten = {p for p in finite for q in finite if q[0] <= p[0] and q[1] <= p[1] and q != p}
    assert sorted(front) == sorted(p for p in finite if p not in beaten)
    assert [p[1] for p in front] == sorted(p[1] for p in front)  # by increasing error
    # by hand: (3, 3) is beaten by (2, 3); (5, 1) and the duplicate pair stay
    hand = [(1, 9), (2, 3), (3, 3), (5, 1), (5, 1), (6, 2)]
    assert pareto_front(hand, cost=lambda p: p[0], error=lambda p: p[1]) == [(5, 1), (5, 1), (2, 3), (1, 9)]
    # with a 5 % tolerance an error 2 % better no longer saves a point 10x the cost
    near = [(10.0, 1.00), (1.0, 1.02)]
    assert pareto_front(near, cost=lambda p: p[0], error=lambda p: p[1]) == near
    assert pareto_front(near, cost=lambda p: p[0], error=lambda p: p[1], tolerance=0.05) == [(1.0, 1.02)]


@pytest.mark.full  # a whole committed sweep plotted
def test_no_panel_carries_more_than_eight_series_and_every_variant_is_drawn_once(tmp_path):
    report = draw_sweep(write_csv(tmp_path / "many.csv", many_variant_rows()))
    for name in ("time_vs_grid", "throughput"):
        panels = report.charts[name].panels
        assert all(len(labels) <= MAX_SERIES for labels in panels.values()), panels
        detail = [label for title, labels in panels.items() if "fastest" not in title for label in labels]
        assert sorted(detail) == sorted(report.series[name]) and len(detail) == 26
        assert list(panels)[1:] == [
            "CPU (numpy, c)",
            "OpenCL, Verlet",
            "OpenCL, PBD jacobi",
            "OpenCL, PBD coloured",
            "GL",
            "CUDA",
            "peers",
        ]
        assert "fastest" in list(panels)[0]
    assert all(len(platforms) <= MAX_SERIES for platforms in report.charts["speed_vs_error"].panels.values())


def test_peers_are_dashed_with_hollow_markers_and_say_peer(tmp_path):
    report = draw_sweep(write_csv(tmp_path / "many.csv", many_variant_rows()))
    chart = report.charts["time_vs_grid"]
    titles = list(chart.panels)
    peers_ax, numpy_ax = chart.figure.axes[titles.index("peers")], chart.figure.axes[titles.index("CPU (numpy, c)")]
    peers = legend_lines(peers_ax)
    assert set(peers) == {"Taichi (peer)", "Warp (peer)", "Numba (peer)"}
    for line in peers.values():
        assert line.get_linestyle() == "--" and line.get_markerfacecolor() == "white"
    for line in legend_lines(numpy_ax).values():
        assert line.get_linestyle() == "-" and line.get_markerfacecolor() != "white"
    # speed against error: a legend entry says which hollow points are peers
    key = [
        t.get_text()
        for ax in report.charts["speed_vs_error"].figure.axes
        if ax.get_legend()
        for t in ax.get_legend().get_texts()
    ]
    assert any("peer" in t for t in key) and any("Pareto front" in t for t in key)


def test_speed_vs_error_labels_exactly_the_front_of_each_grid(tmp_path):
    rows = [row(grid=n) for n in (32, 64)]  # numpy f32: 1e-6 m
    rows += [row(grid=n, mode="f64", precision="f64", ms=3e-4 * n * n, err_rms_m=0) for n in (32, 64)]  # exact, slow
    rows += [row(grid=n, backend="opencl", device="cl", ms=1e-5 * n * n, err_rms_m=5e-6) for n in (32, 64)]  # fast
    rows += [row(grid=n, backend="glsl", device="gl", ms=2e-5 * n * n, err_rms_m=6e-6) for n in (32, 64)]  # beaten
    rows.append(row(grid=64, backend="taichi", peer="true", ms=1e-6 * 64 * 64, err_rms_m=1e-3))  # cheapest at 64
    report = draw_sweep(write_csv(tmp_path / "s.csv", rows))
    fronts = report.charts["speed_vs_error"].fronts
    assert fronts["32×32 (1,024 particles)"] == ["CPU (numpy) f64", "CPU (numpy) f32", "OpenCL"]
    assert fronts["64×64 (4,096 particles)"] == ["CPU (numpy) f64", "CPU (numpy) f32", "OpenCL", "Taichi (peer)"]
    texts = {t.get_text() for ax in report.charts["speed_vs_error"].figure.axes for t in ax.texts}
    assert {"OpenCL", "Taichi (peer)", "CPU (numpy) f64"} <= texts and "GLSL" not in texts


def test_sweep_figures_name_the_machine_commit_and_day_and_every_machine_of_a_mixed_file(tmp_path):
    from conftest import drawn_text

    one = [row(grid=n) for n in (16, 32)]
    texts = drawn_text(draw_sweep(write_csv(tmp_path / "one.csv", one)).charts["time_vs_grid"].figure)
    assert "Test CPU · 2 cores · commit abc123 · 2026-01-01" in texts
    other = dict(cpu="Other CPU", cores="64", git_commit="def456", timestamp="2026-01-03T00:00:00+00:00")
    mixed = one + [row(grid=n, **other) for n in (16, 32)]
    report = draw_sweep(write_csv(tmp_path / "mixed.csv", mixed))
    for name, chart in report.charts.items():
        text = drawn_text(chart.figure)
        assert "2 machines: Other CPU (64 cores), Test CPU (2 cores)" in text, name
        assert "commit abc123, def456" in text and "2026-01-01..2026-01-03" in text, name


@pytest.mark.full  # two whole committed sweeps plotted
@pytest.mark.parametrize("with_bound", [True, False])
def test_the_machine_bound_is_drawn_only_where_the_csv_has_it(tmp_path, with_bound):
    columns = COLUMNS + (("bound_ms",) if with_bound else ())
    rows = many_variant_rows(bound_ms="0.001") if with_bound else many_variant_rows()
    report = draw_sweep(write_csv(tmp_path / "b.csv", rows, columns=columns))
    for name in ("time_vs_grid", "throughput"):
        bound_lines = [
            line
            for ax in report.charts[name].figure.axes
            for line in ax.get_lines()
            if line.get_label().startswith("machine bound")
        ]
        if with_bound:  # every panel, one line per device in it, across its grids
            assert len(bound_lines) >= len(report.charts[name].panels)
            assert all(len(line.get_xdata()) == 3 for line in bound_lines)
        else:
            assert bound_lines == []
    assert "<svg" in figure_svg(report.charts["time_vs_grid"].figure)[:2000]


def test_the_same_figure_writes_the_same_svg_whatever_the_last_bits_of_its_clip_paths(tmp_path, monkeypatch):
    # matplotlib names a clip path by a hash of its unrounded corners, whose last bits differed
    # between processes (about one run in three); here each render's corners are made to differ
    # as they did, and the files must not
    from matplotlib.backends import backend_svg

    make_id, renders = backend_svg.RendererSVG._make_id, []

    def jittered(self, kind, content):
        if kind == "p":
            content = (*content, len(renders))  # another set of last bits each render
        return make_id(self, kind, content)

    monkeypatch.setattr(backend_svg.RendererSVG, "_make_id", jittered)
    for name in ("a", "b"):
        renders.append(name)
        fig = new_figure(6, 3)
        for k, ax in enumerate(fig.subplots(1, 2)):
            ax.plot([1, 2, 3], [k, 2 * k, 1])
            ax.set_title(f"panel {k}")
        save_figure(fig, tmp_path / f"{name}.png")
    a, b = ((tmp_path / f"{n}.svg").read_text() for n in "ab")
    assert a.count("<clipPath") == 2 and a == b
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()


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


@pytest.mark.full  # every figure of a whole committed sweep
def test_the_committed_sweep_plots_every_figure(tmp_path):
    # the machine's own sweep: local sizes at some grids only, generic rows, peers
    committed = Path(__file__).resolve().parent.parent / "results" / "cpu-llvmpipe-pocl.csv"
    if not committed.exists():
        pytest.skip("no committed sweep in this checkout")
    report = plot_sweep(committed, tmp_path)
    for name in ("time_vs_grid", "throughput", "speed_vs_error", "local_size"):
        assert (tmp_path / f"{name}.png").stat().st_size > 10_000, name
        assert (tmp_path / f"{name}.svg").exists(), name
        assert all(len(labels) <= MAX_SERIES for labels in report.charts[name].panels.values()), name
    assert all(report.charts["speed_vs_error"].fronts.values())  # a front in every grid's panel


OCTAVES = (32, 64, 128, 256, 512, 1024, 2048)  # a sweep's grids an octave apart, as `sweep --grids` makes them


def _drawn(fig):
    """`fig` laid out at the dpi its PNG is written at; the renderer its texts are measured with."""
    fig.set_dpi(PNG_DPI)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def _clashes(texts, renderer) -> list[tuple[str, str]]:
    """The pairs of `texts` whose boxes intersect (a front label's own box: not its leader line)."""
    boxes = [(t.get_text(), Text.get_window_extent(t, renderer)) for t in texts if t.get_visible() and t.get_text()]
    return [(a, b) for i, (a, box) in enumerate(boxes) for b, other in boxes[i + 1 :] if box.overlaps(other)]


@pytest.mark.full  # the tick labels' layout over seven grids, measured on a drawn figure
def test_grid_labels_on_time_vs_grid_never_overlap(tmp_path):
    # small multiples (a panel a third of the figure wide) over seven grids: `1024×1024` and
    # `2048×2048` with their particle counts ran into each other. Only this figure is drawn:
    # the speed-vs-error figure's label placement over seven grids is most of draw_sweep's time
    rows, _ = load(write_csv(tmp_path / "many.csv", many_variant_rows(grids=OCTAVES)))
    report = PlotReport()
    plot_time_vs_grid(rows, report)
    fig = report.charts["time_vs_grid"].figure
    renderer = _drawn(fig)
    panels = [ax for ax in fig.axes if ax.get_xticklabels()]
    assert len(panels) == len(report.charts["time_vs_grid"].panels) > 3
    for ax in panels:
        labels = [t for t in ax.get_xticklabels() if t.get_text()]
        assert _clashes(labels, renderer) == [], ax.get_title()
        assert [t.get_text().split("\n")[0] for t in labels] == [f"{n}²" for n in OCTAVES], ax.get_title()


@pytest.mark.full  # the labels' layout in a clump; which rows are labelled: test_speed_vs_error_labels_exactly_the_front_of_each_grid, quick
def test_front_labels_never_overlap_and_a_moved_one_is_joined_to_its_point(tmp_path):
    # eight variants each 6 % less accurate and 3 % cheaper than the last (all on the front, their
    # points in a clump on an axis four decades wide), and numpy f64 (error 0) just above real
    # time, its label where the "real time" line's name is
    n = 2048
    rows = [row(grid=g, mode="f64", precision="f64", ms=0.55, err_rms_m=0) for g in (1024, n)]
    variants = [
        ("numpy", "f32"),
        ("c", "strict"),
        ("c", "fast"),
        ("opencl", "strict"),
        ("opencl", "fast"),
        ("glsl", "fast"),
        ("taichi", "default"),
        ("warp", "default"),
    ]
    for k, (backend, mode) in enumerate(variants):
        peer = "true" if backend in ("taichi", "warp") else "false"
        for g in (1024, n):
            rows.append(
                row(
                    grid=g,
                    backend=backend,
                    mode=mode,
                    strict=str(mode == "strict").lower(),
                    peer=peer,
                    ms=0.3 * 0.97**k,
                    err_rms_m=1e-6 * 1.06**k,
                )
            )
    rows += [row(grid=g, backend="numba", peer="true", ms=0.01, err_rms_m=1e-3) for g in (1024, n)]  # the axis wide
    report = draw_sweep(write_csv(tmp_path / "front.csv", rows))
    chart = report.charts["speed_vs_error"]
    renderer = _drawn(chart.figure)
    panel = f"{n}×{n} ({n * n:,} particles)"
    assert len(chart.fronts[panel]) == len(variants) + 2  # every one on the front, so every one labelled
    for ax in chart.figure.axes:
        labels = [t for t in ax.texts if isinstance(t, Annotation)]
        if not labels:
            continue
        assert _clashes(ax.texts, renderer) == [], ax.get_title()
        for label in labels:
            corner = Text.get_window_extent(label, renderer).p1  # top right, towards its point
            point = ax.transData.transform(label.xy)
            away = np.hypot(*(point - corner)) * 72 / PNG_DPI  # points
            if away > 12:  # its ring's radius (4.5 points) and a label's height away: joined by a line
                assert label.arrow_patch.get_visible(), (ax.get_title(), label.get_text(), away)
            elif away < 8:  # at its point (5 and 4 points left and down) or nearly: no line
                assert not label.arrow_patch.get_visible(), (ax.get_title(), label.get_text(), away)


def test_labels_at_the_lower_left_corner_are_brought_inside_in_a_few_layouts(monkeypatch):
    # points in the axes' lower left corner: their labels (lower left of each point) start
    # outside, and growing the limits brings them in. Each growth used to leave a label a
    # fraction of a pixel outside again, so every figure ran all six layouts; a growth of
    # under a pixel is not worth one
    fig = new_figure(4, 3)
    ax = fig.add_subplot()
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.plot([1e-6, 1e-3], [0.01, 10])
    labels = draw_front(ax, [(1e-6, 0.01, "first"), (1e-5, 0.02, "second")])
    layouts = []
    draw = fig.draw_without_rendering
    monkeypatch.setattr(fig, "draw_without_rendering", lambda: (layouts.append(1), draw())[1])
    fit_labels(fig, labels)
    assert 2 <= len(layouts) <= 3  # the first placement, one growth or two, never the five of the limit
    fig.draw_without_rendering()
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent()
    for label in labels:
        box = Text.get_window_extent(label, renderer)
        assert box.x0 >= frame.x0 + LABEL_MARGIN - 1.5 and box.y0 >= frame.y0 + LABEL_MARGIN - 1.5, label.get_text()
