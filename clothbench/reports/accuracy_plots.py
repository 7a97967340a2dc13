"""The figures of `clothbench accuracy` and `clothbench stability` (analysis/), drawn as
reports/plots.py draws the sweep's (reports/figures_common.py: small multiples of at most
MAX_SERIES series, peers dashed and hollow, the Pareto front, PNG and SVG).

1. speed_vs_error: cost (ms per simulated second) against the error to the converged
   reference of each line's own model, dt halved along each line. A first panel holds every
   run, coloured by platform, with the Pareto front labelled (the runs no other run beats on
   both cost and error); then a panel per platform, a line per backend mode and solver, the
   front drawn thin in each to read the distance from it.
2. convergence: error against dt, a panel per platform, with the fitted order in each label
   and slopes 1 and 2 to read by.
3. vbd_iterations: VBD's convergence against its sweeps: the error against the exact
   implicit-Euler step at the same dt (what the sweeps have not converged) against the sweep
   count, a line per backend mode and dt; dashed, the same runs against Verlet's converged
   answer (that plus implicit Euler's own damping).
4. stability_map: the largest stable dt against k, a panel per scene (flat, stretched,
   crumpled): the linearised bound, Verlet's measured limit per platform, PBD's per method.
5. pbd_study (`clothbench pbd-study`): PBD's error against its cost at 1/60 s, one line per
   substep count, a panel per scene and method: against constraint passes per frame (top) and
   measured ms per frame (bottom).
6. energy (`clothbench energy`): per backend mode, the undamped run's worst drift from its
   start's energy as a share of its band, and the damped run's largest rise between two
   readings as a share of rounding: a bar per mode, coloured by platform, 1 the bound.

Verlet lines are solid, PBD dash-dotted with square (Jacobi) or diamond (coloured) markers,
peers dashed with hollow markers. The *_chart functions return the drawn Chart; the plot_*
functions write it as PNG at the path given and SVG beside it. Under each figure, the machine,
commit and date its rows were measured on, as under the sweep's (figures_common.machine_line).
"""

from __future__ import annotations

import math
import textwrap
from pathlib import Path

from matplotlib.lines import Line2D

from clothbench.analysis.lattice import damping_rate, dt_limit, gershgorin_omega, omega_max
from clothbench.analysis.stability import DT_60HZ, STRETCH
from clothbench.reports.figures_common import (
    FRONT_COLOR,
    FRONT_LEGEND,
    FRONT_TOLERANCE,
    MARKERS,
    PALETTE,
    PEERS,
    Chart,
    draw_front,
    fit_labels,
    is_peer,
    machine_line,
    new_figure,
    panel_axes,
    panel_legend,
    pareto_front,
    platform_color,
    platform_of,
    plain_log_labels,
    platform_rank,
    save_figure,
    series_style,
    small_multiples,
    titled_figure,
)
from clothbench.model.scene import Scene
from clothbench.variant_names import model_display, model_short

DPI = 110
SOLVER_MARKERS = {"verlet": "o", "jacobi": "s", "coloured": "D", "vbd": "v"}  # by _solver_key
FOOTER_WIDTH = 130  # characters of a machine line (6.5 pt) to a line: what fits the narrowest figure, 7 in wide


def _model(r) -> str:
    return model_display(r.solver, r.pbd_method)


def _solver_key(r) -> str:
    """'verlet', a PBD method ('jacobi', 'coloured') or 'vbd': what a row's marker says."""
    return r.pbd_method or r.solver


def _key_display(key: str) -> str:
    """'Verlet', 'PBD jacobi', 'VBD' of a _solver_key."""
    return model_display(key if key in ("verlet", "vbd") else "pbd", key)


def _label(r) -> str:
    return r.label + (" (peer)" if is_peer(r.backend) else "")


def _drawable(rows) -> list:
    return [r for r in rows if r.status == "ok" and r.disc_rms > 0 and r.ms_per_sim_s > 0]


