"""The results CSVs clothbench writes, recognised by their columns, and read back into the
rows the analysis made them from: a sweep (harness/sweep_csv.py), an accuracy run and its
PBD artefacts (analysis/convergence.py, analysis/artefacts.py), a stability run
(analysis/stability.py), an energy study (analysis/energy_study.py), a PBD study
(analysis/pbd_study.py). Everything a report needs is checked here, before any figure is
drawn: a file that is none of these is one line saying what it is instead."""

from __future__ import annotations

import csv
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from clothbench.analysis.artefacts import ArtefactRow
from clothbench.analysis.convergence import FITTED, AccuracyResult, AccuracyRow, fit_orders
from clothbench.analysis.energy_study import EnergyRow
from clothbench.analysis.pbd_study import PbdStudyRow
from clothbench.analysis.stability import StabilityRow
from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import read_sweep
from clothbench.reports import plots


SWEEP, ACCURACY, STABILITY, PBD_STUDY, ENERGY, ARTEFACTS = (
    "sweep",
    "accuracy",
    "stability",
    "pbd-study",
    "energy",
    "artefacts",
)


@dataclass(frozen=True)
class Kind:
    """A kind of results CSV: what makes it one and what its rows are read into."""

    name: str
    what: str  # the kind in a sentence: the page's list of inputs, a refusal's words
    row_class: type | None  # the analysis row each line was written from; None: a sweep's rows stay dicts
    read_by_figures: tuple[str, ...]  # columns its figures read beside the row class's required ones


# Every kind, in the order the report's page puts their sections (the chapter's figures first;
# reports/html.py's SECTIONS draws each). A file must have a kind's columns (REQUIRED): for the
# analysis rows every field without a default and what their figures read; for a sweep, what
# reports/plots.py reads.
KINDS = (
    Kind(SWEEP, "a sweep (clothbench sweep)", None, plots.REQUIRED),
    Kind(
        ACCURACY,
        "an accuracy run (clothbench accuracy)",
        AccuracyRow,
        ("solver", "status", "ms_per_sim_s", "disc_rms", "impl_rms", "order"),
    ),
    Kind(
        STABILITY,
        "a stability run (clothbench stability)",
        StabilityRow,
        ("solver", "pbd_method", "capped", "cap", "at_60hz"),
    ),
    Kind(
        PBD_STUDY,
        "a PBD study (clothbench pbd-study)",
        PbdStudyRow,
        ("status", "rms", "max", "ms_numpy", "ms_opencl"),
    ),
    Kind(
        ENERGY,
        "an energy study (clothbench energy)",
        EnergyRow,
        ("worst_drift_j", "band_j", "max_rise_j", "rounding_j"),
    ),
    Kind(ARTEFACTS, "PBD artefacts (clothbench accuracy --artefacts)", ArtefactRow, ()),
)
KIND = {k.name: k for k in KINDS}


def _required(kind: Kind) -> tuple[str, ...]:
    if kind.row_class is None:
        return kind.read_by_figures
    no_default = [f.name for f in dataclasses.fields(kind.row_class) if f.default is dataclasses.MISSING]
    return tuple(dict.fromkeys(no_default + list(kind.read_by_figures)))


REQUIRED = {kind.name: _required(kind) for kind in KINDS}


@dataclass
class ResultsFile:
    path: Path
    kind: str
    rows: list[dict[str, str]]  # as read, every value a string

    @property
    def name(self) -> str:
        return str(self.path)

    def ok_rows(self) -> list[dict[str, str]]:
        return [r for r in self.rows if r.get("status", "ok") == "ok"]


