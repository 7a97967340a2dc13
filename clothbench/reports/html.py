"""`clothbench report`'s page: one self-contained HTML file (figures inline as SVG, a small
inline stylesheet, nothing fetched) holding a whole study: every sweep, accuracy, artefacts,
stability, energy and PBD-study CSV given, with the figures reports/plots.py and
reports/accuracy_plots.py draw, the tables the README carries, and the machine the rows were
measured on.

What each kind of CSV puts on the page (built of reports/page.py's pieces): its figures, drawn
into a temporary folder and inlined, and its tables: ms per step per backend and mode at every
grid, the peers against clothbench, the Pareto front of speed against error, Verlet against PBD,
the stability limits against the bound, PBD's substeps against its iterations, the energy against
its bounds; and, over every file, the machine and drivers the rows were measured on.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

from clothbench.analysis.convergence import cheapest_at
from clothbench.reports import accuracy_plots, plots, tables
from clothbench.reports.figures_common import FRONT_TOLERANCE, is_peer, pareto_front, vector_only
from clothbench.reports.page import Exact, Figures, Html, Section, esc, notice, num, page, paragraph, slug, table
from clothbench.reports.results_files import (
    ACCURACY,
    ARTEFACTS,
    ENERGY,
    KIND,
    KINDS,
    PBD_STUDY,
    STABILITY,
    SWEEP,
    ResultsFile,
    accuracy_result,
    analysis_rows,
    unfinished,
)
from clothbench.model.solver import ITERATIVE
from clothbench.variant_names import iterations_display, model_display

# A sweep figure's title and what it shows, by the file name reports/plots.py gives it;
# a figure it draws that is not named here is still shown, titled after its file.
SWEEP_FIGURES = {
    "time_vs_grid": (
        "Time per step against grid size",
        "The chapter's Figures 22.5 and 22.6 for this machine: median ms per step, bars from the "
        "fastest to the slowest timed chunk.",
    ),
    "throughput": (
        "Throughput against particle count",
        "Particles per second, with the fitted exponent p of time ∝ N^p per line: p ≈ 1, the cost "
        "grows linearly; p < 1, the hardware is not yet full.",
    ),
    "speed_vs_error": (
        "Speed against error",
        "Compute ms per simulated second against the RMS error to the float64 reference; the "
        "Pareto front joins the configurations that no other beats on both.",
    ),
    "local_size": ("Time per step against work-group size", "Backends that have a work-group or block size."),
}
ACCURACY_FIGURES = {
    "speed_vs_error": (
        "Speed against error",
        "Cost against the error to the converged float64 answer of each line's own model, dt "
        "halved along each line; the Pareto front's runs are listed in the table below.",
    ),
    "convergence": (
        "Convergence",
        "Error against dt with the fitted order; dotted: rounding (float64 at the same dt).",
    ),
}
STABILITY_FIGURES = {
    "stability_map": (
        "Stability against the bound",
        "The largest stable dt against stiffness, measured by bisection, beside the linearised "
        "bound 2/ω of the lattice, its stretched form and Gershgorin's.",
    ),
}
ENERGY_FIGURES = {
    "energy": (
        "Energy against its bounds",
        "Undamped: the largest distance of the energy from its start's over the run, as a share of "
        "the band (1 % of the sheet's M |g| size). Damped: the largest rise between two readings, as a "
        "share of rounding (16 u × the energy scale), on a log axis; 'never rose': its largest change between "
        "two readings was a fall. 1 is the bound.",
    ),
}
PBD_STUDY_FIGURES = {
    "pbd_study": (
        "PBD: substeps against iterations at equal cost",
        "The RMS error against the converged float64 mass-spring answer, one line per substep count, "
        "against constraint passes per frame (top) and the measured ms per frame (bottom).",
    ),
}
MACHINE_COLUMNS = ("cpu", "cores", "python", "packages", "env")


def study(files: list[ResultsFile], figures: Figures) -> tuple[list[Html], list[Section]]:
    """The page's introduction and sections, in the order the files were given; an artefacts
    CSV beside its accuracy CSV (NAME-artefacts.csv) joins that one's section."""
    paired = {}
    for f in files:
        if f.kind == ARTEFACTS and f.path.name.endswith("-artefacts.csv"):
            twin = f.path.with_name(f.path.name.removesuffix("-artefacts.csv") + ".csv")
            if any(g.kind == ACCURACY and g.path == twin for g in files):
                paired[twin] = f
    sections = [machine_section(files)]
    order = [k.name for k in KINDS]
    for f in sorted(files, key=lambda f: order.index(f.kind)):
        if f in paired.values():
            continue  # in its accuracy run's section
        beside = {"artefacts": paired[f.path]} if f.path in paired else {}
        sections.append(SECTIONS[f.kind](f, figures, **beside))
    inputs = [
        [
            Html(f'<a href="#{section_id(f)}">{esc(f.path)}</a>'),
            KIND[f.kind].what,
            len(f.rows),
            len(f.ok_rows()) if "status" in f.rows[0] else len(f.rows),
        ]
        for f in files
    ]
    intro = [
        Html(
            '<p class="lead">One page for a whole study: every figure drawn from the CSVs below, inline, '
            "and the tables beside them.</p>"
        ),
        table(["file", "what", "rows", "rows ok"], inputs),
    ]
    return intro, sections


