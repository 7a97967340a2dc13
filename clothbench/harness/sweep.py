"""The benchmark sweep: every usable backend, each of its sweep variants, every grid size
(and, when asked, every work-group size), timed and checked, one CSV row each.

Nothing measured is lost. Each row is written to the CSV as one complete line in a single
write, then flushed to the disk (fsync), the moment it is measured; an interrupted sweep
keeps every finished row, and `resume` measures only the rows whose key is not in the file
yet, after dropping a half-written last line if a crash left one.

A row is timed by the shared harness (harness/timing.py): build and warm up, then R chunks
of S steps from the initial state, each between two synchronisations; uploads and
readbacks are outside the clock except in a per-step transfer mode, whose point is their
cost. The final state is then compared with the NumPy float64 run of the same scene and
the same S*R steps. A row that raises is written as `failed` and one that blows up as
`unstable`, with the reason and empty measurement columns, and the sweep goes on.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..backends import BACKENDS, BackendOptions, availability, backend_class, create_backend
from ..errors import ClothbenchError
from ..scene import Scene
from . import environment
from .simulate import position_error, reference
from .timing import run_timed

PER_STEP_TRANSFERS = frozenset({"per-step"})  # transfer modes that move the state host<->device every step

# Every column, in file order, with what it means. COLUMNS is the header.
COLUMN_DOCS: dict[str, str] = {
    "backend": "registry name (see `clothbench backends`)",
    "peer": "true for a peer system (taichi, warp, numba), false for clothbench's own kernels",
    "solver": "the integrator: 'verlet' (mass-spring, docs/semantics.md) or 'pbd' (XPBD, docs/pbd.md)",
    "pbd_method": "pbd only: 'jacobi' or 'coloured' (Gauss-Seidel over 12 independent batches)",
    "iterations": "pbd only: constraint passes per substep",
    "substeps": "pbd only: substeps per step",
    "mode": "the backend's own name for the settings that change speed or results",
    "precision": "working precision: f32, or f64 (numpy only, the reference)",
    "strict": "the strict option: bit-exact with numpy f32 (no FMA contraction, no fast math)",
    "transfer": "transfer mode (opencl resident|per-step, cuda swap|copy); empty = the backend's default",
    "local_size": "work-group / block size; empty = the runtime chooses",
    "generic": "true = one kernel for every scene; false = the backend's default (specialised where it has one)",
    "specialised_speedup": "generic rows only: ms/step of this generic kernel / ms/step of the same backend's specialised kernel (same grid, mode and sweep)",
    "device": "what the work ran on, as the driver names it",
    "scene": "scene name",
    "grid": "n, particles per side",
    "particles": "n*n",
    "springs": "springs counted per particle, each seen from both ends (the chapter's count)",
    "dt": "time step (s)",
    "steps": "steps per timed chunk (S)",
    "repeats": "timed chunks (R): the timed run simulates S*R steps after the warm-up",
    "simulated_s": "simulated time of the timed run, S*R*dt (s)",
    "status": "ok | unstable (blew up: NaN/Inf or runaway) | failed (raised); measurements are empty unless ok",
    "note": "why a row is unstable or failed (one line)",
    "ms_median": "median over the R chunks of wall-clock ms per step",
    "ms_min": "fastest chunk, ms per step",
    "ms_max": "slowest chunk, ms per step",
    "ms_iqr": "inter-quartile range of the per-chunk ms per step",
    "device_ms_median": "median device-timed ms per step (profiling events), where the backend has them",
    "particles_per_s": "particles * 1000 / ms_median",
    "ms_per_sim_s": "compute ms per simulated second, ms_median / dt (1000 = real time)",
    "warmup_s": "build (kernel compile) plus warm-up steps, not timed (s)",
    "finite": "the final state is finite",
    "max_penetration_m": "deepest penetration of a particle into a collider at the end (m)",
    "err_rms_m": "RMS distance of the final positions to the numpy float64 run of the same scene and S*R steps (m)",
    "err_max_m": "largest such distance (m)",
    "timed_region": "what the clock saw: 'steps' (upload and readback outside) or 'steps+transfers' (per-step transfer mode)",
    "cpu": "CPU model",
    "cores": "logical CPUs available to the process",
    "python": "Python implementation and version",
    "packages": "versions of the packages that can change a result (name=version ...)",
    "env": "driver environment variables that were set (LP_NUM_THREADS, POCL_*, ...)",
    "git_commit": "clothbench commit, '+dirty' if tracked files had changes",
    "timestamp": "when the row was measured (UTC, ISO 8601)",
}
COLUMNS: tuple[str, ...] = tuple(COLUMN_DOCS)
# What identifies a row: a sweep measures each key once, and --resume skips keys in the file.
KEY_COLUMNS = (
    "backend", "solver", "pbd_method", "scene", "grid", "precision", "strict", "transfer", "generic", "local_size",
)  # fmt: skip
MEASUREMENT_COLUMNS = (
    "ms_median", "ms_min", "ms_max", "ms_iqr", "device_ms_median", "particles_per_s", "ms_per_sim_s",
    "warmup_s", "finite", "max_penetration_m", "err_rms_m", "err_max_m",
)  # fmt: skip
NOTE_MAX = 300  # characters


# --- plan ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlannedRow:
    """One row to measure: a backend with complete options, on one grid."""

    backend: str
    peer: bool
    grid: int
    options: BackendOptions
    label: str = "default"  # the variant, named from its overrides (the mode until measured)
    solver: str = "verlet"

    def fields(self, scene: Scene) -> dict[str, str]:
        """The columns known before measuring (the key among them)."""
        o = self.options
        pbd = scene.solver == "pbd"
        return {
            "backend": self.backend,
            "peer": fmt(self.peer),
            "solver": scene.solver,
            "pbd_method": scene.pbd_method if pbd else "",
            "iterations": str(scene.iterations) if pbd else "",
            "substeps": str(scene.substeps) if pbd else "",
            "mode": self.label,
            "precision": o.precision,
            "strict": fmt(o.strict),
            "transfer": fmt(o.transfer),
            "local_size": fmt(o.local_size),
            "generic": fmt(o.generic),
            "scene": scene.name,
            "grid": str(self.grid),
            "timed_region": "steps+transfers" if o.transfer in PER_STEP_TRANSFERS else "steps",
        }

    def key(self, scene: Scene) -> tuple[str, ...]:
        return row_key(self.fields(scene))

    @property
    def is_reference(self) -> bool:
        """The numpy float64 run: its final state is every other row's reference."""
        return self.backend == "numpy" and self.options.precision == "f64" and self.options.local_size is None