def _lines(rows) -> list[tuple[str, list]]:
    """(label, rows by dt) per backend mode and solver, in first-seen order."""
    groups: dict[str, list] = {}
    for r in rows:
        groups.setdefault(_label(r), []).append(r)
    return [(label, sorted(rs, key=lambda r: r.dt)) for label, rs in groups.items()]


def _line_style(rows, i: int) -> dict:
    r = rows[0]
    style = series_style(i, peer=is_peer(r.backend), pbd=r.solver != "verlet")
    if r.solver != "verlet":
        style["marker"] = SOLVER_MARKERS.get(_solver_key(r), "^")
    return style


def _platform_panels(rows) -> list[tuple[str, list[tuple[str, list]]]]:
    """(title, lines) per panel: by platform when the lines do not fit in one."""
    return small_multiples(_lines(rows), lambda line: platform_of(line[1][0].backend), lambda line: _model(line[1][0]))


def _footer(notes: list[str], rows) -> str:
    """The figure's notes and, last, where and when its rows were measured (wrapped: several
    machines make it long; nothing for rows from files older than the machine columns)."""
    machine = textwrap.fill(machine_line(vars(r) for r in rows), FOOTER_WIDTH)
    return "\n".join([*notes, machine] if machine else notes)


def _accuracy_figure(title: str, panels: int, overview: bool, footer: str = ""):
    cols = 1 if panels == 1 else 3 if overview or panels > 4 else 2
    cells = panels + (1 if overview else 0)  # axes; the overview spans two columns
    rows = math.ceil((cells + (1 if overview else 0)) / cols)
    fig, body = titled_figure(
        title, 10.5 if cols == 1 else 4.9 * cols, (6.0 if cols == 1 else 4.6 * rows) + 0.4, footer
    )
    axes, _ = panel_axes(body, cells, cols, wide_first=overview)
    for ax in axes:
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    return fig, body, axes


def speed_vs_error_chart(result) -> Chart:
    """Cost against error, every run with its Pareto front and a panel per platform; with
    both solvers, a vertical line per PBD model at its converged distance from Verlet's."""
    rows = _drawable(result.rows)
    panels = _platform_panels(rows)
    overview = len(panels) > 1
    r0 = result.rows[0]
    solvers = " and ".join(dict.fromkeys(r.solver for r in result.rows))
    fig, body, axes = _accuracy_figure(
        f"Speed against error: {r0.scene} {r0.grid}×{r0.grid}, {solvers}; dt halved along each line",
        len(panels),
        overview,
        _footer([], rows),
    )
    body.supxlabel(
        f"RMS position error at t = {r0.time_s:g} s against the converged float64 answer of its own model (m)",
        fontsize=9,
    )
    body.supylabel("cost (ms of compute per simulated second)", fontsize=9)
    chart = Chart(fig)
    front = pareto_front(rows, cost=lambda r: r.ms_per_sim_s, error=lambda r: r.disc_rms, tolerance=FRONT_TOLERANCE)
    points = [(r.disc_rms, r.ms_per_sim_s, f"{_label(r)}, dt {r.dt * 1e3:.3g} ms") for r in front]
    labels = []
    if overview:
        ax = axes[0]
        chart.panels["every run"] = _every_run(ax, rows)
        chart.fronts["every run"] = [p[2] for p in points]
        labels = draw_front(ax, points)
        distances = _model_differences(ax, result.differences, annotate=True)
        panel_legend(ax, ncol=3, handles=_every_run_key(rows) + distances)
        ax.set_title("every run, and the Pareto front", fontsize=9)
    for ax, (title, lines) in zip(axes[1:] if overview else axes, panels):
        for i, (label, rs) in enumerate(lines):
            ax.plot([r.disc_rms for r in rs], [r.ms_per_sim_s for r in rs], label=label, **_line_style(rs, i))
        chart.panels[title or "every run"] = [label for label, _ in lines]
        if overview:
            ax.step(
                [p[0] for p in points],
                [p[1] for p in points],
                where="post",
                color=FRONT_COLOR,
                linewidth=0.8,
                alpha=0.5,
                zorder=1,
                label="Pareto front of every run",
            )
        else:
            chart.fronts["every run"] = [p[2] for p in points]
            labels = draw_front(ax, points)
        _model_differences(ax, result.differences, annotate=not overview)
        ax.set_title(title, fontsize=9)
        panel_legend(ax)
    fit_labels(fig, labels)
    return chart