def section_id(f: ResultsFile) -> str:
    """The id of a file's section: unique per path, so two files of one name can be shown."""
    return slug(f"{f.kind} {f.path}")


def _values(rows: list[dict], column: str) -> list[str]:
    return sorted({r.get(column, "") for r in rows} - {""})


def _inline_all(figures: Figures, folder: Path, known: dict[str, tuple[str, str]]) -> list[Html]:
    """Every SVG in `folder`: the known ones first, in `known`'s order, then any other."""
    svgs = sorted(folder.glob("*.svg"), key=lambda p: (list(known).index(p.stem) if p.stem in known else 99, p.name))
    out = []
    for svg in svgs:
        title, caption = known.get(svg.stem, (svg.stem.replace("_", " ").capitalize(), ""))
        out.append(figures.inline(svg, title, caption))
    return out


# --- the machine ---------------------------------------------------------------------------

DRIVER_NOT_RECORDED = "not recorded"  # a file older than the driver column


def driver_cell(row: dict[str, str]) -> str:
    """The runtime and its version that ran a row (its `driver`): one CPU's name is also the
    name every CPU runtime gives its device. "not recorded" for a file older than the column;
    '' where the backend names none (numpy)."""
    return row.get("driver", DRIVER_NOT_RECORDED)


def machine_section(files: list[ResultsFile]) -> Section:
    """The machines (cpu, cores, python, packages, driver environment) the rows record, said
    plainly when there is more than one; each backend's device; commits and dates."""
    sec = Section("Machine and drivers", "machine")
    full = [f for f in files if all(c in f.rows[0] for c in MACHINE_COLUMNS)]  # sweeps
    partial = [f for f in files if f not in full and any(c in f.rows[0] for c in MACHINE_COLUMNS)]
    machines: dict[tuple, dict[str, int]] = {}  # (cpu, cores, python, packages, env) -> file -> rows
    for f in full:
        for r in f.rows:
            per_file = machines.setdefault(tuple(r[c] for c in MACHINE_COLUMNS), {})
            per_file[f.name] = per_file.get(f.name, 0) + 1
    if machines:
        sec.body.append(
            table(
                ["machine", "cpu", "logical cores", "python", "driver environment", "rows from"],
                [
                    [
                        f"#{i}",
                        m[0],
                        m[1],
                        m[2],
                        m[4] or "none set",
                        ", ".join(f"{n} ({k})" for n, k in per_file.items()),
                    ]
                    for i, (m, per_file) in enumerate(machines.items(), start=1)
                ],
            )
        )
    for f in partial:
        recorded = [c for c in MACHINE_COLUMNS if c in f.rows[0]]
        sec.body.append(
            paragraph(
                f"{f.name} records only {', '.join(recorded)}: "
                + "; ".join(", ".join(_values(f.rows, c)) or "none" for c in recorded)
            )
        )
    differ = [c for i, c in enumerate(MACHINE_COLUMNS) if len({m[i] for m in machines}) > 1]
    cpus = {r["cpu"] for f in full + partial for r in f.rows if r.get("cpu")}
    if len(cpus) > 1 and "cpu" not in differ:
        differ.insert(0, "cpu")
    if differ:
        sec.body.append(
            notice(
                f"The rows come from at least {max(len(machines), len(cpus))} different machines or set-ups (they "
                f"differ in {', '.join(differ)}): compare numbers within one machine, or two with clothbench compare."
            )
        )
    elif full or partial:
        sec.body.append(paragraph("Every row that records its machine was measured on this one."))
    for i, packages in enumerate(dict.fromkeys(m[3] for m in machines), start=1):
        whose = f" (machine #{i})" if len({m[3] for m in machines}) > 1 else ""
        items = "".join(f"<li><code>{esc(p)}</code></li>" for p in packages.split())
        sec.body.append(Html(f'<p>Packages that can change a result{whose}:</p><ul class="packages">{items}</ul>'))
    devices: dict[tuple[str, str, str], list[str]] = {}  # (backend, device, driver) -> files
    for f in files:
        for r in f.rows:
            if r.get("device"):
                names = devices.setdefault((r["backend"], r["device"], driver_cell(r)), [])
                names += [] if f.name in names else [f.name]
    if devices:
        sec.body.append(
            table(
                ["backend", "device, as its driver names it", "driver", "in"],
                [[b, d, v, ", ".join(n)] for (b, d, v), n in devices.items()],
                row_classes=["peer" if is_peer(b) else "" for b, _, _ in devices],
            )
        )
    runs = []
    for f in files:
        dates, commits = sorted({s[:10] for s in _values(f.rows, "timestamp")}), _values(f.rows, "git_commit")
        if dates or commits:
            when = f"measured {dates[0]}" + (f" to {dates[-1]}" if len(dates) > 1 else "") + ", " if dates else ""
            runs.append(
                f"<li>{esc(f.name)}: {esc(when)}clothbench commit{'s' * (len(commits) > 1)} "
                f"{esc(', '.join(commits) or 'not recorded')}</li>"
            )
    if runs:
        sec.body.append(Html(f"<ul>{''.join(runs)}</ul>"))
    if any("+dirty" in c for f in files for c in _values(f.rows, "git_commit")):
        sec.body.append(Html("<p>'+dirty': the commit had changes not yet committed.</p>"))
    silent = [f.name for f in files if f not in full and f not in partial]
    if silent:
        sec.body.append(
            paragraph(
                f"{', '.join(silent)} record{'s' * (len(silent) == 1)} no machine (cpu, cores, python, packages, "
                "environment, commit): sweep CSVs record all of it, as do accuracy and stability CSVs written since "
                "they took the same columns."
            )
        )
    return sec


