"""The chapter's comparison figures, drawn from a sweep CSV (matplotlib on Agg, no pyplot).

1. time_vs_grid: ms per step against grid size, a line per backend variant (the chapter's
   Figures 22.5 and 22.6).
2. throughput: particles per second against particles, with the fitted exponent p of
   time ∝ particles^p per line (p ≈ 1: cost grows linearly; p < 1: parallel hardware
   not yet full).
3. speed_vs_error: a panel per grid size: compute ms per simulated second against the RMS
   error to the float64 reference, every backend variant a point coloured by platform, and
   the Pareto front (the points no other point beats on both) drawn and labelled.
4. local_size: ms per step against work-group / block size, a panel per backend.
5. mesh_triangles: ms per step against the triangle count of the scene's mesh colliders
   (sweep --mesh-triangles), a line per backend variant and mesh algorithm (naive solid,
   accelerated dashed), the count where accelerated overtakes naive named per backend.

A panel carries at most MAX_SERIES lines. More make small multiples sharing both axes: a
panel per platform (numpy, OpenCL, GL, CUDA, peers) after a first panel of each platform's
fastest variant at each grid. Peers (taichi, warp, numba) are dashed with hollow markers and
"(peer)" in the legend, so they never pass for clothbench's kernels; the PBD solver is
dash-dotted. Where the CSV has a `bound_ms` column (the machine's lower bound on a step), it
is drawn as a grey line per device across the grids. Only rows with status ok are drawn.

draw_sweep returns the figures as Charts (reports/figures_common.py) without writing them;
plot_sweep writes each as PNG and SVG.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter

from clothbench.errors import ClothbenchError
from clothbench.harness.preflight import check_folder
from clothbench.reports.figures_common import (
    BOUND_COLOR,
    FRONT_COLOR,
    FRONT_LEGEND,
    FRONT_TOLERANCE,
    MAX_SERIES,
    PEERS,
    Chart,
    display_name,
    draw_bound_lines,
    draw_front,
    draw_native_line,
    fit_labels,
    key_legend,
    panel_axes,
    panel_legend,
    pareto_front,
    plain_log_labels,
    platform_color,
    platform_rank,
    platform_title,
    save_figure,
    small_multiples,
    titled_figure,
)
from clothbench.reports.sweep_rows import (
    REQUIRED,
    Row,
    Series,
    by_variant,
    by_variant_grid,
    devices_line,
    footer,
    group,
    load,
)

FILES = ("time_vs_grid", "throughput", "speed_vs_error", "local_size")
MODEL_MARKERS = {"Verlet": "o", "PBD jacobi": "s", "PBD coloured": "D"}


@dataclass
class PlotReport:
    files: list[Path] = field(default_factory=list)
    exponents: dict[str, float] = field(default_factory=dict)  # series label -> p in time ∝ N^p
    series: dict[str, list[str]] = field(default_factory=dict)  # figure name -> its series labels
    notes: list[str] = field(default_factory=list)
    charts: dict[str, Chart] = field(default_factory=dict)  # figure name -> the drawn figure and its panels


def _sweep_figure(
    title: str, rows: list[Row], panels: int, xlabel: str, ylabel: str, panel_height: float = 4.3, key: bool = False
):
    """(figure, axes, key axes): `panels` panels sharing axes (three to a row; one panel:
    wide), the title, the axes' labels, and a footer saying on what and how the rows were
    measured; with key, an axes for a legend every panel shares (figures_common.panel_axes)."""
    cols = 1 if panels == 1 else 2 if panels in (2, 4) else 3
    nrows = math.ceil(panels / cols)
    width = 9.5 if cols == 1 else 4.8 * cols
    fig, body = titled_figure(
        title, width, 6.2 if cols == 1 else nrows * panel_height + 0.8, devices_line(rows) + "\n" + footer(rows)
    )
    body.supxlabel(xlabel, fontsize=9)
    body.supylabel(ylabel, fontsize=9)
    axes, key_axes = panel_axes(body, panels, cols, key=key)
    for ax in axes:
        ax.grid(True, which="major", alpha=0.35)
        ax.grid(True, which="minor", alpha=0.12)
    return fig, axes, key_axes


def _log_if_wide(ax, values, ratio=10.0) -> None:
    """Log y when the values span more than `ratio`, with plain numbers (0.5, 2, 10) as labels."""
    values = [v for v in values if v > 0]
    if values and max(values) / min(values) > ratio:
        ax.set_yscale("log")
        plain_log_labels(ax, ax.yaxis)


def particle_count(count: int) -> str:
    """A particle count in at most six characters: 65,536, 262 k, 4.19 M."""
    if count < 100_000:
        return f"{count:,}"
    if count < 1_000_000:
        return f"{count / 1e3:.3g} k"
    return f"{count / 1e6:.3g} M"


def _grid_axis(ax, grids) -> None:
    """Grids an octave apart on a log axis: each label (n², the particles below) fits in an
    octave of a third of the figure's width; `2048×2048 / 4,194,304` did not."""
    grids = sorted(set(grids))
    ax.set_xscale("log", base=2)
    ax.set_xticks(grids)
    ax.set_xticklabels([f"{n}²\n{particle_count(n * n)}" for n in grids], fontsize=7)
    ax.minorticks_off()
    if len(grids) == 1:
        ax.set_xlim(grids[0] / 1.5, grids[0] * 1.5)


