"""The chapter's comparison plots, drawn from a sweep CSV (matplotlib, headless Agg).

1. time_vs_grid: ms per step against grid size, one line per backend and variant (the
   chapter's Figures 22.5 and 22.6), devices named in the title.
2. throughput: particles per second against particles, with the fitted exponent p of
   time ∝ particles^p per line (p ≈ 1: cost grows linearly; p < 1: parallel hardware
   not yet full).
3. speed_vs_error: compute ms per simulated second against the RMS error to the float64
   reference, every backend, mode and grid.
4. local_size: ms per step against work-group / block size, for backends that have one.

Each is written as PNG and SVG. Only rows with status ok are drawn; peers (taichi, warp,
numba) are drawn dashed with hollow markers so they never pass for clothbench's kernels.
A line is one variant: the option columns (precision, strict, transfer, generic), not the
backend's mode string, which may name the local size and would split a line per size.
"""

from __future__ import annotations

import math
import textwrap
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import read_sweep

# Columns plot needs; a CSV without them is refused with their names.
REQUIRED = (
    "backend", "peer", "mode", "precision", "strict", "transfer", "local_size", "generic", "device", "scene",
    "grid", "particles", "dt", "steps", "repeats", "status", "ms_median", "ms_min", "ms_max", "err_rms_m",
)  # fmt: skip

DISPLAY = {
    "numpy": "CPU (numpy)",
    "opencl": "OpenCL",
    "glsl": "GLSL",
    "glsl-compute": "GLSL compute",
    "cuda": "CUDA",
    "taichi": "Taichi",
    "warp": "Warp",
    "numba": "Numba",
}
COLORS = {
    "numpy": "#404040",
    "glsl": "#2ca02c",
    "glsl-compute": "#17becf",
    "opencl": "#1f77b4",
    "cuda": "#d62728",
    "taichi": "#ff7f0e",
    "warp": "#9467bd",
    "numba": "#8c564b",
}
SPARE_COLORS = ("#e377c2", "#bcbd22", "#7f7f7f", "#aec7e8", "#ffbb78", "#98df8a")
MARKERS = ("o", "s", "D", "^", "v", "<", ">", "p", "h", "*")
FILES = ("time_vs_grid", "throughput", "speed_vs_error", "local_size")


@dataclass
class Row:
    backend: str
    mode: str
    precision: str
    strict: bool
    transfer: str
    peer: bool
    generic: bool
    device: str
    scene: str
    grid: int
    particles: int
    local_size: int | None
    ms: float
    ms_min: float
    ms_max: float
    dt: float
    err_rms: float | None
    raw: dict
    solver: str = "verlet"
    pbd_method: str = ""


@dataclass
class Series:
    key: tuple
    rows: list[Row]
    label: str = ""
    variant: str = ""  # what tells it from the backend's other lines ('' if nothing does)
    color: str = "black"
    marker: str = "o"
    peer: bool = False
    pbd: bool = False

    def style(self) -> dict:
        """Own kernels solid with filled markers; peers dashed with hollow markers; the PBD
        solver dash-dotted."""
        return dict(
            color=self.color,
            marker=self.marker,
            linestyle="--" if self.peer else ("-." if self.pbd else "-"),
            markerfacecolor="white" if self.peer else self.color,
            markersize=5,
            linewidth=1.4,
        )


@dataclass
class PlotReport:
    files: list[Path] = field(default_factory=list)
    exponents: dict[str, float] = field(default_factory=dict)  # series label -> p in time ∝ N^p
    series: dict[str, list[str]] = field(default_factory=dict)  # plot name -> its line labels
    notes: list[str] = field(default_factory=list)