# --- a sweep ---------------------------------------------------------------------------------


def sweep_section(f: ResultsFile, figures: Figures) -> Section:
    ok = f.ok_rows()
    sec = Section(f"Sweep: {f.name}", section_id(f))
    chunks = ", ".join(f"{r} chunks × {s} steps" for r, s in sorted({(r["repeats"], r["steps"]) for r in ok}))
    own = sorted({r["backend"] for r in ok if r["peer"] != "true"})
    peers = sorted({r["backend"] for r in ok if r["peer"] == "true"})
    sec.body.append(
        paragraph(
            f"Scene {', '.join(_values(ok, 'scene'))}, grids {', '.join(f'{g}×{g}' for g in sorted({int(r['grid']) for r in ok}))}, "
            f"dt {', '.join(f'{float(d) * 1e3:g} ms' for d in _values(ok, 'dt'))}; {chunks} timed after warm-up "
            f"(median, min, max). Backends: {', '.join(own) or 'none'}; peers: {', '.join(peers) or 'none'}. "
            f"{len(ok)} of {len(f.rows)} rows ok."
        )
    )
    folder = figures.folder_for(f.path.stem)
    report = plots.plot_sweep(f.path, folder)
    sec.body += _inline_all(figures, folder, SWEEP_FIGURES)
    sec.body += [paragraph(n) for n in report.notes]
    sec.children.append(ms_per_step_section(ok, sec.id))
    ratios = tables.peer_ratios(f.rows)
    if ratios:
        sec.children.append(
            Section(
                "Peers against clothbench",
                f"{sec.id}-peers",
                [
                    table(
                        ["grid", "fastest GPU-style backend", "ms/step", "fastest peer", "ms/step", "peer / it"],
                        [
                            [
                                f"{r['grid']}×{r['grid']}",
                                r["ours"],
                                r["ours_ms"],
                                r["peer"],
                                r["peer_ms"],
                                Html(f"{num(r['ratio'], 2)}×"),
                            ]
                            for r in ratios
                        ],
                        caption="Per grid, clothbench's fastest float32 backend (any mode, the runtime's work-group size) "
                        "against the fastest peer (reports/tables.py peer_ratios).",
                        right={5},
                    )
                ],
            )
        )
    sec.children.append(sweep_pareto_section(ok, sec.id))
    if len({r.get("solver") or "verlet" for r in ok}) > 1:
        sec.children.append(sweep_solvers_section(ok, sec.id))
    doubtful = _doubtful_rows(ok)
    if doubtful:
        sec.children.append(
            Section(
                "Rows whose figure may not hold",
                f"{sec.id}-doubtful",
                [
                    table(
                        ["backend", "mode", "grid", "ms/step", "why"],
                        doubtful,
                        caption="Measured while the machine was busy (the busy and load columns) or with chunks spread over "
                        "10 % of their median (harness/noise.py): measure them again on a quiet machine before "
                        "reading a ratio from them.",
                        right={2, 3},
                    )
                ],
            )
        )
    bad = [r for r in f.rows if r["status"] != "ok"]
    if bad:
        groups: dict[tuple, list[str]] = {}
        for r in bad:
            groups.setdefault((r["backend"], r["status"], r.get("note", "")), []).append(f"{r['mode']} n={r['grid']}")
        sec.children.append(
            Section(
                "Rows not measured",
                f"{sec.id}-bad",
                [table(["backend", "status", "rows", "why"], [[b, s, len(w), n] for (b, s, n), w in groups.items()])],
            )
        )
    return sec


