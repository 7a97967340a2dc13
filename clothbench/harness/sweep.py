"""The benchmark sweep: every usable backend, each of its declared variants, every grid size
(and, when asked, every work-group size), timed and checked, one CSV row each
(harness/sweep_csv.py: the columns and the file that keeps every finished row).

A row is timed by the shared harness (harness/timing.py): build and warm up, then R chunks
of S steps from the solver's start, each between two synchronisations; uploads and
readbacks are outside the clock except in a per-step transfer mode, whose point is their
cost. The final state is then compared with the NumPy float64 run of the same scene,
solver and S*R steps (or of the steps a time budget left). A row that raises is written as
`failed` and one that blows up as `unstable`, with the reason and empty measurement columns,
and the sweep goes on.

The float64 references are shared: the numpy f64 row's final state is every other row's of
its grid and solver (where it did not leave one of S*R steps, one run gives it before the next
row); a row a budget cut to its own step count waits, with the rows after it, and at the end
of its grid one float64 run per scene and solver gives every step count the waiting rows
need (simulate.reference_states).
"""

from __future__ import annotations

import math
import os
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from clothbench import environment, machine_fitness, machine_load
from clothbench.backends import BackendOptions, availability, create_backend, tuning
from clothbench.errors import ClothbenchError
from clothbench.harness import energy, faults, noise
from clothbench.harness.health import self_contact
from clothbench.harness.executor import Outcome, fork_safe, run_isolated, start_method
from clothbench.harness.plan import SceneVariant, Variant, plan_variants
from clothbench.harness.simulate import position_error, reference, reference_states
from clothbench.harness.sweep_csv import (
    BUDGET_NOTE,
    COLUMNS,
    RETRY_STATUSES,
    SweepFile,
    fmt,
    fmt_chunks,
    one_line,
    row_key,
)
from clothbench.harness.sweep_settings import SweepSettings
from clothbench.harness.timing import run_timed
from clothbench.model.scene import Setup
from clothbench.variant_names import PER_STEP_TRANSFERS
from clothbench.model.solver import ITERATIVE, Solver


NATIVE = "c"  # the backend every row's vs_c is taken against: the native CPU line


# --- plan ------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlannedRow:
    """One row to measure: a variant (backend, complete options, solver) on one grid of one
    scene variant (its mesh size and motion)."""

    variant: Variant
    grid: int
    scene_variant: SceneVariant = SceneVariant()

    @property
    def setup_key(self) -> tuple[int, SceneVariant]:
        """The key of the row's setup in SweepSettings.setups."""
        return self.grid, self.scene_variant

    @property
    def backend(self) -> str:
        return self.variant.backend

    @property
    def options(self) -> BackendOptions:
        return self.variant.options

    @property
    def solver(self) -> Solver:
        return self.variant.solver

    def fields(self, scene_name: str) -> dict[str, str]:
        """The columns known before measuring (the key among them)."""
        o, s = self.options, self.solver
        pbd, iterative = s.name == "pbd", s.name in ITERATIVE
        return {
            "backend": self.backend,
            "peer": fmt(self.variant.peer),
            "solver": s.name,
            "pbd_method": s.method if pbd else "",
            "iterations": str(s.iterations) if iterative else "",
            "substeps": str(s.substeps) if iterative else "",
            "mode": self.variant.label,
            "precision": o.precision,
            "strict": fmt(o.strict),
            "transfer": fmt(o.transfer),
            "local_size": fmt(o.local_size),
            "generic": fmt(o.generic),
            "scene": scene_name,
            "mesh_triangles": fmt(self.scene_variant.mesh_triangles),
            "mesh_collision": fmt(o.mesh_collision),
            "motion": self.scene_variant.motion,
            "self_collision": self.scene_variant.self_collision,
            "grid": str(self.grid),
            "timed_region": "steps+transfers" if o.transfer in PER_STEP_TRANSFERS else "steps",
        }

    def key(self, scene_name: str) -> tuple[str, ...]:
        return row_key(self.fields(scene_name))