def _every_run(ax, rows) -> list[str]:
    """Every run a point, colour: platform, marker: solver (hollow: a peer); the series drawn."""
    drawn = []
    for platform in _platforms(rows):
        for solver, marker in SOLVER_MARKERS.items():
            pts = [r for r in rows if platform_of(r.backend) == platform and _solver_key(r) == solver]
            if not pts:
                continue
            color = platform_color(platform)
            face = "white" if platform == PEERS else color
            ax.plot(
                [r.disc_rms for r in pts],
                [r.ms_per_sim_s for r in pts],
                linestyle="none",
                marker=marker,
                markersize=5,
                color=color,
                alpha=0.8,
                markerfacecolor=face,
            )
            drawn.append(f"{platform}, {_model(pts[0])}")
    return drawn


def _platforms(rows) -> list[str]:
    return sorted({platform_of(r.backend) for r in rows}, key=platform_rank)


def _every_run_key(rows) -> list[Line2D]:
    platforms = _platforms(rows)
    solvers = [s for s in SOLVER_MARKERS if any(_solver_key(r) == s for r in rows)]
    handles = [
        Line2D(
            [],
            [],
            color=platform_color(p),
            marker="o",
            linestyle="none",
            markerfacecolor="white" if p == PEERS else platform_color(p),
            label="peers (not clothbench)" if p == PEERS else p,
        )
        for p in platforms
    ]
    if len(solvers) > 1:
        handles += [
            Line2D([], [], color="0.45", marker=SOLVER_MARKERS[s], linestyle="none", label=_key_display(s))
            for s in solvers
        ]
    handles.append(
        Line2D([], [], color=FRONT_COLOR, marker="o", markerfacecolor="none", markersize=8, label=FRONT_LEGEND)
    )
    return handles


def _model_differences(ax, differences, annotate: bool) -> list:
    """A dotted vertical line per PBD model at its converged answer's distance from
    Verlet's, named and labelled for a legend (annotate); the labelled lines."""
    labelled = []
    for i, d in enumerate(differences):
        line = ax.axvline(d.rms, color="grey", lw=1, alpha=0.6, linestyle=(0, (1, 2 + i)))
        if annotate:
            line.set_label(f"{model_short(d.b)}: its converged answer is {d.rms * 1e3:.2g} mm (RMS) from Verlet's")
            ax.annotate(
                model_short(d.b),
                (d.rms, 0.98),
                xycoords=("data", "axes fraction"),
                xytext=(2, 0),
                textcoords="offset points",
                fontsize=6.5,
                alpha=0.75,
                ha="left",
                va="top",
                rotation=90,
            )
            labelled.append(line)
    return labelled


def plot_speed_vs_error(result, path: Path) -> None:
    save_figure(speed_vs_error_chart(result).figure, path, dpi=DPI)