def load(path) -> tuple[list[Row], list[dict]]:
    """(rows with status ok, rows that were not), checking the columns first."""
    raw_rows = read_sweep(path, REQUIRED)
    ok, bad = [], []
    for i, r in enumerate(raw_rows, start=2):
        if r["status"] != "ok":
            bad.append(r)
            continue
        try:
            ok.append(
                Row(
                    backend=r["backend"],
                    mode=r["mode"],
                    precision=r["precision"],
                    strict=r["strict"] == "true",
                    transfer=r["transfer"],
                    peer=r["peer"] == "true",
                    generic=r["generic"] == "true",
                    device=r["device"],
                    scene=r["scene"],
                    grid=int(r["grid"]),
                    particles=int(r["particles"]),
                    local_size=int(r["local_size"]) if r["local_size"] else None,
                    ms=float(r["ms_median"]),
                    ms_min=float(r["ms_min"]),
                    ms_max=float(r["ms_max"]),
                    dt=float(r["dt"]),
                    err_rms=float(r["err_rms_m"]) if r["err_rms_m"] else None,
                    raw=r,
                    solver=r.get("solver") or "verlet",
                    pbd_method=r.get("pbd_method") or "",
                )
            )
        except ValueError as e:
            raise ClothbenchError(f"{path}:{i}: a row with status ok has a value that is not a number ({e})") from None
    return ok, bad


def _variant(r: Row, precisions: set[str], stricts: set[bool]) -> str:
    """'strict', 'fast per-step', 'f64', ... from the option columns; only what tells a
    backend's lines apart in this file (and a precision other than f32) is named."""
    parts = []
    if r.solver == "pbd":
        parts.append(f"PBD {r.pbd_method}".rstrip())
    if precisions != {"f32"}:
        parts.append(r.precision)
    if r.strict:
        parts.append("strict")  # always named: it is a promise (bit-exact with numpy f32)
    elif True in stricts:
        parts.append("fast")
    if r.transfer:
        parts.append(r.transfer)
    if r.generic:
        parts.append("generic")
    return " ".join(parts)


def _group(rows: list[Row], by) -> list[Series]:
    """Series of rows sharing `by(row)`, in first-seen order, with labels, colours and markers."""
    groups: dict[tuple, list[Row]] = {}
    for r in rows:
        groups.setdefault(by(r), []).append(r)
    scenes = {r.scene for r in rows}
    devices, precisions, stricts = defaultdict(set), defaultdict(set), defaultdict(set)
    for r in rows:
        devices[r.backend].add(r.device)
        precisions[r.backend].add(r.precision)
        stricts[r.backend].add(r.strict)
    variants = defaultdict(list)  # backend -> its variants in first-seen order (a marker each)
    spare = iter(SPARE_COLORS * 10)
    colors = dict(COLORS)
    series = []
    for key, members in groups.items():
        first = members[0]
        variant = _variant(first, precisions[first.backend], stricts[first.backend])
        if variant not in variants[first.backend]:
            variants[first.backend].append(variant)
        if first.backend not in colors:
            colors[first.backend] = next(spare)
        label = f"{DISPLAY.get(first.backend, first.backend)} {variant}".rstrip()
        if first.peer:
            label += " (peer)"
        if len(devices[first.backend]) > 1:
            label += f" on {first.device}"
        if len(scenes) > 1:
            label += f" [{first.scene}]"
        series.append(
            Series(
                key=key,
                rows=sorted(members, key=lambda r: (r.grid, r.local_size or 0)),
                label=label,
                variant=variant,
                color=colors[first.backend],
                marker=MARKERS[variants[first.backend].index(variant) % len(MARKERS)],
                peer=first.peer,
                pbd=first.solver == "pbd",
            )
        )
    return series


def _by_variant(r: Row) -> tuple:
    return (r.backend, r.solver, r.pbd_method, r.precision, r.strict, r.transfer, r.generic, r.scene, r.device)


def _devices_line(rows: list[Row]) -> str:
    """'device: backends · device: backends', the devices the plotted rows ran on."""
    by_device: dict[str, list[str]] = {}
    for r in rows:
        names = by_device.setdefault(r.device or "unknown device", [])
        if r.backend not in names:
            names.append(r.backend)
    text = " · ".join(f"{d}: {', '.join(b)}" for d, b in by_device.items())
    return "\n".join(textwrap.wrap(text, 110))