@dataclass
class Plan:
    rows: list[PlannedRow]
    skipped: list[tuple[str, str]]  # (backend, why it cannot run here)


def plan_sweep(
    names: Iterable[str],
    grids: Iterable[int],
    solvers: Iterable[Solver],
    base: BackendOptions = BackendOptions(),
    local_sizes: Iterable[int] = (),
    generic: str = "no",
    scenes: Iterable[tuple[SceneVariant, object]] = (),
    mesh_collisions: Iterable[str] = (),
) -> Plan:
    """harness.plan's variants on every grid, grid-major so an interrupted sweep holds every
    backend at the small grids; the float64 reference first in each grid and solver. With
    `scenes` ((SceneVariant, Scene) pairs), each grid runs each scene variant in turn, and a
    backend that refuses a scene is skipped with its refusal (said once), not measured."""
    names, solvers, scenes = list(names), list(solvers), list(scenes) or [(SceneVariant(), None)]
    per_scene, skipped = [], []
    for sv, scene in scenes:
        variants, skips = plan_variants(names, solvers, base, local_sizes, generic, scene, mesh_collisions)
        # the native c line next, so that every later row of its grid has its vs_c ratio
        variants.sort(key=lambda v: 0 if v.is_reference else 1 if v.backend == NATIVE else 2)
        per_scene.append((sv, variants))
        skipped += skips
    rows = [PlannedRow(v, g, sv) for g in grids for sv, variants in per_scene for v in variants]
    return Plan(rows, list(dict.fromkeys(skipped)))


# --- one row ---------------------------------------------------------------------------


def base_row(row: PlannedRow, setup: Setup, steps: int, repeats: int) -> dict[str, str]:
    """The row's columns known before it runs (the rest empty)."""
    scene, solver = setup.scene, row.solver
    probe = availability(row.backend)  # a row that fails before its backend is built still names them
    out = dict.fromkeys(COLUMNS, "")
    out.update(row.fields(scene.name))
    out.update(
        device=probe.device,
        driver=probe.driver,
        particles=str(scene.particles),
        springs=str(scene.springs),
        dt=repr(solver.dt),
        steps=str(steps),
        repeats=str(repeats),
        simulated_s=fmt(steps * repeats * solver.dt),
        host=environment.host_name(),
    )
    return out


