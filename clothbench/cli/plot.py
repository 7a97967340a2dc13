"""`clothbench plot` (the chapter's figures from a sweep CSV) and `clothbench compare`
(what changed between two sweeps: two machines, two commits)."""

from __future__ import annotations

import math
from pathlib import Path

from clothbench.errors import ClothbenchError

# What compare needs of both files.
COMPARE_REQUIRED = (
    "backend", "solver", "scene", "grid", "precision", "strict", "transfer", "generic", "local_size",
    "mode", "status", "ms_median", "steps", "repeats", "dt",
)  # fmt: skip
SAME = 0.05  # ratios within 5% of 1 are shown as unchanged


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plot",
        help="draw the comparison plots (PNG and SVG) from a sweep CSV",
        description="Draw time per step against grid size (the chapter's Figures 22.5/22.6), throughput "
        "with fitted scaling exponents, speed against error, and work-group size against time, as PNG "
        "and SVG.",
    )
    p.add_argument("csv", help="a CSV written by clothbench sweep")
    p.add_argument("--out", help="folder for the plots (default: beside the CSV, named after it)")
    p.set_defaults(func=cmd_plot)

    c = subparsers.add_parser(
        "compare",
        help="ratios of ms/step between two sweep CSVs, row by matching row",
        description="For every row present in both sweeps (same backend, mode options, scene, grid and "
        "local size), the ratio B/A of the median ms per step: below 1, B is faster.",
    )
    c.add_argument("a", help="the baseline sweep CSV")
    c.add_argument("b", help="the sweep to compare with it")
    c.set_defaults(func=cmd_compare)


def cmd_plot(args) -> int:
    from clothbench.reports.plots import plot_sweep

    csv_path = Path(args.csv)
    out = Path(args.out) if args.out else csv_path.with_suffix("")
    if out == csv_path:  # a CSV without a suffix
        out = csv_path.with_name(csv_path.name + "-plots")
    report = plot_sweep(csv_path, out)
    for note in report.notes:
        print(note)
    if report.exponents:
        print("scaling: time per step ∝ particles^p")
        width = max(map(len, report.exponents))
        for label, p in report.exponents.items():
            print(f"  {label:<{width}}  p = {p:.2f}")
    for path in report.files:
        print(f"wrote {path}")
    return 0


def compare_rows(a_rows: list[dict], b_rows: list[dict]) -> tuple[list[dict], int, int]:
    """(matched rows with ratio B/A where both are ok, rows only in A, rows only in B)."""
    from clothbench.harness.sweep_csv import row_key

    a = {row_key(r): r for r in a_rows}
    b = {row_key(r): r for r in b_rows}
    matched = []
    for key, ra in a.items():
        rb = b.get(key)
        if rb is None:
            continue
        ratio = None
        if ra["status"] == "ok" and rb["status"] == "ok":
            try:
                ratio = float(rb["ms_median"]) / float(ra["ms_median"])
            except (ValueError, ZeroDivisionError):
                raise ClothbenchError(
                    f"ms_median {ra['ms_median']!r} / {rb['ms_median']!r} of {ra['backend']} n={ra['grid']} "
                    "is not a positive number: a row with status ok must have one"
                ) from None
        matched.append({"a": ra, "b": rb, "ratio": ratio})
    return matched, len(set(a) - set(b)), len(set(b) - set(a))


def geometric_mean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


def cmd_compare(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from clothbench.harness.sweep_csv import read_sweep

    a_rows = read_sweep(args.a, COMPARE_REQUIRED)
    b_rows = read_sweep(args.b, COMPARE_REQUIRED)
    matched, only_a, only_b = compare_rows(a_rows, b_rows)
    if not matched:
        raise ClothbenchError(
            f"{args.a} and {args.b} have no row in common (same backend, mode options, scene, grid, local size)"
        )
    console = Console()
    console.print(f"A: {args.a}  ({_machine(a_rows)})")
    console.print(f"B: {args.b}  ({_machine(b_rows)})")
    local = any(m["a"]["local_size"] for m in matched)
    table = Table(title="ms per step, B / A (below 1: B is faster)")
    for col in ("backend", "mode") + (("local",) if local else ()) + ("n", "A ms", "B ms", "B / A"):
        table.add_column(col, justify="left" if col in ("backend", "mode") else "right")
    per_backend: dict[str, list[float]] = {}
    for m in matched:
        ra, rb, ratio = m["a"], m["b"], m["ratio"]
        if ratio is None:
            shown = "[yellow]n/a[/yellow]"
        else:
            per_backend.setdefault(ra["backend"], []).append(ratio)
            colour = "green" if ratio < 1 - SAME else "red" if ratio > 1 + SAME else "default"
            shown = f"[{colour}]{ratio:.2f}[/{colour}]"
        lead = [ra["backend"], rb["mode"]] + ([ra["local_size"] or "auto"] if local else []) + [ra["grid"]]
        table.add_row(*lead, _ms(ra), _ms(rb), shown)
    console.print(table)
    for backend, ratios in per_backend.items():
        console.print(f"{backend}: geometric mean B/A {geometric_mean(ratios):.2f} over {len(ratios)} rows")
    everything = [r for rs in per_backend.values() for r in rs]
    if everything:
        console.print(f"all: geometric mean B/A {geometric_mean(everything):.2f} over {len(everything)} rows")
    not_ok = sum(1 for m in matched if m["ratio"] is None)
    if not_ok:
        console.print(f"{not_ok} matching rows are not ok in A or B (n/a): see their status and note columns")
    if only_a or only_b:
        console.print(f"rows only in A: {only_a}; only in B: {only_b} (not compared)")
    settings = {(m[s]["steps"], m[s]["repeats"], m[s]["dt"]) for m in matched for s in ("a", "b")}
    if len(settings) > 1:
        console.print(
            "note: the files were timed with different --steps/--repeat/--dt: "
            + "; ".join(f"{s} steps x {r} at dt {d}" for s, r, d in sorted(settings))
        )
    return 0


def _ms(row: dict) -> str:
    return f"{float(row['ms_median']):.3f}" if row["status"] == "ok" else row["status"]


def _machine(rows: list[dict]) -> str:
    def values(col):
        return sorted({r.get(col, "") for r in rows} - {""})

    parts = [", ".join(values("cpu")) or "unknown CPU"]
    if values("git_commit"):
        parts.append(f"commit {', '.join(values('git_commit'))}")
    stamps = values("timestamp")
    if stamps:
        parts.append(stamps[0][:16])
    return "; ".join(parts)