def _doubtful_rows(ok: list[dict]) -> list[list]:
    """[backend, mode, grid, ms, why] of each ok row the machine was busy for or whose chunks
    spread wide; [] for a file older than the busy column with steady chunks."""
    from clothbench.harness.noise import row_doubts

    out = []
    for r in ok:
        why = row_doubts(r)
        if why:
            out.append([r["backend"], r["mode"], r["grid"], num(float(r["ms_median"])), "; ".join(why)])
    return out


def ms_per_step_section(ok: list[dict], parent: str) -> Section:
    """The README's table: ms/step per backend and mode (the runtime's work-group size) at every grid."""
    default = [r for r in ok if not r["local_size"]]
    grids = sorted({int(r["grid"]) for r in default})
    scenes = _values(default, "scene")
    lines: dict[tuple, dict[int, dict]] = {}
    for r in default:
        key = (r["backend"], r.get("solver", ""), r.get("iterations", ""), r["mode"], r["scene"], r["device"])
        lines.setdefault(key, {})[int(r["grid"])] = r
    body, classes = [], []
    for (backend, solver, iterations, mode, scene, device), at in lines.items():
        its = f", {iterations_display(iterations)}" if solver in ITERATIVE and iterations else ""
        label = f"{backend} {mode}{its}"
        label += f" [{scene}]" if len(scenes) > 1 else ""
        body.append([label, device] + [float(at[g]["ms_median"]) if g in at else None for g in grids])
        classes.append("peer" if is_peer(backend) or at[min(at)]["peer"] == "true" else "")
    best = set()
    for j, _ in enumerate(grids, start=2):
        column = [(row[j], i) for i, row in enumerate(body) if row[j] is not None]
        if column:
            best.add((min(column)[1], j))
    return Section(
        "ms per step",
        f"{parent}-ms",
        [
            table(
                ["backend, mode", "device"] + [f"{g}×{g}" for g in grids],
                body,
                row_classes=classes,
                best=best,
                caption="Median ms per step; bold: the fastest at that grid. Peers are marked.",
                right=set(range(2, 2 + len(grids))),
            )
        ],
    )


