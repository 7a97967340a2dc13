"""The sweep's CSV: its columns and what each means, one row per key, and the file that
keeps every finished row.

Nothing measured is lost. Each row is written to the CSV as one complete line in a single
write, then flushed to the disk (fsync), the moment it is measured; an interrupted sweep
keeps every finished row, and a resumed one measures only the rows whose key is not in the
file yet, after dropping a half-written last line if a crash left one.
"""

from __future__ import annotations

import csv
import io
import math
import os
import sys
from pathlib import Path
from typing import Iterable

from clothbench.errors import ClothbenchError
from clothbench.variant_names import transfers_help

BUDGET_NOTE = "time budget"  # how the note of a row its per-row time budget shortened begins

# The columns of the machine's limits (harness/bounds.py), with what each means.
BOUND_COLUMN_DOCS = {
    "bound_ms": "the machine's lower bound on ms per step for this scene, solver and precision: max(memory, "
    "arithmetic), measured in this run (docs/bounds.md); verlet: the step's state streamed once and its springs, "
    "particles and colliders' operations; pbd-jacobi, pbd-coloured, vbd: the state streamed once a step, each "
    "substep's iterations (per directed constraint, per constraint, per free particle and its springs) with their "
    "arrays streamed again each iteration only where they exceed the caches; empty where there is no C compiler "
    "or the sweep was told --no-bound",
    "bound_kind": "which limit sets bound_ms: memory (bytes at the streaming rate) or arithmetic (the busiest unit)",
    "bound_fraction": "bound_ms / ms_median: the fraction of the machine's bound achieved (1 = at the bound)",
}
MACHINE_COLUMN_DOCS = {
    "bandwidth_gb_s": "best streaming rate measured this run (max of triad and copy, STREAM's byte count, GB/s)",
    "triad_gb_s": "STREAM triad a = b + s*c, all threads, 3 arrays counted, fastest 2 MiB chunks (GB/s)",
    "copy_gb_s": "STREAM scale a = s*b (a copy's traffic), all threads, 2 arrays counted (GB/s)",
    "triad_pass_gb_s": "the triad timed over whole passes, as STREAM reports it (GB/s; not used by the bound)",
    "sqrt_gops": "float32 sqrt throughput, all threads (1e9/s)",
    "div_gops": "float32 division throughput, all threads (1e9/s)",
    "fp_gops": "float32 add/multiply throughput, all threads (1e9/s)",
    "rsqrt_gops": "float32 fast reciprocal square root (estimate + Newton step) throughput (1e9/s)",
    "bound_threads": "threads the limits were measured with",
}