def measure_row(
    row: PlannedRow,
    setup: Setup,
    steps: int,
    repeats: int,
    references: dict | None = None,
    on_progress: Callable[[int], None] | None = None,
    budget_s: float | None = None,
    unchecked: dict | None = None,
) -> dict[str, str]:
    """Time `row` (R chunks of S steps after warm-up) and compare its final state with the
    float64 reference. Never raises for a backend's failure: that becomes the row's status.
    `setup` is the row's scene at its grid; the row's own solver steps it. `references` maps a
    (scene, solver, steps) to a reference final state already known (the numpy f64 row's, which
    this row adds when it is that row). Where none is known for the steps that ran, the row runs
    the reference itself, or with `unchecked` leaves its error to the caller: its final state
    goes into `unchecked` under that key and the err cells stay empty (check_errors fills them)."""
    references = {} if references is None else references
    scene, solver = setup.scene, row.solver
    total = steps * repeats
    out = base_row(row, setup, steps, repeats)
    out["budget_s"] = fmt(budget_s)
    try:
        tuning.forget_met()  # so that check_row below sees this backend's choice only
        t0 = time.perf_counter()
        backend = create_backend(row.backend, scene, solver, row.options)
        build_s = time.perf_counter() - t0
        with backend:
            out["mode"], out["device"], out["driver"] = backend.mode, backend.device, backend.driver
            faults.inject(row.backend)
            watch = machine_load.LoadSampler().start()  # a row far off its tuning counts only if quiet
            result = run_timed(
                backend,
                total,
                chunk=steps,
                on_progress=on_progress,
                raise_on_blowup=False,
                build_s=build_s,
                budget_s=budget_s,
            )
            load = watch.stop()
            quiet = load.busy is False
    except MemoryError as e:  # a Python-side allocation the machine could not hold
        out.update(status="crashed", note=one_line(f"out of memory: {e}"), **environment.collect())
        return out
    except Exception as e:  # any backend error is this row's result, not the sweep's end
        out.update(status="failed", note=one_line(f"{type(e).__name__}: {e}"), **environment.collect())
        return out

    if result.blowup is not None or not result.finite:
        what = result.blowup or "final state is not finite"
        out.update(status="unstable", note=one_line(str(what)), finite=fmt(result.finite), **environment.collect())
        return out

    spread = result.spread()
    ms = result.ms_per_step
    shape_note = tuning.check_row(backend.name, getattr(backend, "shape", None), ms, quiet)  # provisional?
    if result.budget_cut:
        total = result.steps
        out.update(
            steps=str(result.chunk),
            repeats=str(len(result.chunk_ms_per_step)),
            simulated_s=fmt(total * solver.dt),
            note=f"{BUDGET_NOTE} {fmt(budget_s)} s: {len(result.chunk_ms_per_step)} chunks of {result.chunk} steps "
            f"instead of {repeats} of {steps}; error against the float64 run of the same {total} steps",
        )
    out.update(
        status="ok",
        ms_median=fmt(ms),
        ms_min=fmt(spread["min"]),
        ms_max=fmt(spread["max"]),
        ms_iqr=fmt(spread["iqr"]),
        chunk_ms=fmt_chunks(result.chunk_ms_per_step),
        device_ms_median=fmt(statistics.median(result.device_ms_per_step)) if result.device_ms_per_step else "",
        device_timer=result.device_timer,
        particles_per_s=fmt(scene.particles * 1e3 / ms) if ms > 0 else "",
        ms_per_sim_s=fmt(ms / solver.dt),
        warmup_s=fmt(result.warmup_s),
        finite=fmt(result.finite),
        max_penetration_m=fmt(result.max_penetration),
        **self_contact_cells(end_contact(row, result)),
    )
    key = (scene, solver, total)
    if row.variant.is_reference:  # the float64 run of the steps that ran, shortened or not
        references[key] = result.pos
    if key in references or unchecked is None:
        try:
            ref = references[key] if key in references else reference(scene, solver, total)[0]
            add_error(out, result.pos, ref)
        except Exception as e:
            add_note(out, one_line(f"{REFERENCE_FAILED}: {type(e).__name__}: {e}"))
    else:
        unchecked[key] = result.pos
    out.update(busy="" if load.busy is None else fmt(load.busy), load=f"{load.why}; {machine_load.cpu_context()}")
    # a figure measured on a busy machine, or from chunks spread wide, says so (harness/noise.py)
    doubt = "; ".join(noise.doubts(load.busy, load.why, result.chunk_ms_per_step))
    doubt = f"the figure may not hold: {doubt}" if doubt else ""
    out["note"] = "; ".join(n for n in (out.get("note", ""), shape_note, backend.run_note, doubt) if n)
    out.update(environment.collect())
    return out


REFERENCE_FAILED = "no error measured: float64 reference failed"
REFERENCE_BLEW_UP = "the float64 reference blew up: no error measured"


def add_note(out: dict[str, str], note: str) -> None:
    out["note"] = "; ".join(n for n in (out.get("note", ""), note) if n)


def add_error(out: dict[str, str], pos: np.ndarray, ref: np.ndarray) -> None:
    """The row's err_rms_m and err_max_m against the float64 reference's final positions `ref`
    (or the note that it blew up)."""
    if np.isfinite(ref[:, :3]).all():
        rms, worst = position_error(pos, ref)
        out.update(err_rms_m=fmt(rms), err_max_m=fmt(worst))
    else:
        add_note(out, REFERENCE_BLEW_UP)