def _fastest_per_platform(series: list[Series]) -> list[Series]:
    """Per platform and solver model, the fastest of its variants at each grid: the line a
    reader compares platforms by."""
    models = list(dict.fromkeys(s.model for s in series))
    pooled: dict[tuple[str, str], list[Row]] = {}
    for s in series:
        pooled.setdefault((s.platform, s.model), []).extend(s.rows)
    out = []
    order = sorted(pooled, key=lambda pm: (platform_rank(pm[0]), models.index(pm[1])))
    for platform, model in order:
        rows = pooled[(platform, model)]
        best: dict[int, Row] = {}
        for r in rows:
            if r.grid not in best or r.ms < best[r.grid].ms:
                best[r.grid] = r
        name = f"{platform}, {model}" if len(models) > 1 else platform
        out.append(
            Series(
                key=("fastest", platform, model),
                rows=[best[g] for g in sorted(best)],
                label=name,
                peer=platform == PEERS,
                pbd=model != "Verlet",
                color=platform_color(platform),
            )
        )
    return out


def line_panels(series: list[Series]) -> list[tuple[str, list[Series]]]:
    """(title, series) per panel: all in one when they fit in MAX_SERIES; else each
    platform's fastest variant first (one panel per solver model if they do not fit in one),
    then a panel per platform."""
    panels = small_multiples(series, lambda s: s.platform, lambda s: s.model)
    if len(panels) == 1:
        return [("all variants", panels[0][1])]
    fastest = _fastest_per_platform(series)
    if len(fastest) <= MAX_SERIES:
        overview = [("fastest variant of each platform", fastest)]
    else:
        models = dict.fromkeys(s.model for s in fastest)
        for s in fastest:  # the panel's title names the model
            s.label = s.label.replace(f", {s.model}", "")
        overview = [(f"{m}: fastest variant of each platform", [s for s in fastest if s.model == m]) for m in models]
    return overview + panels


def _line_figure(name: str, title: str, labels: tuple[str, str], rows: list[Row], report: PlotReport, draw):
    """The panels of a line figure; draw(ax, index, series) draws one series."""
    series = group([r for r in rows if r.local_size is None], by_variant)
    report.series[name] = [s.label for s in series]
    used = [r for s in series for r in s.rows]
    panels = line_panels(series)
    fig, axes, _ = _sweep_figure(title, used, len(panels), *labels)
    chart = Chart(fig)
    for ax, (panel, members) in zip(axes, panels):
        chart.panels[panel] = [draw(ax, i, s) for i, s in enumerate(members)]
        ax.set_title(panel, fontsize=9)
    report.charts[name] = chart
    return chart, list(zip(axes, panels))