@dataclass
class Plan:
    rows: list[PlannedRow]
    skipped: list[tuple[str, str]]  # (backend, why it cannot run here)


GENERIC_CHOICES = ("no", "yes", "both")
# What --solvers accepts: a solver, or pbd with its method ("pbd" alone: the scene's method).
SOLVER_SPECS = ("verlet", "pbd", "pbd-jacobi", "pbd-coloured")


def solver_changes(spec: str) -> dict:
    """The scene changes a --solvers entry stands for."""
    solver, _, method = spec.partition("-")
    return {"solver": solver, **({"pbd_method": method} if method else {})}


def plan_sweep(
    names: Iterable[str],
    grids: Iterable[int],
    base: BackendOptions = BackendOptions(),
    local_sizes: Iterable[int] = (),
    solvers: Iterable[str] = ("verlet",),
    generic: str = "no",
) -> Plan:
    """Rows for every usable backend × solver × its sweep_variants × grids (× local sizes
    where it has one; × generic and specialised kernels with generic="both", the generic
    row right after its specialised twin); unusable backends go to `skipped` with the
    reason. Grid-major, so an interrupted sweep holds every backend at the small grids;
    the float64 reference first in each grid and solver."""
    grids, local_sizes = list(grids), tuple(local_sizes)
    kernels = {"no": (False,), "yes": (True,), "both": (False, True)}[generic]
    per_backend: dict[tuple[str, str], tuple[bool, list[tuple[BackendOptions, str]]]] = {}
    skipped: list[tuple[str, str]] = []
    for solver in solvers:
        for name in names:
            a = availability(name)
            if not a.usable:
                if solver == "verlet" or "verlet" not in solvers:
                    skipped.append((name, a.reason))
                continue
            try:
                cls = backend_class(name, solver_changes(solver)["solver"])
                if cls is None:
                    skipped.append((f"{name} ({solver})", f"{name} has no {solver} solver"))
                    continue
                variants = [dataclasses.replace(base, **v) for v in cls.sweep_variants]
                sizes = (None, *local_sizes) if cls.has_local_size else (None,)
                with_generic = kernels if cls.has_generic else (base.generic,)
            except Exception as e:  # a backend that cannot say what to sweep is skipped, not fatal
                skipped.append((name, f"cannot read its sweep_variants: {type(e).__name__}: {e}"))
                continue
            options = []
            for overrides, v in zip(cls.sweep_variants, variants):
                own_size = "local_size" in overrides  # a variant that fixes its size keeps it
                for ls in sizes:
                    for g in with_generic:
                        o = dataclasses.replace(v if own_size else dataclasses.replace(v, local_size=ls), generic=g)
                        options.append((o, variant_label(overrides, o)))
            per_backend[(name, solver)] = (BACKENDS[name].peer, options)

    rows: list[PlannedRow] = []
    for grid in grids:
        for solver in solvers:
            in_grid: dict[tuple, PlannedRow] = {}
            for (name, s), (peer, options) in per_backend.items():
                if s != solver:
                    continue
                for o, label in options:
                    in_grid.setdefault((name, o), PlannedRow(name, peer, grid, o, label, solver))  # once
            rows += sorted(in_grid.values(), key=lambda r: not r.is_reference)  # stable: reference first
    return Plan(rows, skipped)