def sweep_pareto_section(ok: list[dict], parent: str) -> Section:
    """Per grid (each grid is its own problem, with its own error), the rows on the front."""
    sec = Section("Pareto front: speed against error", f"{parent}-pareto")
    body, classes = [], []
    for grid in sorted({int(r["grid"]) for r in ok}):
        mine = [r for r in ok if int(r["grid"]) == grid and not r["local_size"] and r["err_rms_m"]]
        for r in pareto_front(mine, cost=_sweep_cost, error=lambda r: float(r["err_rms_m"]), tolerance=FRONT_TOLERANCE):
            error = float(r["err_rms_m"])
            body.append(
                [
                    f"{grid}×{grid}",
                    Html(num(error) + " <small>(the float64 reference)</small>") if error == 0 else error,
                    _sweep_cost(r),
                    f"{r['backend']} {r['mode']}",
                    r["device"],
                ]
            )
            classes.append("peer" if r["peer"] == "true" else "")
    if not body:
        sec.body.append(paragraph("No row has an error measurement: there is no front to find."))
        return sec
    sec.body.append(
        table(
            ["grid", "RMS error (m)", "ms per simulated second", "backend, mode", "device"],
            body,
            row_classes=classes,
            right={1},
            caption="At each grid, the rows no other row beats on both speed and error (errors within "
            f"{FRONT_TOLERANCE:.0%} count as equal, as in the figure), from the most accurate to the "
            "cheapest: the fastest platform at each error.",
        )
    )
    return sec


def _sweep_cost(r: dict) -> float:
    """Compute ms per simulated second: comparable across solvers and dts."""
    return float(r["ms_median"]) / float(r["dt"])


def sweep_solvers_section(ok: list[dict], parent: str) -> Section:
    """Verlet against PBD and VBD on each backend and grid: the cheapest f32 mode of each solver model."""
    present = [s for s in ITERATIVE if any((r.get("solver") or "verlet") == s for r in ok)]

    def model(r) -> str:
        return model_display(r.get("solver") or "verlet", r["pbd_method"], r["iterations"])

    cost: dict[tuple, dict[str, float]] = {}
    for r in ok:
        if r["local_size"] or r["precision"] != "f32":
            continue
        cell = cost.setdefault((r["backend"], int(r["grid"])), {})
        cell[model(r)] = min(cell.get(model(r), math.inf), _sweep_cost(r))
    models = list(dict.fromkeys(model(r) for r in ok))
    body = []
    for (backend, grid), at in cost.items():
        if "Verlet" not in at or len(at) < 2:
            continue
        cells = [
            Html(f"{num(at[m])}" + (f" (×{num(at[m] / at['Verlet'], 2)})" if m != "Verlet" else "")) if m in at else "–"
            for m in models
        ]
        body.append([backend, f"{grid}×{grid}", *cells])
    return Section(
        f"Verlet against {' and '.join(s.upper() for s in present)}",
        f"{parent}-solvers",
        [
            table(
                ["backend", "grid", *models],
                body,
                right=set(range(2, 2 + len(models))),
                caption="Compute ms per simulated second, the cheapest float32 mode of each solver (× Verlet's cost). "
                "The same dt: PBD pays off only at steps Verlet cannot take (see Stability).",
            )
        ],
    )


# --- an accuracy run -----------------------------------------------------------------------