def plot_time_vs_grid(rows: list[Row], report: PlotReport) -> None:
    def draw(ax, i, s):
        err = [[r.ms - r.ms_min for r in s.rows], [r.ms_max - r.ms for r in s.rows]]
        ax.errorbar(
            [r.grid for r in s.rows],
            [r.ms for r in s.rows],
            yerr=err,
            label=s.label,
            capsize=2,
            elinewidth=0.8,
            **s.style(i),
        )
        return s.label

    labels = ("grid n² (n particles per side; the particles below)", "time per step (ms), median; bars min-max")
    chart, panels = _line_figure(
        "time_vs_grid", "Computation time per step against grid size", labels, rows, report, draw
    )
    for ax, (panel, members) in panels:
        mine = [r for s in members for r in s.rows]
        draw_bound_lines(ax, mine, x=lambda r: r.grid, y=lambda r: r.bound_ms)
        if panel != platform_title("CPU"):
            draw_native_line(ax, rows, x=lambda r: r.grid, y=lambda r: r.ms)
        _grid_axis(ax, [r.grid for r in mine])
        panel_legend(ax)
    _log_if_wide(panels[0][0], [r.ms for _, (_, ms) in panels for s in ms for r in s.rows])


def scaling_exponent(particles: list[int], ms: list[float]) -> float | None:
    """p in time ∝ particles^p, least squares in log-log; None with fewer than two sizes."""
    if len(set(particles)) < 2:
        return None
    return float(np.polyfit(np.log(particles), np.log(ms), 1)[0])


def plot_throughput(rows: list[Row], report: PlotReport) -> None:
    def draw(ax, i, s):
        x = [r.particles for r in s.rows]
        p = scaling_exponent(x, [r.ms for r in s.rows])
        label = s.label
        if p is not None:
            if s.key[0] != "fastest":
                report.exponents[s.label] = p
            label += f": N^{p:.2f}"
        ax.plot(x, [r.particles * 1e3 / r.ms for r in s.rows], label=label, **s.style(i))
        return s.label

    labels = ("particles N; a label's N^p: the fitted time per step ∝ N^p", "throughput (particles per second)")
    chart, panels = _line_figure("throughput", "Throughput against particle count", labels, rows, report, draw)
    for ax, (panel, members) in panels:
        mine = [r for s in members for r in s.rows]
        draw_bound_lines(ax, mine, x=lambda r: r.particles, y=lambda r: r.particles * 1e3 / r.bound_ms)
        if panel != platform_title("CPU"):
            draw_native_line(ax, rows, x=lambda r: r.particles, y=lambda r: r.particles * 1e3 / r.ms)
        panel_legend(ax)
    ax = panels[0][0]
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:,.0f}"))