def variant_label(overrides: dict, options: BackendOptions) -> str:
    """A mode name from a variant's option overrides, e.g. 'strict per-step' or 'f64'."""
    parts = []
    for k, v in overrides.items():
        if isinstance(v, bool):
            parts.append(k if v else ("fast" if k == "strict" else f"no-{k}"))
        elif v is not None:
            parts.append(str(v))
    if options.generic and "generic" not in overrides:
        parts.append("generic")
    return " ".join(parts) or "default"


# --- one row ---------------------------------------------------------------------------


def fmt(value) -> str:
    """A CSV cell: '' for None, true/false for booleans, 6 significant digits for floats."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else ""
    return str(value)


def _one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= NOTE_MAX else text[: NOTE_MAX - 1] + "…"


def measure_row(
    row: PlannedRow,
    scene: Scene,
    steps: int,
    repeats: int,
    references: dict | None = None,
    on_progress: Callable[[int], None] | None = None,
) -> dict[str, str]:
    """Time `row` (R chunks of S steps after warm-up) and compare its final state with the
    float64 reference. Never raises for a backend's failure: that becomes the row's status.
    `references` maps a scene to a reference final state already known (the numpy f64 row's)."""
    references = {} if references is None else references
    total = steps * repeats
    out = dict.fromkeys(COLUMNS, "")
    out.update(row.fields(scene))
    out.update(
        device=availability(row.backend).device,
        particles=str(scene.particles),
        springs=str(scene.springs),
        dt=repr(scene.dt),
        steps=str(steps),
        repeats=str(repeats),
        simulated_s=fmt(total * scene.dt),
    )
    try:
        t0 = time.perf_counter()
        backend = create_backend(row.backend, scene, row.options)
        build_s = time.perf_counter() - t0
        with backend:
            out["mode"], out["device"] = backend.mode, backend.device
            result = run_timed(
                backend, scene, total, chunk=steps, on_progress=on_progress, raise_on_blowup=False, build_s=build_s
            )
    except Exception as e:  # any backend error is this row's result, not the sweep's end
        out.update(status="failed", note=_one_line(f"{type(e).__name__}: {e}"), **environment.collect())
        return out

    if result.blowup is not None or not result.finite:
        what = result.blowup or "final state is not finite"
        out.update(status="unstable", note=_one_line(str(what)), finite=fmt(result.finite), **environment.collect())
        return out

    spread = result.spread()
    ms = result.ms_per_step
    out.update(
        status="ok",
        ms_median=fmt(ms),
        ms_min=fmt(spread["min"]),
        ms_max=fmt(spread["max"]),
        ms_iqr=fmt(spread["iqr"]),
        device_ms_median=fmt(statistics.median(result.device_ms_per_step)) if result.device_ms_per_step else "",
        particles_per_s=fmt(scene.particles * 1e3 / ms) if ms > 0 else "",
        ms_per_sim_s=fmt(ms / scene.dt),
        warmup_s=fmt(result.warmup_s),
        finite=fmt(result.finite),
        max_penetration_m=fmt(result.max_penetration),
    )
    if row.is_reference:
        references[scene] = result.pos
    try:
        ref = references[scene] if scene in references else reference(scene, total)[0]
        if np.isfinite(ref[:, :3]).all():
            rms, worst = position_error(result.pos, ref)
            out.update(err_rms_m=fmt(rms), err_max_m=fmt(worst))
        else:
            out["note"] = "the float64 reference blew up: no error measured"
    except Exception as e:
        out["note"] = _one_line(f"no error measured: float64 reference failed: {type(e).__name__}: {e}")
    out.update(environment.collect())
    return out


# --- the CSV ---------------------------------------------------------------------------


def row_key(row: dict[str, str]) -> tuple[str, ...]:
    return tuple(row.get(c, "") for c in KEY_COLUMNS)


def csv_line(values: Iterable[str]) -> str:
    buf = io.StringIO()
    csv.writer(buf, lineterminator="\n").writerow(list(values))
    return buf.getvalue()


class SweepFile:
    """The sweep CSV, open for appending: one complete line per write, fsynced.

    Holds an exclusive lock while open, so two sweeps never interleave rows in one file.
    """

    def __init__(self, path: str | os.PathLike, resume: bool = False):
        self.path = Path(path)
        self.rows: list[dict[str, str]] = []  # rows already in the file
        self.dropped_bytes = 0  # a partial last line removed on resume
        if not resume and self.path.exists() and self.path.stat().st_size > 0:
            raise ClothbenchError(
                f"{self.path} already exists: pass --resume to measure only the rows it lacks, "
                "or choose another --out"
            )
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        except OSError as e:
            raise ClothbenchError(f"cannot write {self.path}: {e.strerror}") from None
        try:
            self._lock()
            self._load()
        except BaseException:
            os.close(self.fd)
            raise

    def _lock(self) -> None:
        try:
            import fcntl
        except ImportError:  # not POSIX: no lock, the rest still holds
            return
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ClothbenchError(
                f"another clothbench sweep is writing {self.path}: wait for it, or choose another --out"
            ) from None

    def _load(self) -> None:
        data = self._read_all()
        header = csv_line(COLUMNS).encode()
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
            if len(record) != len(COLUMNS):
                raise ClothbenchError(
                    f"{self.path}:{lineno}: {len(record)} fields, expected {len(COLUMNS)}: "
                    "the file was changed by something other than clothbench sweep"
                )
            self.rows.append(dict(zip(COLUMNS, record)))

    def _check_header(self, first_line: bytes) -> None:
        """Refuse (before changing a byte) a file this version did not write."""
        try:
            header = tuple(next(csv.reader([first_line.decode("utf-8")]), []))
        except UnicodeDecodeError:
            raise ClothbenchError(f"{self.path} is not a clothbench sweep CSV (not UTF-8 text)") from None
        if header == COLUMNS:
            return
        if "backend" not in header or "ms_median" not in header:
            raise ClothbenchError(f"{self.path} is not a clothbench sweep CSV: choose another --out")
        missing = [c for c in COLUMNS if c not in header]
        extra = [c for c in header if c not in COLUMNS]
        detail = "; ".join(
            ([f"lacks {', '.join(missing)}"] if missing else []) + ([f"has {', '.join(extra)}"] if extra else [])
        ) or "has them in another order"
        raise ClothbenchError(
            f"{self.path} has other columns than this clothbench writes ({detail}): "
            "resume it with the version that wrote it, or sweep into a new --out"
        )

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
        self._write(csv_line(row.get(c, "") for c in COLUMNS))
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
    A partial last line (a sweep still running, or killed mid-write) is ignored."""
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
    if text and not text.endswith("\n"):
        text = text[: text.rfind("\n") + 1]
    reader = csv.DictReader(io.StringIO(text))
    header = reader.fieldnames or []
    if not header:
        raise ClothbenchError(f"{path} is empty: expected a CSV written by `clothbench sweep`")
    missing = [c for c in required if c not in header]
    if missing:
        raise ClothbenchError(
            f"{path} lacks column{'s' if len(missing) > 1 else ''} {', '.join(missing)}: "
            "expected a CSV written by `clothbench sweep`"
        )
    return list(reader)


# --- the sweep -------------------------------------------------------------------------


@dataclass
class SweepSettings:
    scene: Scene  # grid and steps are set per row
    grids: list[int]
    steps: int  # per chunk
    repeats: int
    base: BackendOptions = field(default_factory=BackendOptions)
    local_sizes: tuple[int, ...] = ()
    solvers: tuple[str, ...] = ("verlet",)
    generic: str = "no"  # no | yes | both (GENERIC_CHOICES)

    def __post_init__(self):
        if self.steps < 1:
            raise ClothbenchError(f"--steps must be >= 1 (steps per timed chunk), got {self.steps}")
        if self.repeats < 1:
            raise ClothbenchError(f"--repeat must be >= 1 (timed chunks per row), got {self.repeats}")
        if not self.grids:
            raise ClothbenchError("no grid size given (e.g. --grids 32,64,128,256)")
        if self.generic not in GENERIC_CHOICES:
            raise ClothbenchError(f"--generic takes {', '.join(GENERIC_CHOICES)}, got {self.generic!r}")
        # every grid and solver is checked as a scene now, before anything is measured
        self.scenes = {
            (solver, g): self.scene.replace(grid=g, steps=self.steps * self.repeats, **solver_changes(solver))
            for solver in self.solvers
            for g in self.grids
        }


@dataclass
class SweepProgress:
    """What a sweep has done so far; the CLI reads it, also after an interruption."""

    plan: Plan
    todo: list[PlannedRow]
    already: int  # rows found in the file
    dropped_bytes: int
    earlier_commits: set[str]
    measured: list[dict[str, str]] = field(default_factory=list)


def check_resumable(rows: list[dict[str, str]], s: SweepSettings, path: Path) -> None:
    """Refuse to mix rows timed with other settings into one file: they would not compare."""
    for r in rows:
        if r["scene"] != s.scene.name:
            continue
        try:
            same = (
                int(r["steps"]) == s.steps
                and int(r["repeats"]) == s.repeats
                and math.isclose(float(r["dt"]), s.scene.dt, rel_tol=1e-9)
            )
        except ValueError:
            same = False
        if not same:
            raise ClothbenchError(
                f"{path} was measured with --steps {r['steps']} --repeat {r['repeats']} --dt {r['dt']} "
                f"for scene {r['scene']}: resume with those, or sweep into a new --out"
            )


def _specialised_twin(row: dict[str, str], rows: list[dict[str, str]]) -> dict[str, str] | None:
    """The specialised row measured with the same key as generic `row`, if any and ok."""
    want = row_key({**row, "generic": "false"})
    for r in reversed(rows):
        if row_key(r) == want and r["status"] == "ok" and r["ms_median"]:
            return r
    return None


def run_sweep(
    names: Iterable[str],
    settings: SweepSettings,
    out: str | os.PathLike,
    resume: bool = False,
    on_start: Callable[[SweepProgress], None] | None = None,
    on_step: Callable[[int, str], None] | None = None,
    on_row: Callable[[dict[str, str]], None] | None = None,
) -> SweepProgress:
    """Measure every planned row not yet in `out`, appending each as it is measured.

    on_start(progress) once the plan is known (the same object then collects the measured
    rows, so a caller holding it can report after a Ctrl-C); on_step(steps_done, description)
    as steps run; on_row(row) after each row is on the disk.
    """
    plan = plan_sweep(
        names, settings.grids, settings.base, settings.local_sizes, settings.solvers, settings.generic
    )
    if not plan.rows:
        raise ClothbenchError(
            "nothing to measure: no backend named can run here ("
            + "; ".join(f"{name}: {reason}" for name, reason in plan.skipped)
            + ")"
        )
    with SweepFile(out, resume=resume) as f:
        check_resumable(f.rows, settings, f.path)
        have = f.keys()
        todo = [r for r in plan.rows if r.key(settings.scenes[(r.solver, r.grid)]) not in have]
        commits = {r["git_commit"] for r in f.rows} - {environment.machine()["git_commit"]}
        progress = SweepProgress(plan, todo, len(f.rows), f.dropped_bytes, commits)
        if on_start:
            on_start(progress)
        references: dict = {}
        per_row = settings.steps * settings.repeats
        for i, row in enumerate(todo):
            scene = settings.scenes[(row.solver, row.grid)]
            size = f" local {row.options.local_size}" if row.options.local_size else ""
            solver = f" {row.solver}" if row.solver != "verlet" else ""
            description = f"{row.backend}{solver} {row.label}{size} n={row.grid} ({i + 1}/{len(todo)})"
            report = None
            if on_step:
                on_step(i * per_row, description)

                def report(done, before=i * per_row, what=description):
                    on_step(before + done, what)

            result = measure_row(row, scene, settings.steps, settings.repeats, references, on_progress=report)
            if row.options.generic and result["status"] == "ok":
                twin = _specialised_twin(result, f.rows + progress.measured)
                if twin is not None:
                    result["specialised_speedup"] = fmt(float(result["ms_median"]) / float(twin["ms_median"]))
            f.append(result)
            progress.measured.append(result)
            if on_row:
                on_row(result)
        if on_step:
            on_step(len(todo) * per_row, "done")
    return progress