def accuracy_section(f: ResultsFile, figures: Figures, artefacts: ResultsFile | None = None) -> Section:
    result = accuracy_result(f)
    rows, r0 = result.rows, result.rows[0]
    sec = Section(f"Accuracy: {f.name}", section_id(f))
    solvers = list(dict.fromkeys(r.solver for r in rows))
    sec.body.append(
        paragraph(
            f"Scene {r0.scene}, {r0.grid}×{r0.grid}, start {r0.start}, damping {r0.damping:g} N s/m; errors at "
            f"t = {r0.time_s:g} s against the converged float64 answer of each row's own model; solvers "
            f"{' and '.join(solvers)}; {len(rows)} runs on {len({r.label for r in rows})} backend modes."
        )
    )
    if unfinished(f):
        sec.body.append(
            notice(
                "This study did not finish (its convergence orders were not yet in the file): they are fitted here "
                "over the runs it has. clothbench accuracy --resume with the same settings measures the rest."
            )
        )
    folder = figures.folder_for(f.path.stem)
    accuracy_plots.plot_speed_vs_error(result, folder / "speed_vs_error.svg")
    accuracy_plots.plot_convergence(result, folder / "convergence.svg")
    sec.body += _inline_all(figures, folder, ACCURACY_FIGURES)
    ok = [r for r in rows if r.status == "ok" and r.disc_rms > 0 and r.ms_per_sim_s > 0]
    front = pareto_front(ok, cost=lambda r: r.ms_per_sim_s, error=lambda r: r.disc_rms, tolerance=FRONT_TOLERANCE)
    sec.children.append(
        Section(
            "Pareto front: the cheapest run to each error",
            f"{sec.id}-pareto",
            [
                table(
                    ["RMS error (m)", "ms per simulated second", "backend, mode", "solver", "dt (s)"],
                    [[r.disc_rms, r.ms_per_sim_s, r.label, r.solver, Exact(r.dt)] for r in front],
                    row_classes=["peer" if is_peer(r.backend) else "" for r in front],
                    caption=f"The runs no other run beats on both cost and error (errors within {FRONT_TOLERANCE:.0%} count as "
                    "equal), from the most accurate to the cheapest.",
                )
            ],
        )
    )
    orders = {}
    for r in rows:
        best = orders.setdefault(r.label, [r, math.inf, math.inf])
        if r in ok and r.disc_rms < best[1]:
            best[1:] = [r.disc_rms, r.ms_per_sim_s]
    sec.children.append(
        Section(
            "Convergence order per backend and mode",
            f"{sec.id}-orders",
            [
                table(
                    [
                        "backend, mode",
                        "solver",
                        "device",
                        "fitted order",
                        "dts fitted",
                        "smallest error (m)",
                        "its cost (ms/sim s)",
                    ],
                    [[label, r.solver, r.device, r.order, r.order_points, e, c] for label, (r, e, c) in orders.items()],
                    row_classes=["peer" if is_peer(r.backend) else "" for r, _, _ in orders.values()],
                    caption="The order of error against dt, fitted where discretisation dominates rounding ('–': it never does).",
                )
            ],
        )
    )
    if "verlet" in solvers and set(ITERATIVE) & set(solvers):
        sec.children.append(accuracy_solvers_section(rows, ok, sec.id))
    _add_failed_runs(sec, rows, ["backend, mode", "dt (s)"], lambda r: [r.label, Exact(r.dt)])
    if artefacts is not None:
        sec.children.append(artefacts_section(artefacts, f"What PBD changes: {artefacts.name}"))
    return sec


def accuracy_solvers_section(rows: list, ok: list, parent: str) -> Section:
    """Per decade of error, the cheapest Verlet, PBD and VBD runs reaching it (PBD and VBD
    against their own converged model and against the mass-spring answer Verlet converges to)."""
    present = [s for s in ITERATIVE if any(r.solver == s for r in ok)]
    titles = {"disc_rms": "{}, own model", "vs_verlet_rms": "{} against Verlet's answer"}
    columns = (
        ("Verlet", "verlet", "disc_rms"),
        *((t.format(s.upper()), s, e) for s in present for e, t in titles.items()),
    )
    errors = [r.disc_rms for r in ok]
    body = []
    for e in range(math.ceil(math.log10(max(errors))), math.floor(math.log10(min(errors))) - 1, -1):
        cells = []
        for _, solver, attr in columns:
            best = cheapest_at([r for r in ok if r.solver == solver], 10.0**e, attr)
            cells.append(
                Html(f"{num(best.ms_per_sim_s)} <small>({esc(best.label)}, dt {num(Exact(best.dt))} s)</small>")
                if best
                else "–"
            )
        body.append([Html(f"≤ {num(Exact(10.0**e))}"), *cells])
    return Section(
        f"Verlet against {' and '.join(s.upper() for s in present)}",
        f"{parent}-solvers",
        [
            table(
                ["RMS error (m)", *(c[0] for c in columns)],
                body,
                caption="The cheapest run reaching each error, in ms of compute per simulated second.",
            )
        ],
    )


def artefacts_section(f: ResultsFile, title: str) -> Section:
    rows = analysis_rows(f)
    return Section(
        title,
        section_id(f),
        [
            table(
                ["model", "dt (s)", "strain at rest", "× Verlet's", "energy change (% of M g L)", "ms per simulated s"],
                [
                    [r.model, Exact(r.dt), r.hanging_strain, r.strain_ratio, 100 * r.energy_change, r.ms_per_sim_s]
                    for r in rows
                ],
                caption="PBD's softness (the hanging sheet's strain against Verlet's) and damping (energy gained or lost "
                "undamped), numpy float64. An over-stretched model's energy change is no damping measure.",
            )
        ],
    )


# --- a stability run -------------------------------------------------------------------------


