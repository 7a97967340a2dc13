"""What every clothbench figure shares (reports/plots.py draws the sweep's, reports/
accuracy_plots.py the accuracy and stability runs'): small multiples of at most MAX_SERIES
series a panel, split by platform; peers drawn apart from clothbench's own backends (dashed
lines, hollow markers, "(peer)" in the legend); the Pareto front of cost against error,
drawn and labelled; log axes labelled in plain numbers; the machine, commit and date under
every figure whose rows record them; every figure written as PNG and SVG.

Figures are matplotlib Figures on the Agg canvas, never pyplot: nothing global, no display.
"""

from __future__ import annotations

import hashlib
import io
import math
import re
import textwrap
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, TypeVar

from matplotlib import rc_context
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.layout_engine import ConstrainedLayoutEngine
from matplotlib.text import Annotation, Text
from matplotlib.ticker import FuncFormatter

from clothbench.backends import BACKENDS, PEERS, PLATFORMS, check_name

T = TypeVar("T")

MAX_SERIES = 8  # more lines than this in one panel and a reader stops telling them apart

# each platform's colour where a figure colours by platform (the registry's PLATFORMS, each one)
COLORS_OF = {"CPU": "#404040", "OpenCL": "#1f77b4", "GL": "#2ca02c", "CUDA": "#d62728", PEERS: "#ff7f0e"}
NATIVE_COLOR = "black"  # the c backend's fast line, drawn in every panel as the native CPU line
# distinct at a glance and in print; a panel's series take them in order
PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#7f7f7f", "#bcbd22")
MARKERS = ("o", "s", "D", "^", "v", "<", ">", "p", "h", "*")
FRONT_COLOR = "black"
# float32 rounding moves equally correct kernels' errors a few per cent apart: closer than
# this, two errors count as equal on the drawn fronts, and the cheaper point wins
FRONT_TOLERANCE = 0.05
FRONT_LEGEND = "Pareto front: no other point both cheaper and more accurate (errors within 5 % count as equal)"
BOUND_COLOR = "0.55"
PNG_DPI = 150  # what save_figure writes a PNG at
REPRODUCIBLE = {"svg.hashsalt": "clothbench"}  # SVG element ids from this, not from a random salt


@dataclass
class Chart:
    """A drawn figure and what is on it: each panel's series labels (title -> labels, in
    drawing order) and, where a Pareto front is drawn, its points' labels (panel -> labels,
    by increasing error)."""

    figure: Figure
    panels: dict[str, list[str]] = field(default_factory=dict)
    fronts: dict[str, list[str]] = field(default_factory=dict)


# A backend's facts are its registry entry's (backends/__init__.py); a results file naming a
# backend the registry does not know is refused in one line (check_name), never drawn under a guess.


def display_name(backend: str) -> str:
    """Its name in tables and legends ('CPU (numpy)', 'GLSL compute')."""
    return check_name(backend).display


def is_peer(backend: str) -> bool:
    """A system users would pick instead of clothbench (the registry's peer flag)."""
    return check_name(backend).peer


def platform_title(platform: str) -> str:
    """A platform's panel title: its name, the CPU's with the backends on it ('CPU (numpy, c)')."""
    if platform != "CPU":
        return platform
    return f"CPU ({', '.join(name for name, e in BACKENDS.items() if e.platform == platform)})"


def platform_of(backend: str) -> str:
    """The panel a backend's series go to (its registry platform's title): CPU, OpenCL, GL
    (fragment and compute), CUDA, or peers."""
    return platform_title(check_name(backend).platform)


def platform_rank(title: str) -> int:
    """Where a platform's panel goes: the registry's PLATFORMS order."""
    return [platform_title(p) for p in PLATFORMS].index(title)


def platform_color(title: str) -> str:
    """The colour of a platform's points, by its panel title (platform_of)."""
    return {platform_title(p): c for p, c in COLORS_OF.items()}[title]


def series_style(index: int, *, peer: bool = False, pbd: bool = False, color: str | None = None) -> dict:
    """Line style of a panel's index-th series: clothbench's kernels solid with filled markers,
    the PBD solver dash-dotted, peers dashed with hollow markers."""
    color = color or PALETTE[index % len(PALETTE)]
    return dict(
        color=color,
        marker=MARKERS[index % len(MARKERS)],
        linestyle="--" if peer else ("-." if pbd else "-"),
        markerfacecolor="white" if peer else color,
        markersize=5,
        linewidth=1.4,
    )