# Every column, in file order, with what it means. COLUMNS is the header.
COLUMN_DOCS: dict[str, str] = {
    "backend": "registry name (see `clothbench backends`)",
    "peer": "true for a peer system (taichi, warp, numba), false for clothbench's own kernels",
    "solver": "the integrator: 'verlet' (mass-spring, docs/semantics.md), 'pbd' (XPBD, docs/pbd.md) or 'vbd' "
    "(implicit Euler by Vertex Block Descent, docs/vbd.md)",
    "pbd_method": "pbd only: 'jacobi' or 'coloured' (Gauss-Seidel over 12 independent batches)",
    "iterations": "pbd: constraint passes per substep; vbd: sweeps over its 4 colours per substep",
    "substeps": "pbd and vbd only: substeps per step",
    "mode": "the backend's own name for the settings that change speed or results",
    "precision": "working precision: f32, or f64 (the reference precision; runs on: {f64_backends})",
    "strict": "the strict option: bit-exact with numpy f32 (no FMA contraction, no fast math)",
    "transfer": f"transfer mode ({transfers_help(' ', ', ')}); empty = the backend's default",
    "local_size": "work-group / block size; empty = the runtime chooses",
    "generic": "true = one kernel for every scene; false = the backend's default (specialised where it has one)",
    "specialised_speedup": "generic rows only: ms/step of this generic kernel / ms/step of the same backend's specialised kernel (same grid, mode and sweep)",
    "device": "what the work ran on, as the driver names it",
    "driver": "the runtime or compiler, with its version, that ran the work (which of several OpenCL runtimes, "
    "the GL renderer, the C compiler)",
    "scene": "scene name",
    "mesh_triangles": "triangles of the scene's [[mesh]] colliders as the step sees them (after the clean-up rules "
    "of colliders/mesh.py); sweep --mesh-triangles sets each built-in shape to the subdivision nearest (by ratio) the count "
    "asked; empty = no meshes",
    "mesh_collision": "how the closest mesh triangle is found: naive (every triangle, in index order) or "
    "accelerated (a host-built BVH traversed in the kernel), the same bits (docs/semantics.md); empty = no meshes",
    "motion": "on = the scene's colliders move and its pins follow a body as the file says; off = the same scene "
    "with every motion stopped (sweep --motion on,off: the cost of motion, docs/scenes.md); empty = the scene has "
    "no motion",
    "self_collision": 'on = the scene\'s [self_collision] pass runs (docs/semantics.md, "Self-collision"); off = '
    "the same scene without the table (sweep --self-collision on,off: the cost of the pass); empty = the scene has "
    "no [self_collision]",
    "grid": "n, particles per side",
    "particles": "n*n",
    "springs": "springs counted per particle, each seen from both ends (the chapter's count)",
    "dt": "time step (s)",
    "steps": "steps per timed chunk (S)",
    "repeats": "timed chunks (R): the timed run simulates S*R steps after the warm-up",
    "simulated_s": "simulated time of the timed run, S*R*dt (s)",
    "budget_s": "the per-row time budget (--row-budget, s) the row ran under; where the run would not fit, "
    "steps and repeats are what ran (fewer than asked) and the note says so",
    "status": "ok | unstable (blew up: NaN/Inf or runaway) | failed (raised) | crashed (its worker process died: "
    "a signal, an abort, out of memory) | timeout (ran past --row-timeout); measurements are empty unless ok",
    "note": "why a row is unstable or failed (one line)",
    "ms_median": "median over the R chunks of wall-clock ms per step",
    "ms_min": "fastest chunk, ms per step",
    "ms_max": "slowest chunk, ms per step",
    "ms_iqr": "inter-quartile range of the per-chunk ms per step",
    "chunk_ms": "every chunk's ms per step, space-separated, in the order measured (R values; "
    "compare's confidence intervals are drawn from them)",
    "device_ms_median": "median over the R chunks of the device's own ms per step (the clock device_timer names), "
    "where the backend has one it trusts; the wall clock's ms_median also holds the host's launches and the "
    "synchronize (docs/timing.md)",
    "device_timer": "the device clock of device_ms_median: cuda-events, gl-timer-query (not on llvmpipe, whose "
    "timer queries are the host's clock), opencl-events (kernels only); empty = none (files older than the column "
    "lack it)",
    "particles_per_s": "particles * 1000 / ms_median",
    "ms_per_sim_s": "compute ms per simulated second, ms_median / dt (1000 = real time)",
    "warmup_s": "build (kernel compile) plus warm-up steps, not timed (s)",
    "finite": "the final state is finite",
    "max_penetration_m": "deepest penetration of a particle into a collider at the end (m)",
    "self_pairs": 'pairs of particles that are not neighbours (docs/semantics.md, "Self-collision") closer than '
    "the scene's [self_collision] thickness at the end; empty = the scene has no [self_collision]",
    "self_min_distance_m": "the smallest distance between two such particles at the end (m), capped at the "
    "search's cell size; empty = the scene has no [self_collision]",
    "err_rms_m": "RMS distance of the final positions to the numpy float64 run of the same scene and S*R steps (m)",
    "err_max_m": "largest such distance (m)",
    **BOUND_COLUMN_DOCS,
    "vs_c": "ms_median / ms_median of the c backend's row of the same grid, solver, precision and strict flag in "
    "this file (the native CPU line; > 1 is slower than it)",
    "timed_region": "what the clock saw: 'steps' (upload and readback outside) or 'steps+transfers' (per-step transfer mode)",
    "busy": "true: other processes used half a core or more, or the hypervisor stole 5 %, while the row ran "
    "(clothbench/machine_load.py); false: quiet; empty: not measured or too short a run to tell",
    "load": "the machine's load while the row ran: other processes' cores and steal, over how long; the CPUs "
    "this process may run on (its affinity) and their clock where readable",
    "machine_state": "`clothbench machine`'s verdict at the sweep's start, once for every row of that run: "
    "'quiet (...)', or what made the machine unfit (busy, a frequency governor); empty on a cluster",
    **MACHINE_COLUMN_DOCS,
    "cpu": "CPU model",
    "cores": "logical CPUs available to the process",
    "host": "the machine the row ran on (its host name; a Dask worker's for a sweep on a cluster)",
    "python": "Python implementation and version",
    "packages": "versions of the packages that can change a result (name=version ...)",
    "env": "environment variables set when measured that change how a library or driver runs "
    "(threads, device choice, JIT settings: OMP_*, NUMBA_*, LP_*, POCL_*, CUDA_VISIBLE_DEVICES, ...), "
    "NAME=value in name order, values shell-quoted",
    "git_commit": "clothbench commit, '+dirty' if tracked files had changes; an installed copy's is the commit "
    "its wheel was built from, with its version: 'abc123456789 (version 0.1.0)'",
    "timestamp": "when the row was measured (UTC, ISO 8601)",
}
COLUMNS: tuple[str, ...] = tuple(COLUMN_DOCS)
# What identifies a row: a sweep measures each key once, and --resume skips keys in the file.
KEY_COLUMNS = (
    "backend",
    "solver",
    "pbd_method",
    "scene",
    "grid",
    "precision",
    "strict",
    "transfer",
    "generic",
    "local_size",
    "mesh_triangles",
    "mesh_collision",
    "motion",
    "self_collision",
)
# The key columns a file written before they were added lacks: row_key reads each as "" there,
# the value every row of such a file had (no PBD method, mesh, motion or self-collision).
KEY_COLUMNS_ADDED_LATER = ("pbd_method", "mesh_triangles", "mesh_collision", "motion", "self_collision")
MEASUREMENT_COLUMNS = (
    "ms_median",
    "ms_min",
    "ms_max",
    "ms_iqr",
    "chunk_ms",
    "device_ms_median",
    "device_timer",
    "particles_per_s",
    "ms_per_sim_s",
    "warmup_s",
    "finite",
    "max_penetration_m",
    "self_pairs",
    "self_min_distance_m",
    "err_rms_m",
    "err_max_m",
)
NOTE_MAX = 300  # characters
RETRY_STATUSES = ("failed", "crashed", "timeout")  # what --retry-failed measures again