def stability_section(f: ResultsFile, figures: Figures) -> Section:
    rows = analysis_rows(f)
    r0 = rows[0]
    sec = Section(f"Stability: {f.name}", section_id(f))
    sec.body.append(
        paragraph(
            f"The largest dt stable for {r0.steps} steps, {r0.grid}×{r0.grid}, b = {r0.damping:g} N s/m, by bisection, "
            f"on {len({r.label for r in rows})} backend modes and {len({r.kind for r in rows})} scenes."
        )
    )
    folder = figures.folder_for(f.path.stem)
    accuracy_plots.plot_stability_map(rows, folder / "stability_map.svg")
    sec.body += _inline_all(figures, folder, STABILITY_FIGURES)

    def model(r) -> str:
        return model_display(r.solver, r.pbd_method, r.iterations)

    def ms(seconds: float | None) -> float | None:
        return None if seconds is None else 1e3 * seconds

    models = list(dict.fromkeys(model(r) for r in rows))
    cases = list(dict.fromkeys((r.kind, r.stiffness) for r in rows))
    body = []
    for kind, k in cases:
        here = [r for r in rows if (r.kind, r.stiffness) == (kind, k)]
        cells = []
        for m in models:
            mine = [r for r in here if model(r) == m]
            if not mine:
                cells.append("–")
                continue
            worst = min(mine, key=lambda r: r.dt_stable)
            # to the digits shown, so backends that agree read as one number
            ratios = sorted({float(f"{r.ratio or r.dt_stable / r.flat_predicted:.3g}") for r in mine})
            spread = num(ratios[0]) + (f"–{num(ratios[-1])}" if len(ratios) > 1 else "")
            cells.append(Html(f"{'≥ ' if worst.capped else ''}{num(ms(worst.dt_stable))} <small>({spread}×)</small>"))
        body.append([kind, Exact(k), ms(here[0].flat_predicted), ms(here[0].predicted), *cells])
    sec.children.append(
        Section(
            "Measured against the bound",
            f"{sec.id}-bound",
            [
                table(
                    [
                        "scene",
                        "k (N/m)",
                        "bound 2/ω, flat (ms)",
                        "this scene's bound (ms)",
                        *(f"{m}: largest stable dt (ms)" for m in models),
                    ],
                    body,
                    right=set(range(4, 4 + len(models))),
                    caption="The smallest of the backends' largest stable dt, and in brackets the range over backends of "
                    "measured ÷ the scene's own bound (÷ the flat bound where the scene has none: crumpled, and PBD, "
                    "which has no step limit of its kind). '≥': stable at the bisection's cap; the limit is higher.",
                )
            ],
        )
    )
    at_60 = [r for r in rows if r.at_60hz]
    if at_60:
        verdicts = []
        for m in models:
            mine = [r for r in at_60 if model(r) == m]
            if mine:
                verdicts.append([m, sum(1 for r in mine if r.stable_at_60hz), len(mine)])
        sec.children.append(
            Section(
                "At dt = 1/60 s",
                f"{sec.id}-60hz",
                [
                    table(
                        ["solver", "stable runs", "of"],
                        verdicts,
                        caption="The same scenes and stiffnesses run at a 60 Hz frame's step, on every backend.",
                    )
                ],
            )
        )
    return sec


# --- a PBD study -----------------------------------------------------------------------------


def pbd_study_section(f: ResultsFile, figures: Figures) -> Section:
    from clothbench.analysis.pbd_study import best_per_cost, how_busy

    rows = analysis_rows(f)
    r0 = rows[0]
    sec = Section(f"PBD study: {f.name}", section_id(f))
    costs = sorted({r.cost for r in rows})
    sec.body.append(
        paragraph(
            f"Scenes {', '.join(dict.fromkeys(r.scene for r in rows))}, {r0.grid}×{r0.grid}, frames of "
            f"1/{1 / r0.frame_dt:.4g} s, errors at t = {r0.time_s:g} s, b = {r0.damping:g} N s/m; every substeps × iterations "
            f"pair of each cost ({', '.join(map(str, costs))} constraint passes a frame) for each method; "
            f"{len(rows)} runs; ms per frame: {how_busy(rows)}. docs/pbd-study.md gives the reasoning."
        )
    )
    folder = figures.folder_for(f.path.stem)
    accuracy_plots.plot_pbd_study(rows, folder / "pbd_study.svg")
    sec.body += _inline_all(figures, folder, PBD_STUDY_FIGURES)
    best = best_per_cost(rows)
    sec.children.append(
        Section(
            "The best pair at each cost",
            f"{sec.id}-best",
            [
                table(
                    ["scene", "method", "cost", "substeps × iterations", "RMS error (m)", "max error (m)"],
                    [[s, m, c, f"{r.substeps} × {r.iterations}", r.rms, r.max] for (s, m, c), r in best.items()],
                    caption="The pair of the smallest RMS error among those of one cost (substeps × iterations).",
                )
            ],
        )
    )
    _add_failed_runs(
        sec,
        rows,
        ["scene", "method", "substeps × iterations"],
        lambda r: [r.scene, r.method, f"{r.substeps} × {r.iterations}"],
    )
    return sec