def end_contact(row: PlannedRow, result) -> tuple[int, float] | None:
    """The run's close pairs at the end: by its scene's [self_collision] table, or, for an
    `--self-collision off` row, by the file's table its scene was run without."""
    table = row.scene_variant.measured_with
    if table is None:
        return result.self_contact
    return self_contact(result.pos, result.scene.replace(self_collision=table))


def self_contact_cells(contact: tuple[int, float] | None) -> dict[str, str]:
    """The row's self_pairs and self_min_distance_m: empty for a scene without [self_collision]."""
    if contact is None:
        return {"self_pairs": "", "self_min_distance_m": ""}
    return {"self_pairs": fmt(contact[0]), "self_min_distance_m": fmt(contact[1])}


def _measure_in_child(row, setup, steps, repeats, known, start=None, on_progress=None, budget_s=None, defer=False):
    """measure_row in a worker process: the row, the reference state it found (if it is the
    reference row) and, with `defer`, its final state where its error is left to the parent.
    `start`: energy.start_energy of the row's scene and solver where the parent has it."""
    if start is not None:
        energy.remember_start(setup.scene, row.solver, start)
    key = (setup.scene, row.solver, steps * repeats)
    references = {} if known is None else {key: known}
    unchecked = {} if defer else None
    out = measure_row(row, setup, steps, repeats, references, on_progress, budget_s, unchecked)
    return out, references if row.variant.is_reference else {}, unchecked or {}


def reference_errors(scene, solver, positions: dict[int, list]) -> dict[int, list]:
    """position_error of each of `positions` ({steps: [final positions]}) against the float64
    reference after that many steps, from one reference run, in a worker: the parent never runs
    a native library's threads (OpenMP does not survive a fork into the next row's worker), and
    only the numbers come back. None for a reference that blew up."""
    errors = {}

    def compare(count, ref, _):
        finite = np.isfinite(ref[:, :3]).all()
        errors[count] = [position_error(pos, ref) if finite else None for pos in positions[count]]

    reference_states(scene, solver, positions, on_state=compare)
    return errors


def _full_reference(scene, solver, steps: int) -> np.ndarray:
    """The float64 reference's final positions after `steps` steps (for a worker)."""
    return reference(scene, solver, steps)[0]


def full_reference(row: PlannedRow, settings, references: dict) -> int:
    """Before a row that is not the reference: the float64 state after S*R steps, where the
    reference row did not leave it (skipped, or shortened by its budget), so that every row
    that runs all its steps is checked, and written, as it comes. Returns the runs made (0, 1)."""
    scene, total = settings.setups[row.setup_key].scene, settings.steps * settings.repeats
    key = (scene, row.solver, total)
    if row.variant.is_reference or key in references:
        return 0
    if not settings.isolate:
        try:
            references[key] = _full_reference(*key)
        except Exception:  # the row's own check says why
            pass
        return 1
    known = run_isolated(_full_reference, key, timeout=settings.row_timeout, method=start_method(False))
    if known.ok:
        references[key] = known.value
    return 1


def _measure(row: PlannedRow, settings, references: dict, report, fork_safe: bool) -> tuple[dict, dict]:
    """The row's CSV row and, where its error waits for a reference, {key: its final state}."""
    setup = settings.setups[row.setup_key]
    if not settings.isolate:
        unchecked: dict = {}
        args = (row, setup, settings.steps, settings.repeats, references, report, settings.row_budget, unchecked)
        return measure_row(*args), unchecked
    known = references.get((setup.scene, row.solver, settings.steps * settings.repeats))
    outcome = run_isolated(
        _measure_in_child,
        (row, setup, settings.steps, settings.repeats, known, _start_energy(setup.scene, row.solver)),
        kwargs={"budget_s": settings.row_budget, "defer": True},
        timeout=settings.row_timeout,
        on_progress=report or (lambda done: None),
        method=start_method(fork_safe),
    )
    return _row_of(outcome, row, settings, references)