def fmt(value) -> str:
    """A CSV cell: '' for None, true/false for booleans, 6 significant digits for floats."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else ""
    return str(value)


def fmt_chunks(values: Iterable[float]) -> str:
    """The chunk_ms cell: each value as fmt writes it, space-separated."""
    return " ".join(fmt(float(v)) for v in values)


def parse_chunks(cell: str) -> list[float]:
    """The values of a chunk_ms cell ([] for an empty one, as in CSVs older than the column);
    ValueError if a value is not a number."""
    return [float(v) for v in cell.split()]


def one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= NOTE_MAX else text[: NOTE_MAX - 1] + "…"


def row_key(row: dict[str, str]) -> tuple[str, ...]:
    return tuple(row.get(c, "") for c in KEY_COLUMNS)


def csv_line(values: Iterable[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(values))
    return buf.getvalue()


class SweepFile:
    """The sweep CSV, open for appending: one complete line per write, fsynced.

    Holds an exclusive lock while open, so two sweeps never interleave rows in one file.
    `columns` and `what` make it the file of another command (accuracy, stability: the
    study files of harness/study_csv.py); a row is retried when its status's first word
    (before any ':') is in `retry`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        resume: bool = False,
        retry: Iterable[str] = (),
        columns: tuple[str, ...] = COLUMNS,
        what: str = "sweep",
    ):
        self.path = Path(path)
        self.retry = frozenset(retry)
        self.columns, self.what = tuple(columns), what
        self.rows: list[dict[str, str]] = []  # rows already in the file
        self.dropped_bytes = 0  # a partial last line removed on resume
        if self.path.is_dir():
            raise ClothbenchError(f"--out {self.path} is a directory: name a CSV file")
        if not resume and self.path.exists() and self.path.stat().st_size > 0:
            raise ClothbenchError(
                f"{self.path} already exists: pass --resume to measure only the rows it lacks, or choose another --out"
            )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        except OSError as e:
            raise ClothbenchError(f"cannot write {self.path}: {e.strerror}") from None
        try:
            self._lock()
            self._load()
            self._check_rows()
            if self.retry and any(self._retried(r) for r in self.rows):
                self._drop_retried()
        except BaseException:
            os.close(self.fd)
            raise

    def _check_rows(self) -> None:
        """Refuse (before a byte changes) rows this run cannot add to; none for a sweep, whose
        run_sweep checks the settings of the rows it resumes itself."""

    def _retried(self, row: dict[str, str]) -> bool:
        return row.get("status", "").split(":", 1)[0].strip() in self.retry

    def _drop_retried(self) -> None:
        """--retry-failed: the file without its failed/crashed/timeout rows, replaced in one
        rename (a crash leaves the old file or the new one, never half of either)."""
        keep = [r for r in self.rows if not self._retried(r)]
        self.rewrite(keep)

    def rewrite(self, rows: list[dict[str, str]]) -> None:
        """The file replaced by `rows` (header first) in one rename, and open again for appending."""
        columns = self.columns
        tmp = self.path.with_name(self.path.name + ".retry-tmp")
        text = csv_line(columns) + "".join(csv_line(r.get(c, "") for c in columns) for r in rows)
        with open(tmp, "w", encoding="utf-8", newline="") as t:
            t.write(text)
            t.flush()
            os.fsync(t.fileno())
        os.replace(tmp, self.path)
        os.close(self.fd)
        self.fd = os.open(self.path, os.O_RDWR | os.O_APPEND)
        self._lock()
        self.rows = list(rows)

    def _lock(self) -> None:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock, the rest still holds
            return
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ClothbenchError(
                f"another clothbench {self.what} is writing {self.path}: wait for it, or choose another --out"
            ) from None

    def _load(self) -> None:
        data = self._read_all()
        header = csv_line(self.columns).encode()
        if not data or (b"\n" not in data and header.startswith(data)):  # new, or a torn header
            os.ftruncate(self.fd, 0)
            self._write(header.decode())
            return
        self._check_header(data[: data.find(b"\n") + 1] if b"\n" in data else data)
        if not data.endswith(b"\n"):  # a write torn by a crash: keep whole lines only
            keep = data.rfind(b"\n") + 1
            os.ftruncate(self.fd, keep)
            os.fsync(self.fd)
            self.dropped_bytes = len(data) - keep
            data = data[:keep]
        records = list(csv.reader(io.StringIO(data.decode("utf-8"))))
        for lineno, record in enumerate(records[1:], start=2):
            if len(record) != len(self.columns):
                raise ClothbenchError(
                    f"{self.path}:{lineno}: {len(record)} fields, expected {len(self.columns)}: "
                    f"the file was changed by something other than clothbench {self.what}"
                )
            self.rows.append(dict(zip(self.columns, record)))

    def _check_header(self, first_line: bytes) -> None:
        """Refuse (before changing a byte) a file this version did not write."""
        try:
            header = tuple(next(csv.reader([first_line.decode("utf-8")]), []))
        except UnicodeDecodeError:
            raise ClothbenchError(f"{self.path} is not a clothbench {self.what} CSV (not UTF-8 text)") from None
        columns = self.columns
        if header == columns:
            return
        if not self._of_this_kind(header):
            raise ClothbenchError(f"{self.path} is not a clothbench {self.what} CSV: choose another --out")
        missing = [c for c in columns if c not in header]
        extra = [c for c in header if c not in columns]
        detail = (
            "; ".join(
                ([f"lacks {', '.join(missing)}"] if missing else []) + ([f"has {', '.join(extra)}"] if extra else [])
            )
            or "has them in another order"
        )
        raise ClothbenchError(
            f"{self.path} has other columns than this clothbench writes ({detail}): "
            f"resume it with the version that wrote it, or write the {self.what} into a new --out"
        )

    def _of_this_kind(self, header: tuple[str, ...]) -> bool:
        """Whether a header is this kind of file's, if perhaps of another version: a sweep's."""
        return "backend" in header and "ms_median" in header

    def _read_all(self) -> bytes:
        chunks, offset = [], 0
        while chunk := os.pread(self.fd, 1 << 20, offset):
            chunks.append(chunk)
            offset += len(chunk)
        return b"".join(chunks)

    def _write(self, line: str) -> None:
        data = line.encode("utf-8")
        written = os.write(self.fd, data)  # one call: a regular file takes it whole
        while written < len(data):  # (should a kernel ever split it, finish the line)
            written += os.write(self.fd, data[written:])
        os.fsync(self.fd)

    def keys(self) -> set[tuple[str, ...]]:
        return {row_key(r) for r in self.rows}

    def append(self, row: dict[str, str]) -> None:
        self._write(csv_line(row.get(c, "") for c in self.columns))
        self.rows.append(row)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_sweep(path: str | os.PathLike, required: Iterable[str] = ()) -> list[dict[str, str]]:
    """The rows of a sweep CSV (as strings), checking `required` columns are present.
    A partial last line (a sweep still running, or killed mid-write) is dropped with a
    warning on stderr naming the file; one line refuses a file cut before any whole row."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ClothbenchError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise ClothbenchError(f"{path} is a directory, expected a sweep CSV") from None
    except UnicodeDecodeError:
        raise ClothbenchError(f"{path} is not a clothbench sweep CSV (not UTF-8 text)") from None
    except OSError as e:
        raise ClothbenchError(f"cannot read {path}: {e.strerror}") from None
    truncated = bool(text) and not text.endswith("\n")
    if truncated:
        text = text[: text.rfind("\n") + 1]
        why = "(a sweep still writing it, or one killed mid-write)"
        if not text:
            raise ClothbenchError(f"{path} is truncated inside its header {why}: no whole line to read")
    reader = csv.DictReader(io.StringIO(text))
    header = reader.fieldnames or []
    if not header:
        raise ClothbenchError(f"{path} is empty: expected a CSV written by `clothbench sweep`")
    if truncated:
        if text.count("\n") == 1:  # the header alone is whole
            raise ClothbenchError(f"{path} is truncated inside its first row {why}: no whole row to read")
        print(
            f"clothbench: warning: {path} is truncated: its last line, cut mid-row, was dropped {why}", file=sys.stderr
        )
    missing = [c for c in required if c not in header]
    if missing:
        raise ClothbenchError(
            f"{path} lacks column{'s' if len(missing) > 1 else ''} {', '.join(missing)}: "
            "expected a CSV written by `clothbench sweep`"
        )
    return list(reader)