def _footer(rows: list[Row]) -> str:
    def values(col):
        return sorted({r.raw.get(col, "") for r in rows} - {""})

    dts = ", ".join(f"{float(v) * 1e3:g}" for v in values("dt"))
    chunks = ", ".join(f"{r} chunks x {s} steps" for r, s in sorted({(r.raw["repeats"], r.raw["steps"]) for r in rows}))
    parts = [
        f"scene {', '.join(values('scene'))}, dt {dts} ms; {chunks} timed after warm-up; "
        "median of chunks, bars min-max; upload and readback not timed (except per-step transfer modes)"
    ]
    machine = [", ".join(values("cpu"))]
    if values("cores"):
        machine.append(f"{', '.join(values('cores'))} cores")
    if values("git_commit"):
        machine.append(f"commit {', '.join(values('git_commit'))}")
    stamps = values("timestamp")
    if stamps:
        machine.append(stamps[0][:10] if stamps[0][:10] == stamps[-1][:10] else f"{stamps[0][:10]}..{stamps[-1][:10]}")
    parts.append(" · ".join(m for m in machine if m))
    return "\n".join(textwrap.fill(p, 170) for p in parts)


def _figure(title: str, rows: list[Row]) -> tuple[Figure, object]:
    fig = Figure(figsize=(9, 6), layout="constrained")
    fig.get_layout_engine().set(rect=(0, 0.06, 1, 0.94))
    ax = fig.add_subplot()
    fig.suptitle(title, fontsize=13, fontweight="bold")
    ax.set_title(_devices_line(rows), fontsize=8.5)
    fig.text(0.01, 0.008, _footer(rows), fontsize=6.5, color="0.35", va="bottom")
    ax.grid(True, which="major", alpha=0.35)
    ax.grid(True, which="minor", alpha=0.12)
    return fig, ax


def _log_if_wide(ax, values, ratio=10.0) -> None:
    """Log y when the values span more than `ratio`, with plain numbers (0.5, 2, 10) as labels."""
    values = [v for v in values if v > 0]
    if values and max(values) / min(values) > ratio:
        ax.set_yscale("log")
        _plain_log_labels(ax, ax.yaxis)


def _plain_log_labels(ax, axis) -> None:
    """Label a log axis 0.1, 1, 10 (not 10^-1), and at 2 and 5 between when it spans little."""

    def span() -> float:
        lo, hi = ax.get_ylim() if axis is ax.yaxis else ax.get_xlim()
        return math.log10(hi / lo) if lo > 0 and hi > 0 else 99.0

    def minor(v, _pos) -> str:
        if v <= 0 or span() > 2.5:
            return ""
        mantissa = v / 10 ** math.floor(math.log10(v) + 1e-9)
        return f"{v:g}" if round(mantissa) in (2, 5) and abs(mantissa - round(mantissa)) < 1e-6 else ""

    axis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    axis.set_minor_formatter(FuncFormatter(minor))


def _grid_axis(ax, grids) -> None:
    grids = sorted(set(grids))
    ax.set_xscale("log", base=2)
    ax.set_xticks(grids)
    ax.set_xticklabels([f"{n}×{n}\n{n * n:,}" for n in grids], fontsize=8)
    ax.minorticks_off()
    if len(grids) == 1:
        ax.set_xlim(grids[0] / 1.5, grids[0] * 1.5)
    ax.set_xlabel("grid: particles per side (particles below)")


def _save(fig: Figure, out: Path, name: str, report: PlotReport) -> None:
    for ext in ("png", "svg"):
        path = out / f"{name}.{ext}"
        fig.savefig(path, dpi=150 if ext == "png" else None)
        report.files.append(path)


def plot_time_vs_grid(rows: list[Row], out: Path, report: PlotReport) -> None:
    series = _group([r for r in rows if r.local_size is None], _by_variant)
    report.series["time_vs_grid"] = [s.label for s in series]
    used = [r for s in series for r in s.rows]
    fig, ax = _figure("Computation time per step against grid size", used)
    for s in series:
        x = [r.grid for r in s.rows]
        y = [r.ms for r in s.rows]
        err = [[r.ms - r.ms_min for r in s.rows], [r.ms_max - r.ms for r in s.rows]]
        ax.errorbar(x, y, yerr=err, label=s.label, capsize=2, elinewidth=0.8, **s.style())
    _grid_axis(ax, [r.grid for r in used])
    _log_if_wide(ax, [r.ms for r in used])
    ax.set_ylabel("time per step (ms), median")
    ax.legend(fontsize=8, loc="upper left")
    _save(fig, out, "time_vs_grid", report)