def plot_speed_vs_error(rows: list[Row], report: PlotReport) -> None:
    """A panel per grid: each variant a point (colour: platform; marker: solver model;
    hollow: a peer), the Pareto front of cost against error labelled with the variants on it."""
    with_err = [r for r in rows if r.local_size is None and r.err_rms is not None]
    if not with_err:
        report.notes.append("speed_vs_error: no row has an error measurement; not drawn")
        return
    series = group(with_err, by_variant)
    report.series["speed_vs_error"] = [s.label for s in series]
    label_of = {id(r): s.label for s in series for r in s.rows}
    platform_of_row = {id(r): s.platform for s in series for r in s.rows}
    positive = [r.err_rms for r in with_err if r.err_rms > 0]
    floor = 10 ** math.floor(math.log10(min(positive))) / 10 if positive else 1e-12
    grids = sorted({r.grid for r in with_err})
    models = list(dict.fromkeys(r.model for r in with_err))
    zero = " (error 0, the float64 reference itself, at the dotted line)" if len(positive) < len(with_err) else ""
    xlabel = f"RMS position error against numpy float64 after the timed run (m){zero}"
    fig, axes, key_axes = _sweep_figure(
        "Speed against error, per grid size",
        with_err,
        len(grids),
        xlabel,
        "compute time per simulated second (ms)",
        4.0,
        key=True,
    )
    chart = Chart(fig)
    labels, bound = [], False
    for ax, n in zip(axes, grids):
        mine = [r for r in with_err if r.grid == n]
        panel = f"{n}×{n} ({n * n:,} particles)"
        platforms = sorted({platform_of_row[id(r)] for r in mine}, key=platform_rank)
        for platform in platforms:
            color = platform_color(platform)
            for model in models:
                pts = [r for r in mine if platform_of_row[id(r)] == platform and r.model == model]
                ax.plot(
                    [max(r.err_rms, floor) for r in pts],
                    [r.cost for r in pts],
                    linestyle="none",
                    marker=MODEL_MARKERS.get(model, "^"),
                    markersize=5.5,
                    color=color,
                    alpha=0.85,
                    markerfacecolor="white" if platform == PEERS else color,
                )
        chart.panels[panel] = platforms
        front = pareto_front(mine, cost=lambda r: r.cost, error=lambda r: r.err_rms, tolerance=FRONT_TOLERANCE)
        chart.fronts[panel] = [label_of[id(r)] for r in front]
        labels += draw_front(ax, [(max(r.err_rms, floor), r.cost, label_of[id(r)]) for r in front])
        for machine in dict.fromkeys(r.raw.get("cpu", "") for r in mine if r.bound_ms):  # one bound per machine
            bound = True
            ax.axhline(
                min(r.bound_ms / r.dt for r in mine if r.bound_ms and r.raw.get("cpu", "") == machine),
                color=BOUND_COLOR,
                linewidth=2.4,
                alpha=0.7,
                linestyle=(0, (6, 2)),
                zorder=1,
            )
        ax.axhline(1000.0, color="0.5", linestyle="-.", linewidth=0.8)
        ax.text(
            0.01,
            1000.0,
            " real time",
            transform=ax.get_yaxis_transform(),
            fontsize=6.5,
            color="0.35",
            ha="left",
            va="bottom",
        )
        if len(positive) < len(with_err):
            ax.axvline(floor, color="0.5", linestyle=":", linewidth=1)
        ax.set_title(panel, fontsize=9)
    axes[0].set_xscale("log")
    axes[0].set_yscale("log")
    plain_log_labels(axes[0], axes[0].yaxis)
    platforms = sorted(set(platform_of_row.values()), key=platform_rank)
    peers = ", ".join(dict.fromkeys(display_name(r.backend) for r in with_err if platform_of_row[id(r)] == PEERS))
    handles = [_marker_key(p, platform_color(p), "o", peers) for p in platforms]
    if len(models) > 1:
        handles += [_marker_key(m, "0.45", MODEL_MARKERS.get(m, "^")) for m in models]
    handles.append(
        Line2D([], [], color=FRONT_COLOR, marker="o", markerfacecolor="none", markersize=8, label=FRONT_LEGEND)
    )
    if bound:
        handles.append(Line2D([], [], color=BOUND_COLOR, linewidth=2.4, linestyle=(0, (6, 2)), label="machine bound"))
    key_legend(key_axes, handles)
    fit_labels(fig, labels)
    report.charts["speed_vs_error"] = chart


def _marker_key(label: str, color: str, marker: str, peers: str = "") -> Line2D:
    """A key entry; the peers' names their display names, `peers`."""
    peer = label == PEERS
    return Line2D(
        [],
        [],
        color=color,
        marker=marker,
        linestyle="none",
        markersize=6,
        markerfacecolor="white" if peer else color,
        label=f"peers ({peers}; not clothbench)" if peer else label,
    )


