"""The CSV of a study (`clothbench accuracy`, `clothbench stability`): SweepFile's
guarantees with the study's own columns. Each finished row is one complete line in a single
write, fsynced, the moment it is measured; an interrupted study keeps every finished row and
none half-written; --resume measures only the rows whose key the file lacks, after refusing
(in one line, before a byte changes) a file measured with other settings.

Cells are written as the csv module writes Python values (str(): floats in full, True/False,
'' for None), so a row read back and written again is the same line.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Iterable

from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import SweepFile


def cell(value) -> str:
    return "" if value is None else str(value)


def cells(row: dict) -> dict[str, str]:
    return {k: cell(v) for k, v in row.items()}


def _kind(annotation) -> str:
    return annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))


def _parse(text: str, kind: str):
    optional = "None" in kind
    kind = kind.replace("| None", "").replace("None |", "").strip()
    if text == "" and kind != "str":  # not measured (yet): None, NaN, 0, False
        return None if optional else {"float": float("nan"), "int": 0, "bool": False}.get(kind, text)
    if kind == "float":
        return float(text)
    if kind == "int":
        return int(float(text))
    if kind == "bool":
        return text == "True"
    return text


def from_cells(cls, row: dict[str, str]):
    """The dataclass `cls` (its fields annotated str, int, float, bool, X | None) of a row
    read back from a study CSV; columns that are not fields are ignored."""
    values = {f.name: _parse(row.get(f.name, ""), _kind(f.type)) for f in dataclasses.fields(cls) if f.init}
    return cls(**values)


class StudyFile(SweepFile):
    """A study's CSV open for appending. `key`: the columns that identify a row (--resume
    skips keys in the file); `settings`: column -> value every row in the file must have
    (the study's settings: another scene, grid or time would mix two studies in one file), a
    value that is a function of the row where it depends on the row's solver; `planned`: the
    keys this run measures, when a row outside them is refused too."""

    def __init__(
        self,
        path: str | os.PathLike,
        columns: Iterable[str],
        key: Iterable[str],
        settings: dict[str, str],
        what: str,
        resume: bool = False,
        retry: Iterable[str] = (),
        planned: Iterable[tuple] | None = None,
    ):
        self.key_columns, self.settings = tuple(key), dict(settings)
        self.planned = None if planned is None else set(planned)
        super().__init__(path, resume=resume, retry=retry, columns=tuple(columns), what=what)

    def _check_rows(self) -> None:
        for lineno, row in enumerate(self.rows, start=2):
            if self.planned is not None and self.key(row) not in self.planned:
                what = ", ".join(f"{c} {v}" for c, v in zip(self.key_columns, self.key(row)) if v)
                raise ClothbenchError(
                    f"{self.path}:{lineno} holds a row this run does not plan ({what}): resume with the "
                    "settings that wrote it, or write into a new --out"
                )
            for column, value in self.settings.items():
                value = value(row) if callable(value) else value
                if row.get(column, "") != value:
                    raise ClothbenchError(
                        f"{self.path}:{lineno} was measured with {column} = {row.get(column, '')!r}, this run has "
                        f"{value!r}: resume with the settings that wrote it, or write into a new --out"
                    )

    def _of_this_kind(self, header: tuple[str, ...]) -> bool:
        """A study's file, of any version, has its key columns (no other kind has them all)."""
        return set(self.key_columns) <= set(header)

    def key(self, row: dict[str, str]) -> tuple[str, ...]:
        return tuple(row.get(c, "") for c in self.key_columns)

    def keys(self) -> set[tuple[str, ...]]:
        return {self.key(r) for r in self.rows}


__all__ = ["StudyFile", "cell", "cells", "from_cells"]