def scaling_exponent(particles: list[int], ms: list[float]) -> float | None:
    """p in time ∝ particles^p, least squares in log-log; None with fewer than two sizes."""
    if len(set(particles)) < 2:
        return None
    return float(np.polyfit(np.log(particles), np.log(ms), 1)[0])


def plot_throughput(rows: list[Row], out: Path, report: PlotReport) -> None:
    series = _group([r for r in rows if r.local_size is None], _by_variant)
    report.series["throughput"] = [s.label for s in series]
    used = [r for s in series for r in s.rows]
    fig, ax = _figure("Throughput against particle count", used)
    for s in series:
        x = [r.particles for r in s.rows]
        p = scaling_exponent(x, [r.ms for r in s.rows])
        label = s.label
        if p is not None:
            report.exponents[s.label] = p
            label += f":  time ∝ N^{p:.2f}"
        ax.plot(x, [r.particles * 1e3 / r.ms for r in s.rows], label=label, **s.style())
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:,.0f}"))
    ax.set_xlabel("particles N")
    ax.set_ylabel("throughput (particles per second)")
    ax.legend(fontsize=8, loc="best", title="fitted: time per step ∝ N^p", title_fontsize=8)
    _save(fig, out, "throughput", report)


def plot_speed_vs_error(rows: list[Row], out: Path, report: PlotReport) -> None:
    with_err = [r for r in rows if r.local_size is None and r.err_rms is not None]
    if not with_err:
        report.notes.append("speed_vs_error: no row has an error measurement; not drawn")
        return
    series = _group(with_err, _by_variant)
    report.series["speed_vs_error"] = [s.label for s in series]
    positive = [r.err_rms for r in with_err if r.err_rms > 0]
    floor = 10 ** math.floor(math.log10(min(positive))) / 10 if positive else 1e-12
    fig, ax = _figure("Speed against error", with_err)
    for s in series:
        x = [max(r.err_rms, floor) for r in s.rows]
        y = [r.ms / r.dt for r in s.rows]
        ax.plot(x, y, label=s.label, **s.style())
        for r, xi, yi in zip(s.rows, x, y):
            ax.annotate(f"{r.grid}", (xi, yi), xytext=(3, 3), textcoords="offset points", fontsize=6, color=s.color)
    ax.set_xscale("log")
    ax.set_yscale("log")
    _plain_log_labels(ax, ax.yaxis)
    if len(positive) < len(with_err):
        ax.axvline(floor, color="0.5", linestyle=":", linewidth=1)
        ax.annotate("error 0: the float64 reference itself", (floor, 0.02), xycoords=ax.get_xaxis_transform(),
                    xytext=(-3, 0), textcoords="offset points", fontsize=7, color="0.35", rotation=90,
                    va="bottom", ha="right")  # fmt: skip
    ax.axhline(1000.0, color="0.5", linestyle="-.", linewidth=0.8)
    ax.text(0.99, 1000.0, "real time ", transform=ax.get_yaxis_transform(), fontsize=7, color="0.35",
            ha="right", va="bottom")  # fmt: skip
    ax.set_xlabel("RMS position error against numpy float64 after the timed run (m)")
    ax.set_ylabel("compute time per simulated second (ms)")
    ax.legend(fontsize=8, loc="best", title="numbers: particles per side", title_fontsize=7)
    _save(fig, out, "speed_vs_error", report)


