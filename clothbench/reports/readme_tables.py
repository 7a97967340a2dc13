"""README's performance tables, computed from one sweep CSV: so that every number and ratio
in README is the CSV's (tests/test_readme_tables.py regenerates them and looks for them in
README.md). `python -m clothbench.reports.readme_tables results/FILE.csv` prints them.

Ratios are taken within the one file, on the one machine that wrote it: the fastest
GPU-style backend (the registry's gpu_style) against the native `c` line, the fastest peer
and the machine's bound (`bound_ms`, docs/bounds.md)."""

from __future__ import annotations

import csv
import re
import sys

from clothbench.backends import BACKENDS, check_name
from clothbench.reports.tables import gpu_style
from clothbench.variant_names import TRANSFERS, base_mode


def _ok(rows: list[dict], grid: int) -> list[dict]:
    return [
        r
        for r in rows
        if r["status"] == "ok"
        and int(r["grid"]) == grid
        and r["solver"] == "verlet"
        and not r["local_size"]
        and r["precision"] == "f32"
    ]


def _fastest(rows: list[dict]) -> dict | None:
    return min(rows, key=lambda r: float(r["ms_median"])) if rows else None


def limits_rows(rows: list[dict]) -> list[dict]:
    """Per grid: the c line, the fastest GPU-style row and peer, and the fastest row's bound."""
    out = []
    for grid in sorted({int(r["grid"]) for r in rows}):
        here = _ok(rows, grid)
        native = _fastest([r for r in here if r["backend"] == "c"])
        best = _fastest([r for r in here if gpu_style(r["backend"])])
        peer = _fastest([r for r in here if r["peer"] == "true"])
        if native is None or best is None:
            continue
        ms = float(best["ms_median"])
        line = {
            "grid": grid,
            "c_ms": float(native["ms_median"]),
            "c_mode": native["mode"],
            "best": f"{best['backend']} {best['mode']}",
            "best_ms": ms,
            "vs_c": ms / float(native["ms_median"]),
            "peer": f"{peer['backend']} {peer['mode']}" if peer else "",
            "peer_ms": float(peer["ms_median"]) if peer else None,
            "peer_ratio": float(peer["ms_median"]) / ms if peer else None,
            "bound_ms": float(best["bound_ms"]) if best.get("bound_ms") else None,
            "bound_kind": best.get("bound_kind", ""),
        }
        fastest_any = _fastest(here)
        line["fastest_any"] = f"{fastest_any['backend']} {fastest_any['mode']}"
        line["fraction"] = float(fastest_any["bound_fraction"]) if fastest_any.get("bound_fraction") else None
        out.append(line)
    return out


def _x(value: float | None, digits: int = 2) -> str:
    return "–" if value is None else f"{value:.{digits}f}×"