def recognise(path, header) -> str:
    """The kind of results CSV `path` is, by its columns (`header`)."""
    header = set(header)
    for kind, required in REQUIRED.items():
        if header.issuperset(required):
            return kind
    # the kind it is closest to, when it is clearly meant as one (half its columns or more)
    kind, required = max(REQUIRED.items(), key=lambda kv: len(header & set(kv[1])) / len(kv[1]))
    if len(header & set(required)) >= len(required) / 2:
        missing = [c for c in required if c not in header]
        raise ClothbenchError(f"{path} looks like {KIND[kind].what} but lacks column(s) {', '.join(missing)}")
    shown = ", ".join(sorted(header)[:6]) + (", ..." if len(header) > 6 else "")
    kinds = [k.name for k in KINDS]
    raise ClothbenchError(
        f"{path} is not a clothbench results CSV (a {', '.join(kinds[:-1])} or {kinds[-1]} CSV); its columns: {shown}"
    )


def read_results(path) -> ResultsFile:
    """Recognise `path` and read its rows, checking every value the report converts."""
    path = Path(path)
    try:
        rows = read_sweep(path)  # the plain CSV reader: says what is no file, no text, or empty
    except csv.Error as e:
        raise ClothbenchError(f"{path} is not a CSV ({e})") from None
    # read_sweep has read it as text: the header alone (rows or none) says what it is
    header = rows[0].keys() if rows else next(csv.reader([path.read_text(encoding="utf-8").partition("\n")[0]]))
    kind = recognise(path, header)
    if not rows:
        raise ClothbenchError(f"{path} has a header but no rows: nothing to report")
    result = ResultsFile(path, kind, rows)
    if kind == SWEEP:
        if not plots.load(path)[0]:  # load() also says which row has a value that is no number
            raise ClothbenchError(f"{path} has no row with status ok: nothing to report")
    else:
        analysis_rows(result)  # converts every row: a bad value is said now, not mid-report
    return result


def _number(text: str, path: Path, lineno: int, column: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise ClothbenchError(f"{path}:{lineno}: column {column} is {text!r}, not a number") from None


def _convert(text: str, annotation: str, path: Path, lineno: int, column: str):
    """A CSV cell back to the type of the dataclass field it was written from."""
    optional = "None" in annotation
    if text == "" and optional:
        return None
    if annotation.startswith("bool"):
        if text.lower() not in ("true", "false"):
            raise ClothbenchError(f"{path}:{lineno}: column {column} is {text!r}, not True or False")
        return text.lower() == "true"
    if annotation.startswith("int"):
        return int(_number(text, path, lineno, column))
    if annotation.startswith("float"):
        return math.nan if text in ("", "nan") else _number(text, path, lineno, column)
    return text


def unfinished(result: ResultsFile) -> bool:
    """Whether `result` is an accuracy study that did not finish: its rows are written as they
    are measured, with the columns fitted over every row (FITTED) left empty until it ends."""
    return result.kind == ACCURACY and any(r.get(c) == "" for r in result.rows for c in FITTED)


def analysis_rows(result: ResultsFile) -> list:
    """The analysis rows (its kind's row_class) the file was written from; columns
    the file lacks keep their defaults, columns the class lacks (ratio, ...) are derived there.
    An unfinished accuracy study's orders are fitted here over the rows it has, as its end
    would have fitted them over all of its rows."""
    cls = KIND[result.kind].row_class
    refit = unfinished(result)
    fields = [f for f in dataclasses.fields(cls) if f.init and not (refit and f.name in FITTED)]
    out = []
    for lineno, r in enumerate(result.rows, start=2):
        values = {f.name: _convert(r[f.name], str(f.type), result.path, lineno, f.name) for f in fields if f.name in r}
        out.append(cls(**values))
    if refit:
        fit_orders(out)
    return out


def accuracy_result(result: ResultsFile) -> AccuracyResult:
    """What the accuracy figures draw, from the CSV. The CSV does not keep the references or
    the converged models' distances, so the figure lacks those lines."""
    return AccuracyResult(rows=analysis_rows(result), reference=None)


__all__ = [
    "Kind",
    "KINDS",
    "KIND",
    "ResultsFile",
    "REQUIRED",
    "recognise",
    "read_results",
    "unfinished",
    "analysis_rows",
    "accuracy_result",
]