def convergence_chart(result) -> Chart:
    """Error against dt per backend mode and solver with its fitted order, a panel per
    platform; solid/dash-dotted: against the converged answer, dotted: rounding."""
    rows = _drawable(result.rows)
    panels = _platform_panels(rows)
    r0 = result.rows[0]
    unstable = sorted({r.dt for r in result.rows if r.status.startswith("unstable")})
    notes = [
        "solid (Verlet), dash-dotted (PBD), dashed (peers): against the converged float64 answer of its own model; "
        "dotted, same colour: against float64 at the same dt (rounding)"
    ]
    if unstable:
        solvers = ", ".join(sorted({r.solver for r in result.rows if r.status.startswith("unstable")}))
        notes.append(f"unstable (not drawn) at dt >= {unstable[0]:.3g} s on {solvers}")
    fig, body, axes = _accuracy_figure(
        f"Convergence: {r0.scene} {r0.grid}×{r0.grid}, start={r0.start}, b={r0.damping:g}",
        len(panels),
        False,
        _footer(notes, rows),
    )
    body.supxlabel("dt (s)", fontsize=9)
    body.supylabel(f"RMS position error at t = {r0.time_s:g} s (m)", fontsize=9)
    chart = Chart(fig)
    dts = sorted({r.dt for r in rows})
    top = max((r.disc_rms for r in rows), default=1.0)
    for ax, (title, lines) in zip(axes, panels):
        for i, (label, rs) in enumerate(lines):
            order = rs[0].order
            shown = f"order {order:.2f}" if math.isfinite(order) else "order n/a"
            style = _line_style(rs, i)
            ax.plot([r.dt for r in rs], [r.disc_rms for r in rs], label=f"{label} ({shown})", **style)
            ax.plot([r.dt for r in rs], [r.impl_rms for r in rs], ":", alpha=0.6, color=style["color"])
        chart.panels[title or "every run"] = [label for label, _ in lines]
        if dts:
            lo, hi = dts[0], dts[-1]
            for p in (1, 2):
                ax.plot([lo, hi], [top * (lo / hi) ** p, top], "k--", alpha=0.3, lw=1)
                ax.annotate(f"slope {p}", (lo, top * (lo / hi) ** p), fontsize=7, alpha=0.6)
        ax.set_title(title, fontsize=9)
        panel_legend(ax, ncol=1 if len(panels) > 1 else 2)
    return chart


def plot_convergence(result, path: Path) -> None:
    save_figure(convergence_chart(result).figure, path, dpi=DPI)


def vbd_iterations_chart(result) -> Chart | None:
    """VBD's error against its sweep count, a line per backend mode and dt: solid against the
    exact implicit-Euler step at the same dt (harness/implicit.py), dashed against Verlet's
    converged answer; None unless some VBD line has two or more sweep counts."""
    rows = [r for r in result.rows if r.solver == "vbd" and r.status == "ok" and r.vs_exact_rms > 0]
    lines: dict[tuple, list] = {}
    for r in rows:
        lines.setdefault((r.backend, r.mode, r.substeps, r.dt), []).append(r)
    lines = {key: sorted(rs, key=lambda r: r.iterations) for key, rs in lines.items() if len(rs) > 1}
    if not lines:
        return None
    r0 = rows[0]
    drawn = [r for rs in lines.values() for r in rs]
    notes = [
        "solid: RMS against the exact implicit-Euler step at the same dt (what the sweeps have not converged); "
        "dashed, same colour: against Verlet's converged answer (that, plus implicit Euler's own damping)"
    ]
    fig, body, axes = _accuracy_figure(
        f"VBD against its sweeps: {r0.scene} {r0.grid}×{r0.grid}, t = {r0.time_s:.3g} s",
        1,
        False,
        _footer(notes, drawn),
    )
    ax = axes[0]
    body.supxlabel("sweeps over the 4 colours per substep (iterations)", fontsize=9)
    body.supylabel(f"RMS position error at t = {r0.time_s:.3g} s (m)", fontsize=9)
    chart = Chart(fig)
    labels = []
    for i, ((backend, mode, substeps, dt), rs) in enumerate(lines.items()):
        style = series_style(i, peer=is_peer(backend))
        label = f"{backend} {mode}, dt = 1/{1 / dt:.4g} s" + (f" x {substeps} substeps" if substeps > 1 else "")
        ax.plot([r.iterations for r in rs], [r.vs_exact_rms for r in rs], label=label, **style)
        style.update(linestyle=":" if is_peer(backend) else "--", alpha=0.6)
        ax.plot([r.iterations for r in rs], [r.vs_verlet_rms for r in rs], **style)
        labels.append(label)
    chart.panels["every run"] = labels
    panel_legend(ax, ncol=1)
    return chart


def plot_vbd_iterations(result, path: Path) -> bool:
    """Write vbd_iterations_chart at `path` (PNG, SVG beside it); False where it has nothing to draw."""
    chart = vbd_iterations_chart(result)
    if chart is None:
        return False
    save_figure(chart.figure, path, dpi=DPI)
    return True


