"""The mesh_triangles figure (sweep --mesh-triangles) and its naive/accelerated crossover,
apart from reports/plots.py because it draws one scene variant's triangle axis, not the grids."""

from __future__ import annotations

import math
import textwrap
from typing import TYPE_CHECKING

from clothbench.reports.figures_common import Chart, panel_axes, panel_legend, titled_figure
from clothbench.reports.sweep_rows import Row, by_variant, devices_line, footer, group

if TYPE_CHECKING:
    from clothbench.reports.plots import PlotReport

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
    from clothbench.reports.plots import _log_if_wide  # here, not at the top: plots imports this module

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
        s.label += f", {algorithm}" + (f", motion {motion}" if len(motions) > 1 else "") + (
            f", n={grid}" if len(grids) > 1 else ""
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
        notes.append({
            "between": f"{name}: accelerated faster from about {at:,.0f} triangles" if at else "",
            "always": f"{name}: accelerated faster at every count measured",
            "never": f"{name}: accelerated not faster up to {top:,} triangles",
            "none": f"{name}: no triangle count measured with both algorithms",
        }[kind])
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