def plot_local_size(rows: list[Row], report: PlotReport) -> None:
    """One panel per backend (per backend and grid where one panel would carry more than
    MAX_SERIES lines); a line per variant and grid (colour = grid), with the runtime's own
    choice (empty local_size) drawn at the left as 'auto'."""
    sized = [r for r in rows if r.local_size is not None]
    if not sized:
        report.notes.append(
            "local_size: no rows with a work-group / block size; not drawn "
            "(sweep with --local-sizes 16,32,64,128 on a backend that has one)"
        )
        return
    variants = {r[:-1] for r in map(by_variant_grid, sized)}
    grids = sorted({r.grid for r in sized})
    # the runtime's own choice, at the grids the local sizes were swept at
    defaults = [r for r in rows if r.local_size is None and r.grid in grids and by_variant_grid(r)[:-1] in variants]
    sizes = sorted({r.local_size for r in sized})
    auto_x = sizes[0] / 2  # where the runtime's own choice is drawn
    cmap = matplotlib.colormaps["viridis"]
    shade = {n: cmap(0.85 * i / max(1, len(grids) - 1)) for i, n in enumerate(grids)}
    panels = []  # (backend, grids of the panel)
    for backend in dict.fromkeys(r.backend for r in sized):
        mine = [r for r in sized if r.backend == backend]
        if len({by_variant_grid(r) for r in mine}) <= MAX_SERIES:
            panels.append((backend, sorted({r.grid for r in mine})))
        else:
            panels += [(backend, [n]) for n in sorted({r.grid for r in mine})]

    fig, axes, _ = _sweep_figure(
        "Time per step against work-group / block size",
        sized,
        len(panels),
        "work-group / block size (work items); auto (hollow) = the runtime's choice",
        "time per step (ms), median; bars min-max",
        panel_height=4.8,
    )
    report.series["local_size"] = []
    chart = Chart(fig)
    for ax, (backend, panel_grids) in zip(axes, panels):
        mine = [r for r in sized if r.backend == backend and r.grid in panel_grids]
        series = group(mine + [r for r in defaults if r.backend == backend and r.grid in panel_grids], by_variant_grid)
        title = f"{display_name(backend)} on {mine[0].device}"
        title += f", n={panel_grids[0]}" if len(panel_grids) == 1 and len(grids) > 1 else ""
        ax.set_title(title, fontsize=9)
        chart.panels[title] = []
        linestyles: dict[str, str] = {}
        for s in series:
            n = s.rows[0].grid
            variant = s.variant or "default"
            linestyles.setdefault(variant, ("-", "--", "-.", ":")[len(linestyles) % 4])
            marker = ("o", "s", "D", "^", "v", "<", ">")[list(linestyles).index(variant) % 7]
            style = s.style(0) | dict(color=shade[n], linestyle=linestyles[variant], marker=marker)
            if not s.peer:
                style["markerfacecolor"] = shade[n]
            pts = [r for r in s.rows if r.local_size is not None]
            if not pts:
                continue
            report.series["local_size"].append(f"{s.label}, n={n}")
            chart.panels[title].append(f"{s.label}, n={n}")
            err = [[r.ms - r.ms_min for r in pts], [r.ms_max - r.ms for r in pts]]
            ax.errorbar(
                [r.local_size for r in pts],
                [r.ms for r in pts],
                yerr=err,
                capsize=2,
                elinewidth=0.7,
                label=f"{variant}, n={n}",
                **style,
            )
            for r in s.rows:
                if r.local_size is None:
                    ax.plot(
                        [auto_x],
                        [r.ms],
                        marker=style["marker"],
                        color=shade[n],
                        markersize=6,
                        markerfacecolor="white",
                        linestyle="none",
                    )
        ax.set_xscale("log", base=2)
        ax.set_xticks([auto_x, *sizes])
        ax.set_xticklabels(["auto", *map(str, sizes)])
        ax.minorticks_off()
        ax.set_xlim(auto_x / 1.4, sizes[-1] * 1.4)
        ax.grid(True, which="major", alpha=0.35)
        panel_legend(ax)
    _log_if_wide(axes[0], [r.ms for r in sized] + [r.ms for r in defaults])
    report.charts["local_size"] = chart


MESH_FILE = "mesh_triangles"  # drawn too where a sweep varied the mesh's triangles (--mesh-triangles)


def _mesh_triangles(r: Row) -> int | None:
    cell = r.raw.get("mesh_triangles", "")
    return int(cell) if cell else None


def crossover(naive: list[tuple[int, float]], accelerated: list[tuple[int, float]]) -> tuple[str, float | None]:
    """Where the accelerated algorithm overtakes the naive one, from (triangles, ms) pairs:
    ('between', T) with T interpolated in log-log between the last count where naive is not
    slower and the first from which accelerated stays faster; ('always', None) when it is
    faster at every common count, ('never', None) when at none from some count on, ('none',
    None) with fewer than one common count."""
    a, n = dict(accelerated), dict(naive)
    common = sorted(set(a) & set(n))
    if not common:
        return "none", None
    faster = [a[t] < n[t] for t in common]
    if all(faster):
        return "always", None
    if not faster[-1]:
        return "never", None
    k = max(i for i, f in enumerate(faster) if not f)  # the last count where naive is not slower
    t0, t1 = common[k], common[k + 1]
    g0, g1 = math.log(a[t0] / n[t0]), math.log(a[t1] / n[t1])  # log(accelerated / naive): >= 0, then < 0
    f = g0 / (g0 - g1)
    return "between", math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))