def stability_map_chart(rows) -> Chart:
    """Largest stable dt against k, a panel per scene: the bound that applies (and the
    Gershgorin one), Verlet measured per platform (a platform's modes side by side), PBD per
    method as the smallest over its backends (an arrow: stable at the cap, the limit is
    higher), lines at the cap and at 1/60 s."""
    r0 = rows[0]
    kinds = list(dict.fromkeys(r.kind for r in rows))
    fig, body = titled_figure(
        f"Stability map: {r0.grid}×{r0.grid}, {r0.steps} steps, b = {r0.damping:g}",
        max(7.0, 5.0 * len(kinds)),
        6.2,
        _footer([], rows),
    )
    body.supxlabel("spring stiffness k (N/m), m = 0.01 kg", fontsize=9)
    body.supylabel("largest stable dt (s)", fontsize=9)
    axes, _ = panel_axes(body, len(kinds), cols=3)
    chart = Chart(fig)
    ks = sorted({r.stiffness for r in rows})
    kk = [ks[0] / 1.6, ks[-1] * 1.6]
    m = Scene().mass  # every stability scene uses the default particle mass
    beta = damping_rate(Scene(damping=r0.damping))
    caps = sorted({r.cap for r in rows if r.solver != "verlet" and r.cap})
    for ax, kind in zip(axes, kinds):
        mine = [r for r in rows if r.kind == kind]
        if kind == "stretched":
            ax.loglog(
                kk,
                [dt_limit(omega_max(k, m, STRETCH), beta) for k in kk],
                "k-.",
                lw=1,
                label=f"bound: lattice at {STRETCH}x stretch",
            )
        else:
            what = "bound: flat lattice 2/ω"
            what += ", for scale (a crumpled sheet has none)" if kind == "crumpled" else ""
            ax.loglog(kk, [dt_limit(omega_max(k, m), beta) for k in kk], "k-", lw=1, label=what)
        ax.loglog(kk, [dt_limit(gershgorin_omega(k, m), beta) for k in kk], "k:", lw=1, label="Gershgorin 24 k/m")
        chart.panels[kind] = _stability_points(ax, mine)
        for c in caps:
            ax.axhline(c, color="tab:green", lw=1, ls="--", alpha=0.6)
            ax.annotate(
                f"PBD cap {c:g} s (arrow: stable there)",
                (kk[0], c),
                xytext=(4, -3),
                textcoords="offset points",
                fontsize=6.5,
                va="top",
                color="tab:green",
            )
        ax.axhline(DT_60HZ, color="grey", lw=1, ls=(0, (4, 4)), alpha=0.7)
        ax.annotate(
            "dt = 1/60 s",
            (kk[0], DT_60HZ),
            xytext=(4, 2),
            textcoords="offset points",
            fontsize=6.5,
            va="bottom",
            color="grey",
        )
        ax.set_xlim(*kk)
        ax.set_title(kind, fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        panel_legend(ax, ncol=1)
    if caps:
        axes[0].set_ylim(top=max(caps) * 3)
    return chart


def _stability_points(ax, rows) -> list[str]:
    """Verlet: every backend mode a hollow marker in its platform's colour, a platform's
    modes side by side around k; PBD: per method the smallest limit over the backends."""
    verlet = [r for r in rows if r.solver == "verlet"]
    platforms = _platforms(verlet)
    drawn = []
    for j, platform in enumerate(platforms):
        pts = [r for r in verlet if platform_of(r.backend) == platform]
        shift = 1.07 ** (j - (len(platforms) - 1) / 2)
        modes = len({r.label for r in pts})
        label = f"Verlet, {'peers' if platform == PEERS else platform} ({modes} mode{'s' * (modes > 1)})"
        color = platform_color(platform)
        ax.loglog(
            [r.stiffness * shift for r in pts],
            [r.dt_stable for r in pts],
            "o",
            color=color,
            fillstyle="none",
            markersize=6,
            alpha=0.8,
            label=label,
            linestyle="none",
        )
        drawn.append(label)
    iterative = [r for r in rows if r.solver != "verlet"]
    for key, marker, color, shift in (
        ("jacobi", "P", "tab:purple", 1 / 1.12),
        ("coloured", "X", "tab:brown", 1.12),
        ("vbd", "v", "tab:olive", 1.0),
    ):
        mine = [r for r in iterative if _solver_key(r) == key]
        if not mine:
            continue
        worst = [
            min((r for r in mine if r.stiffness == k), key=lambda r: r.dt_stable)
            for k in sorted({r.stiffness for r in mine})
        ]
        its = "/".join(map(str, sorted({r.iterations for r in mine})))
        label = f"{_key_display(key)} ({its} it): smallest of {len({r.label for r in mine})} backend modes"
        ax.loglog(
            [r.stiffness * shift for r in worst],
            [r.dt_stable for r in worst],
            marker,
            color=color,
            markersize=8,
            alpha=0.85,
            label=label,
            linestyle="none",
        )
        for r in worst:
            if r.capped:
                ax.annotate(
                    "",
                    (r.stiffness * shift, r.dt_stable * 1.8),
                    (r.stiffness * shift, r.dt_stable * 1.1),
                    arrowprops=dict(arrowstyle="->", color=color, alpha=0.7),
                )
        drawn.append(label)
    return drawn


def plot_stability_map(rows, path: Path) -> None:
    save_figure(stability_map_chart(rows).figure, path, dpi=DPI)


def energy_chart(rows) -> Chart:
    """The energy study's two bounds, a panel each: the undamped drift over its band (a linear
    axis: it is a share of the band, 0.36-0.47 in the committed study) and the damped rise
    between readings over rounding (a log axis: a thousandth of it and less), a horizontal bar
    per backend mode. A damped run whose energy never rose between two readings (its largest
    "rise" is a fall) has no bar and says so. Rows whose run did not finish are in the report's
    table, not here."""
    ok = [r for r in rows if r.status == "ok"]
    r0 = rows[0]
    labels = list(dict.fromkeys(_label(r) for r in ok))
    fig, body = titled_figure(
        f"Energy: {r0.scene} {r0.grid}×{r0.grid} from rest, dt = {r0.dt:g} s",
        10.5,
        1.4 + 0.22 * len(labels),
        _footer([], rows),
    )
    # inches: constrained layout's default pad clips the longest mode's first letter
    fig.get_layout_engine().set(w_pad=0.08)
    axes = body.subplots(1, 2, sharey=True)  # the same modes; the two shares are not one quantity
    chart = Chart(fig)
    panels = (
        ("undamped", "worst |E − E0| ÷ band (1 % of M |g| size)"),
        ("damped", "largest rise between readings ÷ rounding (16 u × scale)"),
    )
    for ax, (case, xlabel) in zip(axes, panels):
        mine = {_label(r): r for r in ok if r.case == case}
        shown = [label for label in labels if label in mine]
        values = [mine[label].share() for label in shown]
        if case == "damped":
            ax.set_xscale("log")
            rose = [v for v in values if v > 0]
            ax.set_xlim(min([*rose, 1.0]) / 10, 2.0)
        else:
            ax.set_xlim(0.0, max([1.15, *values]) * 1.05)
        for label, value in zip(shown, values):
            y, color = labels.index(label), platform_color(platform_of(mine[label].backend))
            if value > 0:  # from the axis's left end (0, or the log axis's first decade) to the value
                left = ax.get_xlim()[0]
                ax.barh(y, value - left, left=left, color=color, height=0.7)
            else:
                ax.annotate(
                    "never rose",
                    (ax.get_xlim()[0], y),
                    xytext=(3, 0),
                    textcoords="offset points",
                    fontsize=6.5,
                    va="center",
                    color=color,
                )
        ax.axvline(1.0, color="black", lw=1, ls="--")
        ax.annotate(
            "bound",
            (1.0, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(-3, -3),
            textcoords="offset points",
            fontsize=6.5,
            ha="right",
            va="top",
        )
        steps = sorted({mine[label].steps for label in shown})
        ax.set_title(f"{case}, {', '.join(f'{s:,}' for s in steps)} steps", fontsize=10)
        ax.set_xlabel(xlabel, fontsize=8)
        ax.grid(True, axis="x", which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
        chart.panels[case] = shown
    axes[0].set_yticks(range(len(labels)), labels)
    axes[0].invert_yaxis()  # the modes top to bottom in the file's order
    return chart


def pbd_study_figure(rows):
    """Error against cost, one line per substep count: a panel per scene and method, against
    constraint passes per frame (top) and measured OpenCL ms per frame (bottom, numpy's where
    OpenCL was not measured)."""
    from clothbench.analysis.pbd_study import how_busy  # it imports the backends: not at this module's import

    cases = list(dict.fromkeys((r.scene, r.method) for r in rows))
    subs = sorted({r.substeps for r in rows})
    fig = new_figure(3.3 * len(cases), 6.4)
    axes = fig.subplots(2, len(cases), squeeze=False)
    opencl = any(math.isfinite(r.ms_opencl) for r in rows)
    own = "opencl" if opencl else "numpy"

    def ms(r) -> float:  # a peer's rows are timed on the peer's own run
        return r.ms_newton if r.method == "newton" else r.ms_opencl if opencl else r.ms_numpy

    for col, (scene, method) in enumerate(cases):
        mine = [r for r in rows if (r.scene, r.method) == (scene, method) and r.status == "ok"]
        timed_on = "newton" if method == "newton" else own
        for top, x, xlabel in (
            (0, lambda r: r.cost, "substeps x iterations per frame"),
            (1, ms, f"f32 ms per frame ({timed_on}, measured)"),
        ):
            ax = axes[top][col]
            for i, s in enumerate(subs):
                line = sorted((r for r in mine if r.substeps == s and math.isfinite(x(r))), key=lambda r: r.cost)
                if line:
                    ax.plot(
                        [x(r) for r in line],
                        [r.rms * 1e3 for r in line],
                        marker=MARKERS[i % len(MARKERS)],
                        color=PALETTE[i % len(PALETTE)],
                        label=f"{s} substep{'s' * (s > 1)}",
                    )
            ax.set_xscale("log")
            ax.set_yscale("log")
            plain_log_labels(ax, ax.yaxis)
            plain_log_labels(ax, ax.xaxis)
            ax.set_xlabel(xlabel, fontsize=8)
            ax.set_title(f"{scene}, {method}", fontsize=9)
            ax.grid(True, which="both", alpha=0.3)
            if col == 0:
                ax.set_ylabel("RMS error (mm)", fontsize=8)
    handles = {}
    for ax in axes.flat:  # one key for every panel: each substep count once, fewest first
        for h, label in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(label, h)
    order = sorted(handles, key=lambda label: int(label.split()[0]))
    fig.legend([handles[k] for k in order], order, loc="outside right upper", fontsize=7)
    r0 = rows[0]
    fig.suptitle(
        f"PBD substeps against iterations at equal cost ({r0.grid}x{r0.grid}, dt = 1/60 s, t = {r0.time_s:g} s, "
        f"b = {r0.damping:g}): error against the converged float64 mass-spring answer; ms measured on "
        f"{' and '.join(sorted({r.cpu for r in rows if r.cpu})) or 'an unnamed CPU'}, {how_busy(rows)}",
        fontsize=9,
    )
    return fig


def plot_pbd_study(rows, path: Path) -> None:
    save_figure(pbd_study_figure(rows), path, dpi=DPI)


def plot_energy(rows, path: Path) -> None:
    save_figure(energy_chart(rows).figure, path, dpi=DPI)


__all__ = [
    "plot_speed_vs_error",
    "plot_convergence",
    "plot_stability_map",
    "plot_vbd_iterations",
    "speed_vs_error_chart",
    "convergence_chart",
    "vbd_iterations_chart",
    "stability_map_chart",
    "plot_energy",
    "energy_chart",
    "pbd_study_figure",
    "plot_pbd_study",
]