def _add_failed_runs(sec: Section, rows: list, head: list[str], cells) -> None:
    """A table of the runs whose status is not ok (what stopped each), under `sec`, if any."""
    bad = [r for r in rows if r.status != "ok"]
    if bad:
        sec.children.append(
            Section(
                "Runs that did not finish",
                f"{sec.id}-bad",
                [table([*head, "status"], [[*cells(r), r.status] for r in bad])],
            )
        )


# --- an energy study -------------------------------------------------------------------------


def energy_section(f: ResultsFile, figures: Figures) -> Section:
    rows = analysis_rows(f)
    r0 = rows[0]
    sec = Section(f"Energy: {f.name}", section_id(f))
    cases = {r.case: r for r in rows}
    damped = cases.get("damped")
    sec.body.append(
        paragraph(
            f"Scene {r0.scene}, {r0.grid}×{r0.grid} from rest, dt = {r0.dt:g} s, the energy (float64 of each mode's "
            f"own state) read every {r0.every} steps: "
            + "; ".join(f"{case} (b = {r.damping:g} N s/m) for {r.steps:,} steps" for case, r in cases.items())
            + f'; {len({r.label for r in rows})} backend modes. docs/accuracy.md ("Energy") gives the bounds.'
        )
    )
    folder = figures.folder_for(f.path.stem)
    accuracy_plots.plot_energy(rows, folder / "energy.svg")
    sec.body += _inline_all(figures, folder, ENERGY_FIGURES)
    by_label: dict[str, dict] = {}
    for r in rows:
        by_label.setdefault(r.label, {})[r.case] = r
    body = []
    for label, mine in by_label.items():
        u, d = (r if r and r.status == "ok" else None for r in (mine.get("undamped"), mine.get("damped")))
        body.append(
            [
                label,
                u.share() if u else "–",
                u.worst_drift_j if u else "–",
                ("never rose" if d.share() <= 0 else d.share()) if d else "–",
                d.max_rise_j if d else "–",
                d.e0_j - d.e_end_j if d else "–",
                "; ".join(f"{r.case}: {r.status}" for r in mine.values() if r.status != "ok") or "ok",
            ]
        )
    sec.children.append(
        Section(
            "Per backend mode",
            f"{sec.id}-modes",
            [
                table(
                    [
                        "backend, mode",
                        "undamped: drift ÷ band",
                        "worst |E − E0| (J)",
                        "damped: rise ÷ rounding",
                        "largest rise (J)",
                        "energy lost by the end (J)",
                        "status",
                    ],
                    body,
                    row_classes=[
                        "peer" if is_peer(next(iter(mine.values())).backend) else "" for mine in by_label.values()
                    ],
                    caption=f"Both bounds hold where both shares are at most 1. The damped run starts with "
                    f"{num(damped.e0_j if damped else r0.e0_j)} J.",
                )
            ],
        )
    )
    return sec


# Each kind of results CSV's section of the page (results_files.KINDS: how each is recognised
# and read, and the page's order); an artefacts file beside its accuracy run goes in that
# run's section instead (study)
SECTIONS = {
    SWEEP: sweep_section,
    ACCURACY: accuracy_section,
    STABILITY: stability_section,
    PBD_STUDY: pbd_study_section,
    ENERGY: energy_section,
    ARTEFACTS: lambda f, _figures: artefacts_section(f, f"PBD artefacts: {f.name}"),
}


def build_report(files: list, title: str = "clothbench report") -> tuple[str, int]:
    """(the page, how many figures it holds) for results files read by reports/results_files.py."""
    with tempfile.TemporaryDirectory(prefix="clothbench-report-") as tmp, vector_only():
        figures = Figures(Path(tmp))
        intro, sections = study(files, figures)
        return page(title, intro, sections), figures.count


__all__ = ["study", "machine_section", "build_report"]