def plot_mesh_triangles(rows: list[Row], report: PlotReport) -> None:
    """ms per step against the meshes' triangle count, log-log: a line per backend variant,
    mesh algorithm, motion and grid; the crossover of naive and accelerated per backend
    variant in a note under the title (and in report.notes)."""
    meshed = [r for r in rows if _mesh_triangles(r) is not None and r.local_size is None]
    counts = {_mesh_triangles(r) for r in meshed}
    if len(counts) < 2:
        if not counts:  # a sweep of a scene without meshes: nothing to say
            return
        report.notes.append(
            "mesh_triangles: fewer than two triangle counts in the CSV; not drawn "
            "(sweep with --mesh-triangles, e.g. 20,320,5120,20480)"
        )
        return

    def extra(r: Row) -> tuple:
        return (r.raw.get("mesh_collision", ""), r.raw.get("motion", ""), r.grid)

    series = group(meshed, lambda r: (*by_variant(r), *extra(r)))
    grids = {r.grid for r in meshed}
    motions = {r.raw.get("motion", "") for r in meshed}
    for s in series:
        algorithm, motion, grid = extra(s.rows[0])
        s.rows.sort(key=_mesh_triangles)
        s.label += (
            f", {algorithm}"
            + (f", motion {motion}" if len(motions) > 1 else "")
            + (f", n={grid}" if len(grids) > 1 else "")
        )
    # each backend variant (less its algorithm) keeps one colour; accelerated is dashed
    variants = list(dict.fromkeys(s.key[:-3] + s.key[-2:] for s in series))
    notes = []
    for v in variants:
        members = {s.key[-3]: s for s in series if s.key[:-3] + s.key[-2:] == v}
        if "naive" not in members or "accelerated" not in members:
            continue
        pairs = {k: [(_mesh_triangles(r), r.ms) for r in m.rows] for k, m in members.items()}
        kind, at = crossover(pairs["naive"], pairs["accelerated"])
        name = members["naive"].label.replace(", naive", "", 1)
        top = max(t for t, _ in pairs["accelerated"])
        notes.append(
            {
                "between": f"{name}: accelerated faster from about {at:,.0f} triangles" if at else "",
                "always": f"{name}: accelerated faster at every count measured",
                "never": f"{name}: accelerated not faster up to {top:,} triangles",
                "none": f"{name}: no triangle count measured with both algorithms",
            }[kind]
        )
    if not notes:
        notes.append("no backend measured with both algorithms: no crossover (numpy has the naive loop only)")
    report.notes += [f"mesh_triangles: {n}" for n in notes]
    report.series[MESH_FILE] = [s.label for s in series]
    scenes = ", ".join(sorted({r.scene for r in meshed}))
    grid = f", n={next(iter(grids))}" if len(grids) == 1 else ""
    title = f"Time per step against mesh triangles ({scenes}{grid})"
    fig, body = titled_figure(title, 9.5, 6.4, devices_line(meshed) + "\n" + footer(meshed))
    body.supxlabel("triangles of the mesh collider (log); naive: every triangle, accelerated: a BVH", fontsize=9)
    body.supylabel("time per step (ms), median; bars min-max", fontsize=9)
    axes, _ = panel_axes(body, 1, 1)
    ax = axes[0]
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    # the crossovers, interpolated in log-log between the two counts around each
    ax.set_title(textwrap.fill("; ".join(notes), 120), fontsize=8)
    for s in series:
        i = variants.index(s.key[:-3] + s.key[-2:])
        style = s.style(i)
        if s.key[-3] == "accelerated":
            style.update(linestyle="--", markerfacecolor="white")
        x, y = [_mesh_triangles(r) for r in s.rows], [r.ms for r in s.rows]
        err = [[r.ms - r.ms_min for r in s.rows], [r.ms_max - r.ms for r in s.rows]]
        ax.errorbar(x, y, yerr=err, label=s.label, capsize=2, elinewidth=0.8, **style)
    ax.set_xscale("log")
    ax.set_xticks(sorted(counts))
    ax.set_xticklabels([f"{t:,}" for t in sorted(counts)], fontsize=7)
    ax.minorticks_off()
    _log_if_wide(ax, [r.ms for r in meshed])
    panel_legend(ax)
    chart = Chart(fig)
    chart.panels[ax.get_title()] = [s.label for s in series]
    report.charts[MESH_FILE] = chart