def _start_energy(scene, solver) -> tuple[float, float] | None:
    """energy.start_energy, here once a scene and solver for every row's own process; None
    where it fails (the row's own check then says why)."""
    try:
        return energy.start_energy(scene, solver)
    except Exception:
        return None


def check_errors(waiting: list[tuple[dict, dict]], references: dict, settings) -> int:
    """Fill the error cells of the rows in `waiting` ((row, {key: final state})): against
    `references` where it holds the key, else from one float64 reference run per scene and
    solver giving every step count the rows need (in a worker where settings.isolate). Returns
    how many reference runs it made."""
    wanted: dict = {}  # (scene, solver) -> {steps: [(row, final positions)]}
    for out, unchecked in waiting:
        for (scene, solver, steps), pos in unchecked.items():
            if (scene, solver, steps) in references:
                add_error(out, pos, references[scene, solver, steps])
            else:
                wanted.setdefault((scene, solver), {}).setdefault(steps, []).append((out, pos))
    for (scene, solver), by_steps in wanted.items():
        args = (scene, solver, {steps: [pos for _, pos in rows] for steps, rows in by_steps.items()})
        why = ""
        if settings.isolate:
            outcome = run_isolated(reference_errors, args, timeout=settings.row_timeout, method=start_method(False))
            errors, why = (outcome.value, "") if outcome.ok else ({}, one_line(outcome.note))
        else:
            try:
                errors = reference_errors(*args)
            except Exception as e:
                errors, why = {}, one_line(f"{type(e).__name__}: {e}")
        for steps, rows in by_steps.items():
            for (out, _), error in zip(rows, errors.get(steps) or [False] * len(rows)):
                if error is None:
                    add_note(out, REFERENCE_BLEW_UP)
                elif error is False:
                    add_note(out, f"{REFERENCE_FAILED}: {why or 'no state'}")
                else:
                    out.update(err_rms_m=fmt(error[0]), err_max_m=fmt(error[1]))
    return len(wanted)


def _row_of(outcome: Outcome, row: PlannedRow, settings, references: dict) -> tuple[dict[str, str], dict]:
    """The CSV row of a worker's outcome: its measurement, or crashed / timeout and why; and
    {key: final state} where its error waits for a reference."""
    setup = settings.setups[row.setup_key]
    if not outcome.ok:
        out = base_row(row, setup, settings.steps, settings.repeats)
        out.update(status=outcome.status, note=one_line(outcome.note), **environment.collect())
        if outcome.host:
            out["host"] = outcome.host
        return out, {}
    result, found, unchecked = outcome.value
    references.update(found)
    return result, unchecked


def _run_distributed(todo, settings, executor, keep, have, name, on_step, per_row) -> None:
    """Every row to the cluster at once; each written as it returns, once per key."""
    futures = {}
    for row in todo:
        setup = settings.setups[row.setup_key]
        args = (row, setup, settings.steps, settings.repeats, None)
        submitted = executor.submit(
            _measure_in_child, *args, budget_s=settings.row_budget, timing=True, timeout=settings.row_timeout
        )
        futures[submitted] = row
    written = set(have)
    for i, future in enumerate(executor.as_completed(list(futures))):
        row = futures[future]
        try:
            outcome = future.result()
        except Exception as e:  # the scheduler gave up on it (e.g. KilledWorker: it killed every worker it ran on)
            outcome = Outcome("crashed", note=f"{type(e).__name__}: {e}")
        result, _ = _row_of(outcome, row, settings, {})  # a remote row ran its own reference
        if row_key(result) in written:
            continue
        written.add(row_key(result))
        keep(row, result)
        if on_step:
            on_step((i + 1) * per_row, f"{row.backend} n={row.grid} on {result.get('host', '?')} ({i + 1}/{len(todo)})")