def small_multiples(
    series: list[T], platform: Callable[[T], str], model: Callable[[T], str] | None = None
) -> list[tuple[str, list[T]]]:
    """(title, series) panels of at most MAX_SERIES each: one panel when they all fit; else a
    panel per platform (in the registry's PLATFORMS order), a platform with too many split per
    solver model where `model` tells them apart, and what is still too many in chunks."""
    if len(series) <= MAX_SERIES:
        return [("", list(series))]
    panels = []
    for name, members in _grouped(series, platform, platform_rank):
        parts = [(name, members)]
        if len(members) > MAX_SERIES and model is not None:
            parts = [(f"{name}, {m}", ms) for m, ms in _grouped(members, model, lambda _: 0)]
        for title, ms in parts:
            chunks = [ms[i : i + MAX_SERIES] for i in range(0, len(ms), MAX_SERIES)]
            for k, chunk in enumerate(chunks):
                panels.append((title if len(chunks) == 1 else f"{title} ({k + 1}/{len(chunks)})", chunk))
    return panels


def _grouped(items: list[T], key: Callable[[T], str], rank: Callable[[str], int]) -> list[tuple[str, list[T]]]:
    """(key, items) groups by rank(key), in first-seen order within a rank."""
    groups: dict[str, list[T]] = {}
    for item in items:
        groups.setdefault(key(item), []).append(item)
    return sorted(groups.items(), key=lambda kv: rank(kv[0]))


def pareto_front(
    items: Iterable[T], cost: Callable[[T], float], error: Callable[[T], float], tolerance: float = 0.0
) -> list[T]:
    """The items no other item beats on both cost and error (lower is better in each: at
    least as good in both and better in one), by increasing error. With a `tolerance`,
    errors within that fraction of each other count as equal, so a cheaper item beats one
    that is only within rounding noise more accurate. Items whose cost or error is not a
    finite number are left out; two items equal in both are both kept."""
    points = [(error(i), cost(i), i) for i in items]
    points = [p for p in points if math.isfinite(p[0]) and math.isfinite(p[1])]
    slack = 1.0 + tolerance

    def beats(a, b) -> bool:
        as_good = a[0] <= b[0] * slack and a[1] <= b[1]
        return as_good and (a[1] < b[1] or a[0] * slack < b[0])

    front = [p for p in points if not any(beats(q, p) for q in points)]
    return [p[2] for p in sorted(front, key=lambda p: (p[0], p[1]))]


def draw_front(ax, points: list[tuple[float, float, str]], labelled: bool = True) -> list:
    """The front through (error, cost, label) points, by increasing error, as the staircase of
    the best cost reachable at each error, its points ringed and (labelled) named at their
    lower left, a region no measured point can be in (it would beat the front point). Returns
    the labels, for fit_labels."""
    if not points:
        return []
    xs, ys = [p[0] for p in points], [p[1] for p in points]
    ax.step(xs, ys, where="post", color=FRONT_COLOR, linewidth=1.1, alpha=0.75, zorder=4, label="Pareto front")
    ax.plot(
        xs,
        ys,
        linestyle="none",
        marker="o",
        markersize=9,
        markerfacecolor="none",
        markeredgecolor=FRONT_COLOR,
        markeredgewidth=1.0,
        zorder=5,
    )
    if not labelled:
        return []
    labels = [
        ax.annotate(
            label,
            (x, y),
            xytext=LABEL_OFFSET,
            textcoords="offset points",
            ha="right",
            va="top",
            fontsize=6.5,
            zorder=6,
            bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.8),
            arrowprops=LEADER,
        )
        for x, y, label in points
    ]
    for label in labels:
        label.arrow_patch.set_visible(False)  # shown by fit_labels where it moves the label off its point
    return labels


LABEL_OFFSET = (-5.0, -4.0)  # points: a front label's top right corner, from its point
# a moved label's line from its top right corner (the one towards its point) to the point's ring
# (draw_front's markersize 9: radius 4.5 points)
LEADER_AFTER = 4.0  # points a label moves down before it needs a leader: less, and it still touches the ring
LEADER = dict(arrowstyle="-", color=FRONT_COLOR, linewidth=0.5, alpha=0.6, shrinkA=0, shrinkB=4.5, relpos=(1, 1))


def fit_labels(fig: Figure, labels: list) -> None:
    """Move draw_front's labels apart: each one that overlaps a text placed before it (a label,
    or an axes' own text, such as a line's name) goes down, still lower left of its point, so
    still on no other point, with a leader line to its point once it is moved far. The axes
    grow down and left until every label is inside, five times at most; the last placement is
    on the final limits, so no two texts overlap even where a label could not be brought in."""
    if not labels:
        return
    for _ in range(5):
        boxes = _place_labels(fig, labels)
        if not _grow_to_fit(labels, boxes):
            return
    _place_labels(fig, labels)