def limits_markdown(rows: list[dict]) -> str:
    lines = [
        "| grid | c, ms | fastest GPU-style backend | ms | × c | fastest peer | ms | peer / it | bound, ms | fastest row's share of the bound |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in limits_rows(rows):
        peer_ms = "–" if r["peer_ms"] is None else f"{r['peer_ms']:.3f}"
        bound = "–" if r["bound_ms"] is None else f"{r['bound_ms']:.3f} ({r['bound_kind']})"
        # the fastest row's name only where it is not the GPU-style row already named
        who = "the same row" if r["fastest_any"] == r["best"] else r["fastest_any"]
        share = "–" if r["fraction"] is None else f"{100 * r['fraction']:.0f} % ({who})"
        lines.append(
            f"| {r['grid']}×{r['grid']} | {r['c_ms']:.3f} | {r['best']} | {r['best_ms']:.3f} | {_x(r['vs_c'])} | "
            f"{r['peer'] or '–'} | {peer_ms} | {_x(r['peer_ratio'], 1)} | {bound} | {share} |"
        )
    return "\n".join(lines)


def ms_markdown(rows: list[dict]) -> str:
    """ms/step of every backend and mode (f32 and f64, default local size) at every grid, in
    registry order, with each row's ratio to the c line at the largest grid it reached. The
    mode is the base mode: the shape tuned on each grid is in the CSV's mode column."""
    grids = sorted({int(r["grid"]) for r in rows if r["status"] == "ok"})
    order = list(BACKENDS)
    table: dict[tuple, dict[int, dict]] = {}
    for r in rows:
        if r["status"] != "ok" or r["solver"] != "verlet" or r["local_size"]:
            continue
        label = (order.index(check_name(r["backend"]).name), r["backend"], base_mode(r["mode"]))
        table.setdefault(label, {})[int(r["grid"])] = r
    head = " | ".join(f"{g}²" for g in grids)
    lines = [f"| backend | mode | {head} | × c at the largest |", "| --- | --- |" + " --- |" * (len(grids) + 1)]
    for (_, backend, mode), cells in sorted(table.items()):
        values = " | ".join(f"{float(cells[g]['ms_median']):.3f}" if g in cells else "–" for g in grids)
        largest = cells[max(cells)]
        vs_c = f"{float(largest['vs_c']):.2f}× ({max(cells)}²)" if largest.get("vs_c") else "–"
        lines.append(f"| {backend} | {mode} | {values} | {vs_c} |")
    return "\n".join(lines)


def runtime_cells(rows: list[dict]) -> dict[int, tuple[float, float]]:
    """Per grid: (ms, ms / the c fast row's ms) of the opencl fast resident row of one sweep."""
    out = {}
    for grid in sorted({int(r["grid"]) for r in rows}):
        here = _ok(rows, grid)
        native = _fastest([r for r in here if r["backend"] == "c" and r["strict"] == "false"])
        ocl = _fastest(
            [
                r
                for r in here
                if r["backend"] == "opencl"
                and r["strict"] == "false"
                and r["generic"] != "true"
                and (r["transfer"] or TRANSFERS["opencl"][0]) == TRANSFERS["opencl"][0]
            ]
        )
        if native and ocl:
            out[grid] = (float(ocl["ms_median"]), float(ocl["ms_median"]) / float(native["ms_median"]))
    return out


def short_driver(driver: str) -> str:
    """'PoCL 3.1+debian, LLVM 15.0.6' or 'Intel(R) OpenCL, driver 2026...' from a row's driver."""
    pocl, llvm = re.search(r"PoCL [\w.+-]+", driver), re.search(r"LLVM [\d.]+", driver)
    if pocl:
        return pocl.group(0) + (f", {llvm.group(0)}" if llvm else "")
    platform, _, rest = driver.partition(":")
    version = re.search(r"driver ([^;]+)", rest)
    return platform.strip() + (f", driver {version.group(1).strip()}" if version else "")


def runtimes_markdown(sweeps: dict[str, list[dict]]) -> str:
    """One line per OpenCL runtime (a sweep each, with its own c line): opencl fast ms/step and
    its ratio to c fast at every grid, and the driver that ran it."""
    cells = {name: runtime_cells(rows) for name, rows in sweeps.items()}
    grids = sorted({g for c in cells.values() for g in c})
    lines = [f"| runtime | driver | {' | '.join(f'{g}²' for g in grids)} |", "| --- | --- |" + " --- |" * len(grids)]
    for name, rows in sweeps.items():
        drivers = sorted({short_driver(r["driver"]) for r in rows if r["backend"] == "opencl" and r["status"] == "ok"})
        values = " | ".join(
            f"{cells[name][g][0]:.3f} ({cells[name][g][1]:.2f}×)" if g in cells[name] else "–" for g in grids
        )
        lines.append(f"| {name} | {'; '.join(drivers)} | {values} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if not argv or argv[0].startswith("-"):
        print(
            "usage: python -m clothbench.reports.readme_tables SWEEP.csv [NAME=RUNTIME_SWEEP.csv ...]", file=sys.stderr
        )
        return 2
    rows = list(csv.DictReader(open(argv[0], newline="")))
    print(limits_markdown(rows), end="\n\n")
    print(ms_markdown(rows), end="\n\n")
    if argv[1:]:
        sweeps = {}
        for spec in argv[1:]:
            name, _, path = spec.partition("=")
            sweeps[name] = list(csv.DictReader(open(path, newline="")))
        print(runtimes_markdown(sweeps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