def _fork_safe(rows: list[PlannedRow]) -> bool:
    return all(fork_safe(r.backend, r.solver.name) for r in rows)


# --- the sweep -------------------------------------------------------------------------


@dataclass
class SweepProgress:
    """What a sweep has done so far; the CLI reads it, also after an interruption."""

    plan: Plan
    todo: list[PlannedRow]
    earlier: list[dict[str, str]]  # rows found in the file (--resume)
    dropped_bytes: int
    earlier_commits: set[str]
    measured: list[dict[str, str]] = field(default_factory=list)
    machine: object = None  # the machine's limits (harness/bounds.py), once measured
    machine_note: str = ""  # why they were not, if not
    # `clothbench machine`'s verdict before the first row (machine_fitness.Fitness), where rows run
    # here; every row of the run records it (machine_state)
    fitness: object = None
    reference_runs: int = 0  # float64 reference runs the sweep made beside its rows (check_errors)

    @property
    def already(self) -> int:
        return len(self.earlier)

    @property
    def rows(self) -> list[dict[str, str]]:
        """Every row in the file now, in file order."""
        return self.earlier + self.measured


def check_resumable(rows: list[dict[str, str]], s: SweepSettings, path: Path) -> None:
    """Refuse to mix rows timed with other settings into one file: they would not compare."""
    for r in rows:
        if r["scene"] != s.setup.scene.name or r.get("note", "").startswith(BUDGET_NOTE):
            continue  # a row its time budget shortened ran fewer steps on purpose
        try:
            same = (
                int(r["steps"]) == s.steps
                and int(r["repeats"]) == s.repeats
                and math.isclose(float(r["dt"]), s.setup.solver.dt, rel_tol=1e-9)
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


def _compared_columns(result: dict[str, str], rows: list[dict[str, str]], settings, row, machine) -> dict[str, str]:
    """The row's bound from `machine` (harness/bounds.py, measured once at the sweep's start;
    None: not measured, and not tried again per row) and its ratio to the c backend's row of
    the same grid, solver, precision and strictness."""
    out: dict[str, str] = {}
    ms = float(result["ms_median"])
    if machine is not None:
        from clothbench.harness.bounds import bound_columns, machine_columns

        scene, o = settings.setups[row.setup_key].scene, row.options
        bound = bound_columns(scene, o.precision, ms, row.solver, strict=o.strict, normals=o.normals, bounds=machine)
        out.update(bound)
        out.update(machine_columns(machine))
    same = ("grid", "solver", "pbd_method", "precision", "strict", "scene", "mesh_triangles", "motion")
    native = [
        r
        for r in [*rows, result]
        if r["backend"] == NATIVE and r["status"] == "ok" and r["ms_median"] and all(r[c] == result[c] for c in same)
    ]
    if native:
        out["vs_c"] = fmt(ms / float(native[-1]["ms_median"]))
    return out


def run_sweep(
    names: Iterable[str],
    settings: SweepSettings,
    out: str | os.PathLike,
    resume: bool = False,
    on_start: Callable[[SweepProgress], None] | None = None,
    on_step: Callable[[int, str], None] | None = None,
    on_row: Callable[[dict[str, str]], None] | None = None,
    retry_failed: bool = False,
    executor=None,
) -> SweepProgress:
    """Measure every planned row not yet in `out`, appending each as it is measured.

    on_start(progress) once the plan is known (the same object then collects the measured
    rows, so a caller holding it can report after a Ctrl-C); on_step(steps_done, description)
    as steps run; on_row(row) after each row is on the disk. Rows run one at a time, each
    in a worker process unless settings.isolate is false; `retry_failed` measures again the
    rows the file holds as failed, crashed or timeout. With a Dask `executor`
    (harness/executor.py, DaskExecutor) every row is submitted at once as a timed task (one per
    worker machine at a time) and written here, by this process alone, as it comes back.
    """
    plan = plan_sweep(
        names,
        settings.grids,
        settings.solver_settings,
        settings.base,
        settings.local_sizes,
        settings.generic,
        [(sv, s) for sv, s, _ in settings.scene_variants],
        settings.mesh_collisions,
    )
    if not plan.rows:
        raise ClothbenchError(
            "nothing to measure: no backend named can run here ("
            + "; ".join(f"{name}: {reason}" for name, reason in plan.skipped)
            + ")"
        )
    fork_safe = _fork_safe(plan.rows)
    with SweepFile(out, resume=resume, retry=RETRY_STATUSES if retry_failed else ()) as f:
        check_resumable(f.rows, settings, f.path)
        have = f.keys()
        name = settings.setup.scene.name
        todo = [r for r in plan.rows if r.key(name) not in have]
        commits = {r["git_commit"] for r in f.rows} - {environment.machine()["git_commit"]}
        progress = SweepProgress(plan, todo, list(f.rows), f.dropped_bytes, commits)
        here = executor is None or getattr(executor, "where", "local") == "local"
        if todo and here:  # once, before any row: is this machine fit to benchmark now?
            progress.fitness = machine_fitness.check(window_s=machine_load.MIN_WINDOW_S)
        if on_start:
            on_start(progress)
        references: dict = {}
        per_row = settings.steps * settings.repeats
        if settings.bounds and todo:
            from clothbench.harness.bounds import machine_or_reason

            progress.machine, progress.machine_note = machine_or_reason()  # once, before any row

        def keep(row: PlannedRow, result: dict[str, str]) -> None:
            if row.options.generic and result["status"] == "ok":
                twin = _specialised_twin(result, f.rows)  # f.rows holds this run's rows too
                if twin is not None:
                    result["specialised_speedup"] = fmt(float(result["ms_median"]) / float(twin["ms_median"]))
            if result["status"] == "ok":
                result.update(_compared_columns(result, f.rows, settings, row, progress.machine))
            if progress.fitness is not None:
                result["machine_state"] = progress.fitness.verdict
            f.append(result)
            progress.measured.append(result)
            if on_row:
                on_row(result)

        if executor is not None and getattr(executor, "where", "local") != "local":
            _run_distributed(todo, settings, executor, keep, have, name, on_step, per_row)
            todo = []
        # rows in plan order from the first whose error waits for a reference (check_errors, at
        # the end of its grid and scene variant), so that each row is written in order
        waiting: list[tuple[PlannedRow, dict, dict]] = []

        def release() -> None:
            progress.reference_runs += check_errors([(r, u) for _, r, u in waiting], references, settings)
            for planned, result, _ in waiting:
                keep(planned, result)
            waiting.clear()
            references.clear()  # keyed by scene: a grid's references serve no other grid

        try:
            for i, row in enumerate(todo):
                if i and row.setup_key != todo[i - 1].setup_key:
                    release()
                size = f" local {row.options.local_size}" if row.options.local_size else ""
                solver = f" {row.solver.spec}" if row.solver.name != "verlet" else ""
                shape = f" {row.scene_variant.label}" if row.scene_variant.label else ""
                description = (
                    f"{row.backend}{solver} {row.variant.label}{size}{shape} n={row.grid} ({i + 1}/{len(todo)})"
                )
                report = None
                if on_step:
                    on_step(i * per_row, description)

                    def report(done, before=i * per_row, what=description):
                        on_step(before + done, what)

                progress.reference_runs += full_reference(row, settings, references)
                result, unchecked = _measure(row, settings, references, report, fork_safe)
                if unchecked or waiting:
                    waiting.append((row, result, unchecked))
                else:
                    keep(row, result)
            release()
        except BaseException:  # interrupted: the rows measured are kept, without the error they waited for
            for planned, result, unchecked in waiting:
                if unchecked:
                    add_note(result, "no error measured: the sweep stopped before its float64 reference ran")
                keep(planned, result)
            raise
        if on_step:
            on_step(len(progress.todo) * per_row, "done")
    return progress
