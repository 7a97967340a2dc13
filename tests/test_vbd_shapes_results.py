"""results/vbd-shapes/README.md against its committed CSV (tools/vbd-shapes): every figure of
its table is the fastest round of that case in the CSV, the bold one is the fastest shape of
its backend and device at that grid, and the ratios the README and docs/vbd.md state hold."""

from __future__ import annotations

import csv
import re
from collections import defaultdict
from pathlib import Path

RESULTS = Path(__file__).parent.parent / "results" / "vbd-shapes"
README = RESULTS / "README.md"
CSV = RESULTS / "zen4-2026-12-05.csv"
GRIDS = (64, 128, 256)
# the README's first column: (backend, what the row's driver names)
DEVICES = {
    "c": ("c", ""),
    "opencl, Intel 1:0": ("opencl", "Intel"),
    "opencl, PoCL 0:0": ("opencl", "PoCL"),
    "glsl-compute, llvmpipe": ("glsl-compute", ""),
}


def fastest() -> dict:
    """(backend, driver word, shape, grid, arithmetic) -> the fastest round's ms per step."""
    best: dict = defaultdict(lambda: float("inf"))
    with CSV.open() as f:
        for row in csv.DictReader(f):
            word = "Intel" if "Intel" in row["driver"] else "PoCL" if "PoCL" in row["driver"] else ""
            shape = row["shape"].split("/", 1)[1] if row["shape"].startswith("ls=") else row["shape"]
            key = (row["backend"], word, shape, int(row["grid"]), row["arithmetic"])
            best[key] = min(best[key], float(row["ms_per_step"]))
    return dict(best)


def table_rows() -> list[tuple[str, str, list[str]]]:
    """(device column, shape, the three grid cells) of each row of the README's table."""
    rows = []
    for line in README.read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 5 and cells[0] in DEVICES:
            rows.append((cells[0], cells[1], cells[2:]))
    return rows


def test_every_figure_of_the_table_is_the_csvs_fastest_round_and_bold_marks_the_fastest_shape():
    best, rows = fastest(), table_rows()
    assert len(rows) == 10, "the table lost or gained a row"
    for device, shape, cells in rows:
        backend, word = DEVICES[device]
        for grid, cell in zip(GRIDS, cells):
            m = re.fullmatch(r"(\*\*)?([\d.]+)(\*\*)?(?: \(([\d.]+)\))?", cell)
            assert m, cell
            assert float(m.group(2)) == round(best[backend, word, shape, grid, "fast"], 2), (device, shape, grid)
            if m.group(4):  # the strict figure beside it
                assert float(m.group(4)) == round(best[backend, word, shape, grid, "strict"], 2), (device, shape)
            mine = {s: ms for (b, w, s, g, a), ms in best.items() if (b, w, g, a) == (backend, word, grid, "fast")}
            if len(mine) > 1:  # bold: the backend's fastest shape here
                assert bool(m.group(1)) == (min(mine, key=mine.get) == shape), (device, shape, grid)


def test_the_planes_shapes_beat_gather_by_what_the_readme_says():
    best = fastest()
    for word, low, high in (("Intel", 1.4, 2.9), ("PoCL", 2.2, 3.4)):
        for grid in GRIDS:
            for arithmetic in ("fast", "strict"):
                gather = best["opencl", word, "gather", grid, arithmetic]
                planes = min(
                    v
                    for k, v in best.items()
                    if k[:2] == ("opencl", word) and k[3:] == (grid, arithmetic) and k[2].startswith("planes/")
                )
                assert low <= gather / planes <= high, (word, grid, arithmetic, gather / planes)
    # with them OpenCL VBD is within 1.3x of c's step at 256^2 on Intel's runtime (gather: 3.6x)
    c = best["c", "", "threads=2", 256, "fast"]
    assert (
        best["opencl", "Intel", "planes/v16", 256, "fast"] / c
        < 1.3
        < 3.5
        < best["opencl", "Intel", "gather", 256, "fast"] / c
    )


def test_the_bound_sweep_holds_the_shares_the_readme_gives():
    rows = {
        (r["backend"], r["grid"], r["strict"]): r
        for r in csv.DictReader((RESULTS / "bound-sweep-zen4-2026-12-05.csv").open())
    }
    share = {key: round(float(r["bound_fraction"]), 2) for key, r in rows.items()}
    assert share["c", "256", "false"] == 0.22 and share["c", "256", "true"] == 0.21
    assert (share["c", "128", "false"], share["c", "128", "true"]) == (0.17, 0.15)
    assert (share["opencl", "256", "false"], share["opencl", "128", "false"]) == (0.11, 0.09)
    assert all(r["bound_kind"] == "arithmetic" and r["busy"] != "true" for r in rows.values())
    assert round(float(rows["c", "256", "false"]["bound_ms"]), 2) == 1.22