def _place_labels(fig: Figure, labels: list) -> list:
    """fit_labels' placement on the figure as it is laid out now; each label's box."""
    fig.draw_without_rendering()  # laid out and the texts placed, no pixels: the same PNG, ~10 % sooner
    renderer = fig.canvas.get_renderer()
    own = set(map(id, labels))
    axes = list(dict.fromkeys(label.axes for label in labels))
    placed = [
        _text_box(t, renderer)
        for ax in axes
        for t in ax.texts
        if id(t) not in own and t.get_visible() and t.get_text().strip()
    ]
    boxes = []
    for label in labels:
        label.xyann = LABEL_OFFSET
        box = _text_box(label, renderer)
        for _ in range(len(placed) * 4):
            clash = next((p for p in placed if box.overlaps(p)), None)
            if clash is None:
                break
            down = (box.y1 - clash.y0 + 2) * 72 / fig.dpi
            label.xyann = (label.xyann[0], label.xyann[1] - down)
            box = _text_box(label, renderer)
        label.arrow_patch.set_visible(LABEL_OFFSET[1] - label.xyann[1] > LEADER_AFTER)
        placed.append(box)
        boxes.append(box)
    return boxes


def _text_box(text, renderer):
    """A text's own box in pixels: an annotation's without its leader line, where it is now."""
    if isinstance(text, Annotation):
        text.update_positions(renderer)
    return Text.get_window_extent(text, renderer)


def _grow_to_fit(labels: list, boxes: list) -> bool:
    """Widen the labels' axes down and left (once per group of shared axes) where a label
    falls more than a pixel short of its margin inside them; whether any was widened."""
    need: dict[tuple, list] = {}  # shared x axes, shared y axes -> [axes, left px, below px]
    for label, box in zip(labels, boxes):
        ax = label.axes
        frame = ax.get_window_extent()
        key = (_siblings(ax.get_shared_x_axes(), ax), _siblings(ax.get_shared_y_axes(), ax))
        entry = need.setdefault(key, [ax, 0.0, 0.0])
        entry[1] = max(entry[1], frame.x0 - box.x0 + LABEL_MARGIN)
        entry[2] = max(entry[2], frame.y0 - box.y0 + LABEL_MARGIN)
    grown = False
    for ax, left, below in need.values():
        frame = ax.get_window_extent()
        if left > GROW_AT_LEAST:
            ax.set_xlim(*_widened(ax.get_xlim(), left / frame.width, ax.get_xscale() == "log"))
        if below > GROW_AT_LEAST:
            ax.set_ylim(*_widened(ax.get_ylim(), below / frame.height, ax.get_yscale() == "log"))
        grown = grown or left > GROW_AT_LEAST or below > GROW_AT_LEAST
    return grown


LABEL_MARGIN = 8  # pixels a label keeps inside its axes' lower and left edges
# Pixels short of that margin worth another layout: each growth leaves the label a hair outside
# again (the new layout moves the frame by a fraction of a pixel), so without this every
# fit_labels ran its five layouts, the last four for under a pixel (the report of every committed
# CSV: 54 layouts for its 9 labelled figures, 1 s each on the Zen 3, 2026-12-06)
GROW_AT_LEAST = 1.0


def _siblings(grouper, ax) -> tuple[int, ...]:
    return tuple(sorted(id(a) for a in grouper.get_siblings(ax)))


def _widened(lim: tuple[float, float], fraction: float, log: bool) -> tuple[float, float]:
    """Limits whose lower end moves out far enough that what sat at the old lower end now sits
    `fraction` of the axes in (the span grows by fraction / (1 - fraction))."""
    lo, hi = lim
    grow = min(fraction, 0.5) / (1 - min(fraction, 0.5))
    if log:
        return lo / (hi / lo) ** grow, hi
    return lo - (hi - lo) * grow, hi


def draw_bound_lines(ax, rows: list, x: Callable, y: Callable) -> bool:
    """The machine's bound (the rows' `bound_ms`, where a sweep measured it) as a grey line per
    machine (its CPU: every backend's device on it shares the one bound) across its grids;
    nothing when no row has one. Whether a line was drawn."""
    by_machine: dict[str, dict] = {}
    for r in rows:
        if r.bound_ms:
            by_machine.setdefault(r.raw.get("cpu", ""), {}).setdefault(x(r), []).append(y(r))
    for machine, points in by_machine.items():
        xs = sorted(points)
        label = "machine bound" + (f" ({machine})" if len(by_machine) > 1 else "")
        ax.plot(
            xs,
            [min(points[v]) for v in xs],
            color=BOUND_COLOR,
            linewidth=2.4,
            alpha=0.7,
            linestyle=(0, (6, 2)),
            zorder=1,
            label=label,
        )
    return bool(by_machine)