def plot_mesh(path, out) -> PlotReport:
    """The mesh_triangles figure alone, written to `out` (PNG, and SVG beside it)."""
    check_folder(Path(out).parent, "plot folder")
    ok, _ = load(path)
    if not ok:
        raise ClothbenchError(f"{path} has no row with status ok: nothing to plot")
    report = PlotReport()
    plot_mesh_triangles(ok, report)
    if MESH_FILE not in report.charts:
        why = (
            report.notes[-1].removeprefix("mesh_triangles: ")
            if report.notes
            else ("no row has a mesh (sweep a scene with [[mesh]] colliders, with --mesh-triangles)")
        )
        raise ClothbenchError(f"{path}: {why}")
    report.files += save_figure(report.charts[MESH_FILE].figure, Path(out), dpi=150)
    return report


def draw_sweep(path) -> PlotReport:
    """Every figure the sweep CSV at `path` has data for, drawn (report.charts) but not
    written; what was left out and why in report.notes."""
    ok, bad = load(path)
    if not ok:
        raise ClothbenchError(f"{path} has no row with status ok: nothing to plot")
    report = PlotReport()
    left_out: dict[tuple[str, str, str], list[str]] = {}
    for r in bad:
        left_out.setdefault((r["backend"], r["status"], r.get("note", "")), []).append(f"{r['mode']} n={r['grid']}")
    for (backend, status, note), where in left_out.items():
        rows_ = f"{len(where)} rows" if len(where) > 1 else "1 row"
        report.notes.append(f"left out {rows_} of {backend}, {status}: {note} ({'; '.join(dict.fromkeys(where))})")
    plot_mesh_triangles(ok, report)
    ok = _one_scene_variant(ok, report)
    plot_time_vs_grid(ok, report)
    plot_throughput(ok, report)
    plot_speed_vs_error(ok, report)
    plot_local_size(ok, report)
    return report


def _one_scene_variant(rows: list[Row], report: PlotReport) -> list[Row]:
    """The rows the grid figures draw: where a sweep varied the mesh's triangles or the motion
    (a line would otherwise hold several points per grid), those of the largest count with
    motion on, said in a note."""
    counts = {_mesh_triangles(r) for r in rows}
    motions = {r.raw.get("motion", "") for r in rows}
    if len(counts) < 2 and len(motions) < 2:
        return rows
    top = max((c for c in counts if c is not None), default=None)
    motion = "on" if "on" in motions else next(iter(motions))
    report.notes.append(
        f"the grid figures draw the rows of {top} mesh triangles" * (len(counts) > 1)
        + (" and " if len(counts) > 1 and len(motions) > 1 else "")
        + f"motion {motion}" * (len(motions) > 1)
        + " (the sweep varied them: mesh_triangles draws the triangle counts)"
    )
    return [r for r in rows if _mesh_triangles(r) == top and r.raw.get("motion", "") == motion]


def plot_sweep(path, out) -> PlotReport:
    """Draw every figure the CSV has data for into `out` as PNG and SVG; say what was left
    out and why."""
    out = check_folder(out, "plot folder")  # before the drawing, seconds of it
    report = draw_sweep(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ClothbenchError(f"cannot create {out}: {e.strerror}") from None
    for name in (*FILES, MESH_FILE):
        if name in report.charts:
            report.files += save_figure(report.charts[name].figure, out / f"{name}.png", dpi=150)
    return report


# REQUIRED, Row and load are sweep_rows' and stay importable from here (reports/results_files.py)
__all__ = [
    "FILES",
    "REQUIRED",
    "Row",
    "PlotReport",
    "load",
    "draw_sweep",
    "plot_sweep",
    "scaling_exponent",
    "line_panels",
    "plot_mesh",
    "crossover",
]
