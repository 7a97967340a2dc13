"""results/c-planes/README.md against its two committed sweeps: every figure of the table is
its row's ms_median (or bound_fraction) in the file it names, and the ratio is theirs."""

from __future__ import annotations

import csv
from pathlib import Path

RESULTS = Path(__file__).parent.parent / "results" / "c-planes"


def rows(name: str) -> dict:
    with (RESULTS / f"zen4-2026-12-05-{name}.csv").open() as f:
        return {(r["grid"], r["mode"].removesuffix("/threads=2")): r for r in csv.DictReader(f)}


def test_every_figure_of_the_table_is_the_sweeps():
    before, after = rows("before"), rows("after")
    table = []
    for line in (RESULTS / "README.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 6 and cells[0].isdigit():
            table.append(cells)
    assert len(table) == len(before) == len(after) == 6
    for grid, mode, old, new, ratio, fractions in table:
        b, a = before[grid, mode], after[grid, mode]
        assert float(old) == round(float(b["ms_median"]), 3) and float(new) == round(float(a["ms_median"]), 3)
        assert float(ratio) == round(float(b["ms_median"]) / float(a["ms_median"]), 2), (grid, mode)
        shares = [float(x) for x in fractions.split(" → ")]
        assert shares == [round(float(b["bound_fraction"]), 2), round(float(a["bound_fraction"]), 2)], (grid, mode)
        assert a["err_rms_m"] == b["err_rms_m"], "the same scene, steps and bits: the same error"
        assert "quiet" in a["machine_state"] and "quiet" in b["machine_state"]