def draw_native_line(ax, rows: list, x: Callable, y: Callable) -> bool:
    """The c backend's fast float32 Verlet rows as a thin black line: the native CPU line
    every other panel is read against (the chapter's CPU line). Whether a line was drawn."""
    native = sorted(
        (
            r
            for r in rows
            if r.backend == "c" and not r.strict and r.precision == "f32" and r.solver == "verlet" and not r.local_size
        ),
        key=x,
    )
    if not native:
        return False
    ax.plot(
        [x(r) for r in native],
        [y(r) for r in native],
        color=NATIVE_COLOR,
        linewidth=1.0,
        linestyle=":",
        zorder=2,
        label="c fast: the native CPU line",
    )
    return True


def new_figure(width: float, height: float) -> Figure:
    """A Figure on the Agg canvas (so labels can be measured before saving), laid out by
    constrained layout."""
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def machine_line(records: Iterable[Mapping]) -> str:
    """Where and when the rows' costs were measured, from their cpu, cores, git_commit and
    timestamp columns (environment.collect()'s): 'Intel Xeon · 2 cores · commit abc123 ·
    2026-12-01'. Rows from several machines say so and name each ('2 machines: A (2 cores),
    B (64 cores)'), from several commits name each, from several days the first and last. A
    column no row has is left out: rows older than the columns give less, or ''."""
    records = list(records)

    def values(col: str) -> list[str]:
        return sorted({str(r.get(col) or "") for r in records} - {""})

    machines = sorted({(str(r.get("cpu") or ""), str(r.get("cores") or "")) for r in records} - {("", "")})
    parts = []
    if len(machines) == 1:
        cpu, cores = machines[0]
        parts += [cpu, f"{cores} cores" if cores else ""]
    elif machines:
        named = [f"{cpu or 'unknown CPU'}" + (f" ({cores} cores)" if cores else "") for cpu, cores in machines]
        parts.append(f"{len(machines)} machines: {', '.join(named)}")
    if values("git_commit"):
        parts.append(f"commit {', '.join(values('git_commit'))}")
    days = sorted({stamp[:10] for stamp in values("timestamp")})
    if days:
        parts.append(days[0] if len(days) == 1 else f"{days[0]}..{days[-1]}")
    return " · ".join(p for p in parts if p)


def titled_figure(title: str, width: float, body_height: float, footer: str = ""):
    """(figure, body): a figure with a bold title, and under the body (what panels go in, a
    subfigure laid out on its own) the footer's lines, small and grey."""
    foot_height = 0.12 * (footer.count("\n") + 1) + 0.1 if footer else 0.0
    fig = new_figure(width, body_height + foot_height)
    body = fig
    if footer:
        body, foot = fig.subfigures(2, 1, height_ratios=[body_height, foot_height])
        foot.text(0.006, 0.92, footer, fontsize=6.5, color="0.35", va="top")
    body.suptitle(title, fontsize=13, fontweight="bold")
    return fig, body


def panel_axes(body, count: int, cols: int = 3, wide_first: bool = False, key: bool = False):
    """(axes, key axes or None): `count` axes sharing both axes, `cols` to a row; with
    wide_first the first spans two columns (an overview before the per-platform panels).
    With key, an axes without axes for a legend shared by every panel: the empty cells of
    the last row, or a row of its own when there are none."""
    cols = max(1, min(cols, count + (1 if wide_first else 0)))
    cells = count + (1 if wide_first and cols > 1 else 0)
    rows = math.ceil(cells / cols)
    spare = rows * cols - cells
    extra = key and not spare
    grid = body.add_gridspec(rows + extra, cols, height_ratios=[1.0] * rows + [0.18] * extra)
    axes, cell = [], 0
    for i in range(count):
        span = 2 if (i == 0 and wide_first and cols > 1) else 1
        r, c = divmod(cell, cols)
        axes.append(
            body.add_subplot(grid[r, c : c + span], sharex=axes[0] if axes else None, sharey=axes[0] if axes else None)
        )
        cell += span
    key_axes = None
    if key:
        key_axes = body.add_subplot(grid[rows, :] if extra else grid[rows - 1, cols - spare :])
        key_axes.axis("off")
    return axes, key_axes


