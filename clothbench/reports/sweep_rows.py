"""A sweep CSV's rows as the sweep figures (reports/plots.py) read them: typed rows, grouped
into series (one per backend variant), each labelled by what tells it from the others, and
the lines that say where and how it was measured.

A series is one variant: the option columns (precision, strict, transfer, generic, solver),
not the backend's mode string, which may name the local size and would split a line per size.
"""

from __future__ import annotations

import textwrap
from collections import defaultdict
from dataclasses import dataclass

from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import BUDGET_NOTE, read_sweep
from clothbench.reports.figures_common import display_name, machine_line, platform_of, series_style
from clothbench.variant_names import model_display

# Columns the figures need; a CSV without them is refused with their names.
REQUIRED = (
    "backend",
    "peer",
    "mode",
    "precision",
    "strict",
    "transfer",
    "local_size",
    "generic",
    "device",
    "scene",
    "grid",
    "particles",
    "dt",
    "steps",
    "repeats",
    "status",
    "ms_median",
    "ms_min",
    "ms_max",
    "err_rms_m",
)


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
    bound_ms: float | None = None  # the machine's lower bound on ms per step, where the sweep has one
    # the device's own ms per step and its clock (sweep_csv: device_timer), where the row has them;
    # files older than the device_timer column say nothing of the clock
    device_ms: float | None = None
    device_timer: str = ""

    @property
    def model(self) -> str:
        """'Verlet', 'PBD jacobi', ...: the solver model, what a panel may be split by."""
        return model_display(self.solver, self.pbd_method)

    @property
    def cost(self) -> float:
        """Compute ms per simulated second."""
        return self.ms / self.dt


@dataclass
class Series:
    key: tuple
    rows: list[Row]
    label: str = ""
    variant: str = ""  # what tells it from the backend's other lines ('' if nothing does)
    peer: bool = False
    pbd: bool = False
    color: str | None = None  # None: the panel's palette colour for its place in the panel

    @property
    def platform(self) -> str:
        return platform_of(self.rows[0].backend)

    @property
    def model(self) -> str:
        return self.rows[0].model

    def style(self, index: int) -> dict:
        return series_style(index, peer=self.peer, pbd=self.pbd, color=self.color)


def _optional_float(text: str | None) -> float | None:
    return float(text) if text else None


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
                    err_rms=_optional_float(r["err_rms_m"]),
                    raw=r,
                    solver=r.get("solver") or "verlet",
                    pbd_method=r.get("pbd_method") or "",
                    bound_ms=_optional_float(r.get("bound_ms")),
                    device_ms=_optional_float(r.get("device_ms_median")),
                    device_timer=r.get("device_timer") or "",
                )
            )
        except ValueError as e:
            raise ClothbenchError(f"{path}:{i}: a row with status ok has a value that is not a number ({e})") from None
    return ok, bad


def _variant(r: Row, precisions: set[str], stricts: set[bool]) -> str:
    """'strict', 'fast per-step', 'f64', ... from the option columns; only what tells a
    backend's lines apart in this file (and a precision other than f32) is named."""
    parts = []
    if r.solver != "verlet":
        parts.append(model_display(r.solver, r.pbd_method))
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


def group(rows: list[Row], by) -> list[Series]:
    """Series of rows sharing `by(row)`, in first-seen order, with labels."""
    groups: dict[tuple, list[Row]] = {}
    for r in rows:
        groups.setdefault(by(r), []).append(r)
    scenes = {r.scene for r in rows}
    devices, precisions, stricts = defaultdict(set), defaultdict(set), defaultdict(set)
    for r in rows:
        devices[r.backend].add(r.device)
        precisions[r.backend].add(r.precision)
        stricts[r.backend].add(r.strict)
    series = []
    for key, members in groups.items():
        first = members[0]
        variant = _variant(first, precisions[first.backend], stricts[first.backend])
        label = f"{display_name(first.backend)} {variant}".rstrip()
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
                peer=first.peer,
                pbd=first.solver != "verlet",
            )
        )
    return series


def by_variant(r: Row) -> tuple:
    return (r.backend, r.solver, r.pbd_method, r.precision, r.strict, r.transfer, r.generic, r.scene, r.device)


def by_variant_grid(r: Row) -> tuple:
    return (*by_variant(r), r.grid)


def devices_line(rows: list[Row]) -> str:
    """'device: backends · device: backends', the devices the plotted rows ran on."""
    by_device: dict[str, list[str]] = {}
    for r in rows:
        names = by_device.setdefault(r.device or "unknown device", [])
        if r.backend not in names:
            names.append(r.backend)
    text = " · ".join(f"{d}: {', '.join(b)}" for d, b in by_device.items())
    return "\n".join(textwrap.wrap(text, 150))


def footer(rows: list[Row]) -> str:
    """How the rows were measured, and on what: scene, dt, chunks, machine, commit, date."""

    def values(col):
        return sorted({r.raw.get(col, "") for r in rows} - {""})

    dts = ", ".join(f"{float(v) * 1e3:g}" for v in values("dt"))

    def budget_cut(r: Row) -> bool:
        return r.raw.get("note", "").startswith(BUDGET_NOTE)

    cut = sum(map(budget_cut, rows))
    planned = {(r.raw["repeats"], r.raw["steps"]) for r in rows if not budget_cut(r)}
    planned = planned or {(r.raw["repeats"], r.raw["steps"]) for r in rows}
    chunks = ", ".join(f"{r} chunks x {s} steps" for r, s in sorted(planned))
    if cut:
        chunks += f" ({cut} slow rows fewer, cut by the per-row time budget: see their notes)"
    parts = [
        f"scene {', '.join(values('scene'))}, dt {dts} ms; {chunks} timed after warm-up; "
        "median of chunks, bars min-max; upload and readback not timed (except per-step transfer modes)"
    ]
    parts.append(machine_line(r.raw for r in rows))
    return "\n".join(textwrap.fill(p, 170) for p in parts)
