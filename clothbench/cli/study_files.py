"""The CSVs of `clothbench accuracy` and `clothbench stability` as they are measured
(harness/study_csv.py): each finished row lands in the file at once, --resume measures only
the rows the file lacks, --retry-failed measures its failed ones again.

Accuracy's fitted columns (order, order_points, in_fit: analysis/convergence.py's FITTED,
fitted over a line's rows) are left empty in a row written as it is measured; when the study
completes they are computed from every row of the file, the ones a resumed run found there and
the ones it measured, and the file is rewritten once (a single rename) in the plan's order.
docs/accuracy.md says so. `clothbench report` of a file whose study did not finish fits them
itself, the same way (reports/results_files.py).
"""

from __future__ import annotations

import sys

from clothbench.harness.study_csv import StudyFile, cell, cells, from_cells
from clothbench.model.solver import ITERATIVE

ACCURACY_KEY = ("backend", "label", "solver", "pbd_method", "iterations", "substeps", "dt")
ACCURACY_RETRY = ("error", "failed", "crashed", "timeout")  # a status's first word
STABILITY_KEY = ("backend", "label", "solver", "pbd_method", "iterations", "kind", "stiffness")


def add_resume_args(p, retry_help: str) -> None:
    p.add_argument(
        "--resume",
        action="store_true",
        help="measure only the rows --out lacks (after an interruption); a file measured with other "
        "settings is refused",
    )
    p.add_argument("--retry-failed", action="store_true", help=retry_help)


def say_interrupted(f: StudyFile) -> None:
    """What an interrupted study leaves, on stderr, before it exits 130."""
    print(
        f"{len(f.rows)} rows are in {f.path}; run the same command with --resume to measure the rest", file=sys.stderr
    )


def _pbd_cells(solver, substeps: bool = True) -> dict[str, str]:
    pbd, iterative = solver.name == "pbd", solver.name in ITERATIVE
    d = {"pbd_method": solver.method if pbd else "", "iterations": cell(solver.iterations) if iterative else ""}
    if substeps:
        d["substeps"] = cell(solver.substeps) if iterative else ""
    return d


def accuracy_key(v, solver) -> tuple[str, ...]:
    d = {"backend": v.backend, "label": v.name, "solver": solver.name, "dt": cell(solver.dt), **_pbd_cells(solver)}
    return tuple(d[c] for c in ACCURACY_KEY)


def accuracy_file(path, planned, scene, time_s, verlet_start: str, pbd_start: str, resume: bool, retry: bool):
    """The accuracy CSV, open for appending, of `planned` (variant, solver) rows."""
    from clothbench.analysis.convergence import AccuracyRow

    settings = {
        "scene": scene.name,
        "grid": cell(scene.grid),
        "damping": cell(scene.damping),
        "time_s": cell(time_s),
        "stiffness": cell(scene.stiffness),
        "start": lambda row: pbd_start if row.get("solver") in ITERATIVE else verlet_start,
    }
    return StudyFile(
        path,
        tuple(f.name for f in _fields(AccuracyRow)),
        ACCURACY_KEY,
        settings,
        "accuracy",
        resume=resume or retry,
        retry=ACCURACY_RETRY if retry else (),
        planned={accuracy_key(v, s) for v, s in planned},
    )


def early_cells(row) -> dict[str, str]:
    """A row as written the moment it is measured: its fitted columns empty."""
    from clothbench.analysis.convergence import FITTED

    return {**cells(row.as_dict()), **{c: "" for c in FITTED}}


def finish_accuracy(f: StudyFile, planned, measured: list) -> list:
    """Every planned row (measured now, or read back from the file), in the plan's order,
    with the derived columns fitted over them; the file rewritten with them."""
    from clothbench.analysis.convergence import AccuracyRow, fit_orders

    by_key = {f.key(r): r for r in f.rows}
    new = {f.key(cells(r.as_dict())): r for r in measured}
    rows = []
    for v, solver in planned:
        key = accuracy_key(v, solver)
        if key in new:
            rows.append(new[key])
        elif key in by_key:
            rows.append(from_cells(AccuracyRow, by_key[key]))
    fit_orders(rows)
    f.rewrite([cells(r.as_dict()) for r in rows])
    return rows


def stability_key(v, kind: str, stiffness: float) -> tuple[str, ...]:
    d = {
        "backend": v.backend,
        "label": v.name,
        "solver": v.solver.name,
        "kind": kind,
        "stiffness": cell(stiffness),
        **_pbd_cells(v.solver, substeps=False),
    }
    return tuple(d[c] for c in STABILITY_KEY)


STABILITY_COLUMNS_EXTRA = ("ratio", "ratio_to_flat", "stable_at_60hz")  # StabilityRow.as_dict's


def stability_file(path, cases, grid: int, steps: int, damping: float, cap: float, resume: bool):
    """The stability CSV, open for appending, of `cases` (variant, scene kind, k). A case
    whose bisection failed is printed and not written, so --resume measures it again."""
    from clothbench.analysis.stability import StabilityRow

    settings = {
        "grid": cell(grid),
        "steps": cell(steps),
        "damping": cell(damping),
        "cap": lambda row: cell(cap) if row.get("solver") in ITERATIVE else "",
    }
    columns = tuple(f.name for f in _fields(StabilityRow)) + STABILITY_COLUMNS_EXTRA
    return StudyFile(
        path,
        columns,
        STABILITY_KEY,
        settings,
        "stability",
        resume=resume,
        planned={stability_key(*c) for c in cases},
    )


def finish_stability(f: StudyFile, cases, measured: dict) -> list:
    """Every case's row (measured now, or read back), in the plan's order; the file
    rewritten in that order, so a resumed study's file is the uninterrupted one's."""
    from clothbench.analysis.stability import StabilityRow

    by_key = {f.key(r): r for r in f.rows}
    rows = []
    for case in cases:
        key = stability_key(*case)
        if key in measured:
            rows.append(measured[key])
        elif key in by_key:
            rows.append(from_cells(StabilityRow, by_key[key]))
    f.rewrite([cells(r.as_dict()) for r in rows])
    return rows


def _fields(cls):
    import dataclasses

    return dataclasses.fields(cls)


__all__ = [
    "add_resume_args",
    "say_interrupted",
    "accuracy_key",
    "accuracy_file",
    "early_cells",
    "finish_accuracy",
    "stability_key",
    "stability_file",
    "finish_stability",
]