def key_legend(key_axes, handles: list) -> None:
    """The legend every panel shares, in the key axes panel_axes made: as many columns as
    the key spans panels, long labels wrapped to fit."""
    span = len(key_axes.get_subplotspec().colspan)
    for h in handles:
        h.set_label(textwrap.fill(h.get_label(), 50))
    key_axes.legend(
        handles=handles, loc="center", ncol=min(len(handles), span), fontsize=7.5, frameon=False, handlelength=2.4
    )


def plain_log_labels(ax, axis) -> None:
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


def panel_legend(ax, ncol: int | None = None, handles: list | None = None) -> None:
    """The panel's legend under it, where it covers no data: its labelled lines, or `handles`;
    in `ncol` columns, by default two, or one when a label is too long for two side by side."""
    if handles is None:
        handles, _ = ax.get_legend_handles_labels()
    if ncol is None:
        ncol = 1 if max((len(h.get_label()) for h in handles), default=0) > 48 else 2
    for h in handles:
        if hasattr(h, "set_label"):
            h.set_label(textwrap.fill(h.get_label(), 60))
    if handles:
        ax.legend(
            handles=handles,
            fontsize=6.5,
            loc="upper center",
            bbox_to_anchor=(0.5, -0.16),
            ncol=ncol,
            frameon=False,
            handlelength=2.6,
            columnspacing=1.2,
        )


# whether save_figure rasterises: `clothbench report` inlines the SVG alone, and the PNGs at
# 150 dpi were a quarter of its time (results/*.csv: 125 s, 94 s without; the Zen 3, 2026-12-06)
_RASTER: ContextVar[bool] = ContextVar("raster", default=True)


@contextmanager
def vector_only():
    """Within it, save_figure writes the SVG alone (for a page that inlines its figures)."""
    token = _RASTER.set(False)
    try:
        yield
    finally:
        _RASTER.reset(token)


def save_figure(fig: Figure, path: Path, dpi: int = PNG_DPI) -> list[Path]:
    """Write `fig` as PNG at `path` (its suffix made .png) and as SVG beside it, the folder
    made if missing; the paths (the SVG's alone within vector_only). No date, the layout frozen
    once (freeze_layout) and SVG ids from a fixed salt or what they name (figure_svg): a figure
    drawn again from the same data writes the same bytes, so regenerated figures change in git
    only where they changed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    freeze_layout(fig)
    png, svg = path.with_suffix(".png"), path.with_suffix(".svg")
    if _RASTER.get():
        with rc_context(REPRODUCIBLE):
            fig.savefig(png, dpi=dpi)
    svg.write_text(figure_svg(fig), encoding="utf-8")
    return [png, svg] if _RASTER.get() else [svg]


def figure_svg(fig: Figure) -> str:
    """The figure as SVG text (for a page that inlines its figures), as save_figure writes it:
    its clip paths named by a hash of what they hold (below), every other id from the salt."""
    buffer = io.StringIO()
    freeze_layout(fig)
    with rc_context(REPRODUCIBLE):
        fig.savefig(buffer, format="svg", metadata={"Date": None})
    svg = buffer.getvalue()
    names = {m[1]: "p" + hashlib.sha256(m[2].encode()).hexdigest()[:10] for m in _CLIP_PATH.finditer(svg)}
    return re.sub(r"\bp[0-9a-f]{10}\b", lambda m: names.get(m[0], m[0]), svg) if names else svg


# matplotlib names an SVG clip path by a hash of its rectangle's unrounded corners, whose last
# bits differ from one process to the next even where the axes' places are the same (measured:
# 1e-13 apart, about one run in three), though the rectangle it writes (6 decimals) is the
# same: figure_svg renames each by a hash of what it writes. (Not numbered: a page inlines
# several figures, and one id must name one clip path in all of them.)
_CLIP_PATH = re.compile(r'<clipPath id="(p[0-9a-f]{10})">(.*?)</clipPath>', re.S)


def freeze_layout(fig: Figure) -> None:
    """Lay `fig` out once more and keep that layout, its axes' places rounded to 1e-7 of the
    figure, for every file drawn from it (PNG and SVG alike). Constrained layout's solver
    (kiwisolver) does not repeat its last bits from one process to the next (measured: the same
    figure's axes 1e-13 apart, about one run in three); a coordinate that lay on a 6-decimal
    boundary was then written differently."""
    if not isinstance(fig.get_layout_engine(), ConstrainedLayoutEngine):
        return  # laid out and frozen already, or laid out by hand
    fig.draw_without_rendering()
    places = [(ax, ax.get_position(original=False).bounds) for ax in fig.axes]
    fig.set_layout_engine("none")
    for ax, bounds in places:
        ax.set_position([round(v, 7) for v in bounds])