def plot_local_size(rows: list[Row], out: Path, report: PlotReport) -> None:
    """One panel per backend; a line per variant and grid (colour = grid), with the runtime's
    own choice (empty local_size) drawn at the left as 'auto'."""
    sized = [r for r in rows if r.local_size is not None]
    if not sized:
        report.notes.append(
            "local_size: no rows with a work-group / block size; not drawn "
            "(sweep with --local-sizes 16,32,64,128 on a backend that has one)"
        )
        return
    backends = list(dict.fromkeys(r.backend for r in sized))
    variants = {r[:-1] for r in map(_by_variant_grid, sized)}
    grids = sorted({r.grid for r in sized})
    # the runtime's own choice, at the grids the local sizes were swept at
    defaults = [
        r for r in rows if r.local_size is None and r.grid in grids and _by_variant_grid(r)[:-1] in variants
    ]
    sizes = sorted({r.local_size for r in sized})
    auto_x = sizes[0] / 2  # where the runtime's own choice is drawn
    cmap = matplotlib.colormaps["viridis"]
    shade = {n: cmap(0.85 * i / max(1, len(grids) - 1)) for i, n in enumerate(grids)}

    fig = Figure(figsize=(max(7.0, 5.2 * len(backends)), 6), layout="constrained")
    fig.get_layout_engine().set(rect=(0, 0.06, 1, 0.94))
    fig.suptitle("Time per step against work-group / block size", fontsize=13, fontweight="bold")
    fig.text(0.01, 0.008, _footer(sized), fontsize=6.5, color="0.35", va="bottom")
    axes = fig.subplots(1, len(backends), sharey=True, squeeze=False)[0]
    report.series["local_size"] = []
    for ax, backend in zip(axes, backends):
        mine = [r for r in sized if r.backend == backend]
        series = _group(mine + [r for r in defaults if r.backend == backend], _by_variant_grid)
        ax.set_title(f"{DISPLAY.get(backend, backend)} on {mine[0].device}", fontsize=9)
        linestyles = {}
        for s in series:
            n = s.rows[0].grid
            variant = s.variant or "default"
            linestyles.setdefault(variant, ("-", "--", "-.", ":")[len(linestyles) % 4])
            style = s.style() | dict(color=shade[n], linestyle=linestyles[variant])
            if not s.peer:
                style["markerfacecolor"] = shade[n]
            pts = [r for r in s.rows if r.local_size is not None]
            if not pts:
                continue
            report.series["local_size"].append(f"{s.label}, n={n}")
            err = [[r.ms - r.ms_min for r in pts], [r.ms_max - r.ms for r in pts]]
            ax.errorbar([r.local_size for r in pts], [r.ms for r in pts], yerr=err, capsize=2, elinewidth=0.7,
                        label=f"{variant}, n={n}", **style)  # fmt: skip
            for r in s.rows:
                if r.local_size is None:
                    ax.plot([auto_x], [r.ms], marker=style["marker"], color=shade[n], markersize=6,
                            markerfacecolor="white", linestyle="none")  # fmt: skip
        ax.set_xscale("log", base=2)
        ax.set_xticks([auto_x, *sizes])
        ax.set_xticklabels(["auto", *map(str, sizes)])
        ax.minorticks_off()
        ax.set_xlim(auto_x / 1.4, sizes[-1] * 1.4)
        ax.set_xlabel("work-group / block size (work items); auto = the runtime's choice")
        ax.grid(True, which="major", alpha=0.35)
        ax.legend(fontsize=7, loc="best", ncol=2 if len(series) > 6 else 1)
    _log_if_wide(axes[0], [r.ms for r in sized] + [r.ms for r in defaults])
    axes[0].set_ylabel("time per step (ms), median")
    _save(fig, out, "local_size", report)


def _by_variant_grid(r: Row) -> tuple:
    return (*_by_variant(r), r.grid)


def plot_sweep(path, out) -> PlotReport:
    """Draw every plot the CSV has data for into `out`; say what was left out and why."""
    ok, bad = load(path)
    if not ok:
        raise ClothbenchError(f"{path} has no row with status ok: nothing to plot")
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ClothbenchError(f"cannot create {out}: {e.strerror}") from None
    report = PlotReport()
    left_out: dict[tuple[str, str, str], list[str]] = {}
    for r in bad:
        left_out.setdefault((r["backend"], r["status"], r.get("note", "")), []).append(f"{r['mode']} n={r['grid']}")
    for (backend, status, note), where in left_out.items():
        rows_ = f"{len(where)} rows" if len(where) > 1 else "1 row"
        report.notes.append(f"left out {rows_} of {backend}, {status}: {note} ({'; '.join(dict.fromkeys(where))})")
    plot_time_vs_grid(ok, out, report)
    plot_throughput(ok, out, report)
    plot_speed_vs_error(ok, out, report)
    plot_local_size(ok, out, report)
    return report
