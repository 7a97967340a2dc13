"""Error against cost: how wrong each backend is at each dt, and the convergence order.

Two errors, both as RMS and max per-particle position distance (m) at a stated simulated time:

- implementation error: a backend's state against the NumPy float64 run of the same scene,
  solver, dt and steps (float32 rounding, FMA contraction, built-ins);
- discretisation error: against a converged float64 reference of the same model at the same
  simulated time (converged_reference says how "converged" is decided).

A model is the scene and the solver settings without dt (model_key): a PBD line's
discretisation error is against the converged reference of its *own* model (the same method,
iterations, substeps and relaxation, dt -> 0), and the difference between the Verlet and
each PBD model's converged answers is measured and reported beside it (model_difference).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from clothbench.backends import BackendOptions, create_backend
from clothbench import environment
from clothbench.errors import ClothbenchError
from clothbench.harness.energy import total_energy
from clothbench.harness import faults
from clothbench.harness.executor import fork_safe, runner
from clothbench.harness.plan import Variant
from clothbench.harness.simulate import float64_state, float64_state_fork_safe, position_error, reference
from clothbench.harness.implicit import exact_implicit
from clothbench.harness.timing import run_timed
from clothbench.model.scene import Scene
from clothbench.model.solver import ITERATIVE, Solver, as_verlet
from clothbench.variant_names import model_name

F64 = BackendOptions(precision="f64")
EARLY_LEVELS = 4  # levels 0..3: what converged_reference always runs before it can stop


def dt_levels(dt0: float, levels: int) -> list[float]:
    """dt0, dt0/2, dt0/4, ... (levels values)."""
    return [dt0 / 2**i for i in range(levels)]


def steps_for(time_s: float, dt: float) -> int:
    """Steps to reach `time_s` with `dt`; refuses a time that is not a whole number of steps."""
    steps = round(time_s / dt)
    if steps < 1 or abs(steps * dt - time_s) > 1e-9 * time_s:
        raise ClothbenchError(
            f"--time {time_s:g} s is not a whole number of steps of dt {dt:g} s; "
            f"give a time that is a multiple of the largest dt"
        )
    return steps


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return position_error(a, b)[0]


def _max(a: np.ndarray, b: np.ndarray) -> float:
    return position_error(a, b)[1]


@dataclass
class Reference:
    """The converged float64 state of a scene at a simulated time."""

    pos: np.ndarray
    dt: float  # the finest dt run
    levels: int  # how many halvings below the finest measured dt
    order: float  # the convergence order the reference sequence itself shows
    uncertainty: float  # max-norm change of the reference at the last refinement (m)
    converged: bool
    prev: np.ndarray | None = None  # pos minus the finest run's displacement per step (dt)


def converged_reference(
    scene: Scene,
    solver: Solver,
    time_s: float,
    dt_finest: float,
    rtol: float = 0.02,
    max_levels: int = 5,
    on_level: Callable[[int, float], None] | None = None,
    runs_at: dict[int, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Reference:
    """The float64 state of `scene` stepped by `solver` at `time_s`, refined until it stops
    changing.

    Runs the float64 reference step (harness/simulate.py: NumPy's bits, stepped by c where it
    can) at dt_finest/2, /4, ... and extrapolates each pair (Richardson, with the order the
    last three runs show, clamped to [0.5, 4]). It is converged when two
    successive extrapolations differ (max norm) by less than `rtol` times the smallest error it
    will be compared with: the float64 error of the finest measured dt. Not converged after
    `max_levels` halvings: the last extrapolation is returned with converged=False, and the
    caller says so (errors smaller than `uncertainty` then mean nothing). `runs_at` holds
    (pos, prev) of levels already run (run_accuracy runs the first ones side by side).
    """
    runs_at = runs_at or {}
    steps0 = steps_for(time_s, dt_finest)
    runs = [runs_at[0][0] if 0 in runs_at else reference(scene, solver.replace(dt=dt_finest), steps0)[0]]
    extrapolated: list[np.ndarray] = []
    order = float("nan")
    step = np.zeros_like(runs[0])  # the finest run's pos - prev

    def result(best, dt, level, change, converged) -> Reference:
        prev = best.copy()
        prev[:, :3] -= step[:, :3]
        return Reference(best, dt, level, order, change, converged, prev)

    for level in range(1, max_levels + 1):
        dt = dt_finest / 2**level
        if on_level:
            on_level(level, dt)
        pos, prev = runs_at.get(level) or float64_state(scene, solver.replace(dt=dt), steps_for(time_s, dt))
        runs.append(pos)
        step = pos - prev
        if len(runs) < 3:
            continue
        d_old, d_new = _rms(runs[-3], runs[-2]), _rms(runs[-2], runs[-1])
        if d_new == 0.0:
            best = runs[-1]
        else:
            order = min(4.0, max(0.5, math.log2(d_old / d_new))) if d_old > 0 else 4.0
            best = runs[-1].copy()
            best[:, :3] += (runs[-1][:, :3] - runs[-2][:, :3]) / (2**order - 1)
        extrapolated.append(best)
        if len(extrapolated) >= 2:
            change = _max(extrapolated[-1], extrapolated[-2])
            smallest = _max(runs[0], best)
            if change <= rtol * smallest or smallest == 0.0:
                return result(best, dt, level, change, True)
    if not extrapolated:
        return result(runs[-1], dt_finest / 2**max_levels, max_levels, float("nan"), False)
    change = _max(extrapolated[-1], extrapolated[-2]) if len(extrapolated) >= 2 else float("nan")
    return result(extrapolated[-1], dt_finest / 2**max_levels, max_levels, change, False)


def fit_order(dts, errors, floor=None) -> float:
    """Least-squares slope of log(error) against log(dt) over the points above `floor`
    (float32 rounding or reference uncertainty); NaN with fewer than two such points."""
    pts = [
        (math.log(dt), math.log(e))
        for dt, e in zip(dts, errors)
        if e is not None and math.isfinite(e) and e > 0 and (floor is None or e > floor)
    ]
    if len(pts) < 2:
        return float("nan")
    x, y = np.array(pts).T
    return float(np.polyfit(x, y, 1)[0])


@dataclass
@environment.with_columns(after=("vs_exact_rms", "vs_exact_max"))  # then where and when it was measured
class AccuracyRow:
    scene: str
    grid: int
    start: str
    damping: float
    time_s: float
    backend: str
    label: str
    mode: str
    device: str
    dt: float
    steps: int
    solver: str = "verlet"
    pbd_method: str = ""  # PBD only
    iterations: int | None = None  # PBD and VBD only
    substeps: int | None = None  # PBD and VBD only
    status: str = "ok"  # "ok", or "unstable at step N: ..."
    ms_per_step: float = float("nan")
    ms_per_sim_s: float = float("nan")  # cost: milliseconds of compute per simulated second
    impl_rms: float = float("nan")
    impl_max: float = float("nan")
    disc_rms: float = float("nan")  # against the converged reference of this row's own model
    disc_max: float = float("nan")
    ref_model: str = ""  # which converged reference disc_* is measured against
    ref_dt: float = float("nan")
    ref_converged: bool = False
    ref_uncertainty: float = float("nan")
    vs_verlet_rms: float = float("nan")  # against the converged mass-spring (Verlet) answer
    vs_verlet_max: float = float("nan")
    strain: float = float("nan")  # mean structural-spring strain |L/rest - 1| at time_s
    kinetic_j: float = float("nan")  # kinetic energy at time_s (J, float64)
    order: float = float("nan")  # fitted over this backend/mode's rows, same in each
    order_points: int = 0  # how many of its dts the fit used (discretisation_dominates)
    in_fit: bool = False  # whether this row is one of them
    stiffness: float = float("nan")  # k of the scene (N/m): the model a row's cost and error are of
    driver: str = ""  # the runtime that ran it (Backend.driver); '' where none, or in files older than the column
    # VBD only (after the machine columns: with_columns' `after`), against the exact implicit-Euler
    # step at the same dt (harness/implicit.py): what its sweeps have not converged; disc_* and
    # vs_verlet_* add implicit Euler's own error
    vs_exact_rms: float = float("nan")
    vs_exact_max: float = float("nan")

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        for k in ("pbd_method", "iterations", "substeps"):
            if d[k] is None:
                d[k] = ""
        return d


def model_key(scene: Scene, solver: Solver) -> tuple[Scene, Solver]:
    """What identifies a model: the scene and the solver settings but the dt, so every dt of
    one model shares one converged reference."""
    return scene, solver.replace(dt=type(solver).dt)


def pbd_fields(solver: Solver) -> dict:
    """The PBD and VBD columns of a row (none for Verlet)."""
    if solver.name == "vbd":
        return dict(iterations=solver.iterations, substeps=solver.substeps)
    if solver.name != "pbd":
        return {}
    return dict(pbd_method=solver.method, iterations=solver.iterations, substeps=solver.substeps)


@dataclass
class ModelDifference:
    """How far apart two models' converged answers are at the stated time."""

    a: str
    b: str
    rms: float
    max: float
    uncertainty: float  # the larger reference uncertainty (max norm) of the two
    converged: bool  # both references converged

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class AccuracyResult:
    rows: list[AccuracyRow]
    reference: Reference  # the first model's (Verlet's when it was measured)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    references: dict[str, Reference] = field(default_factory=dict)  # model_name -> reference
    differences: list[ModelDifference] = field(default_factory=list)  # Verlet vs each PBD model
    ref_bulk: dict[str, tuple[float, float]] = field(default_factory=dict)  # model -> (strain, kinetic)

    def orders(self) -> dict[str, tuple[float, int]]:
        """label -> (fitted order, number of dts it was fitted over)."""
        out = {}
        for r in self.rows:
            out.setdefault(r.label, (r.order, r.order_points))
        return out


def cheapest_at(rows, target: float, error: str = "disc_rms"):
    """The row with the lowest cost (ms per simulated second) among those whose `error`
    column is at most `target`; None when no row reaches it."""
    ok = [r for r in rows if r.status == "ok" and getattr(r, error) <= target and r.ms_per_sim_s > 0]
    return min(ok, key=lambda r: r.ms_per_sim_s) if ok else None


DOMINANCE = 10.0  # a point enters the order fit when discretisation is 10x everything else


def discretisation_dominates(row: AccuracyRow) -> bool:
    """Whether row's error to the converged reference is discretisation error: at least
    DOMINANCE times its implementation error (rounding, which in float32 grows as dt shrinks)
    and times the reference's own uncertainty (the row's ref_uncertainty)."""
    unc = row.ref_uncertainty if math.isfinite(row.ref_uncertainty) else 0.0
    return row.status == "ok" and row.disc_rms > DOMINANCE * row.impl_rms and row.disc_max > DOMINANCE * unc


# the columns fit_orders writes: a study's CSV leaves them empty in a row written as it is
# measured, and fills them when the study completes (cli/study_files.py)
FITTED = ("order", "order_points", "in_fit")


def fit_orders(rows: list[AccuracyRow]) -> None:
    """Each backend mode's convergence order, fitted over its rows (one label's, every dt) whose
    error is discretisation error, written into each of them: order, order_points, in_fit. The
    measurement, a resumed study and a report of an unfinished study's file all fit it here."""
    for label in dict.fromkeys(r.label for r in rows):
        mine = [r for r in rows if r.label == label]
        used = [r for r in mine if discretisation_dominates(r)]
        order = fit_order([r.dt for r in used], [r.disc_rms for r in used])
        for r in mine:
            r.order, r.order_points, r.in_fit = order, len(used), r in used


def structural_strain(pos: np.ndarray, scene: Scene) -> float:
    """Mean |L/rest - 1| over the structural springs: how stretched the cloth is. A solver
    that under-resolves its constraints (PBD at few iterations) shows it as extra strain."""
    n = scene.grid
    x = pos[:, :3].astype(np.float64).reshape(n, n, 3)
    lengths = np.concatenate(
        [np.linalg.norm(x[:, 1:] - x[:, :-1], axis=2).ravel(), np.linalg.norm(x[1:] - x[:-1], axis=2).ravel()]
    )
    return float(np.abs(lengths / scene.spacing - 1).mean())


def bulk(pos: np.ndarray, prev: np.ndarray, scene: Scene, dt: float) -> tuple[float, float]:
    """(mean structural strain, kinetic energy in J) of a state, prev taken dt before pos:
    what a softer or more damped model changes, and what position error alone does not
    separate."""
    with np.errstate(all="ignore"):
        return structural_strain(pos, scene), total_energy(pos, prev, scene, dt, springs=False).kinetic


def model_difference(a_solver: Solver, a: Reference, b_solver: Solver, b: Reference) -> ModelDifference:
    rms, mx = position_error(a.pos, b.pos)
    unc = [u for u in (a.uncertainty, b.uncertainty) if math.isfinite(u)]
    return ModelDifference(
        model_name(a_solver),
        model_name(b_solver),
        rms,
        mx,
        max(unc) if unc else float("nan"),
        a.converged and b.converged,
    )


def _measure(
    v: Variant, scene: Scene, solver: Solver, time_s: float, ref: Reference, verlet_ref: Reference | None
) -> AccuracyRow:
    """One row: `v` stepped by `solver` to `time_s`, timed, against both references."""
    return _against(*_run_row(v, scene, solver, time_s), scene, solver, ref, verlet_ref)


def _run_row(v: Variant, scene: Scene, solver: Solver, time_s: float, exact: bool = True):
    """The part of a row that needs no converged reference (so it can run beside them):
    `v` stepped to `time_s`, timed, against float64 at the same dt. (row, pos, prev)."""
    steps = steps_for(time_s, solver.dt)
    row = _unmeasured_row(v, scene, solver, time_s)
    try:
        with create_backend(v.backend, scene, solver, v.options) as b:
            faults.inject(v.backend)
            result = run_timed(b, steps, raise_on_blowup=False)
    except Exception as e:  # a broken backend is a row saying so, not a dead command
        row.status = f"error: {type(e).__name__}: {e}"
        return row, None, None
    row.mode, row.device, row.driver = result.mode, result.device, result.driver
    row.ms_per_step = result.ms_per_step
    row.ms_per_sim_s = result.ms_per_step / solver.dt
    if result.blowup is not None:
        row.status = f"unstable at step {result.blowup.step}: {result.blowup.what}"
        return row, None, None
    row.impl_rms, row.impl_max = position_error(result.pos, reference(scene, solver, steps)[0])
    if solver.name == "vbd" and exact:
        row.vs_exact_rms, row.vs_exact_max = position_error(result.pos, exact_implicit(scene, solver, steps)[0])
    return row, result.pos, result.prev


def _against(row: AccuracyRow, pos, prev, scene: Scene, solver: Solver, ref: Reference, verlet_ref) -> AccuracyRow:
    """The row's errors against the converged references."""
    if row.status.startswith("error:"):
        return row
    row.ref_dt, row.ref_converged, row.ref_uncertainty = ref.dt, ref.converged, ref.uncertainty
    if pos is None:
        return row
    row.disc_rms, row.disc_max = position_error(pos, ref.pos)
    if verlet_ref is not None:
        row.vs_verlet_rms, row.vs_verlet_max = position_error(pos, verlet_ref.pos)
    row.strain, row.kinetic_j = bulk(pos, prev, scene, solver.dt)
    return row


def _measure_failed(v: Variant, scene: Scene, solver: Solver, time_s: float, why: str) -> AccuracyRow:
    """The row of a run whose worker process crashed or timed out."""
    return _unmeasured_row(v, scene, solver, time_s, status=" ".join(why.split()))


def _unmeasured_row(v: Variant, scene: Scene, solver: Solver, time_s: float, **fields) -> AccuracyRow:
    """A row naming the run (scene, variant, dt, steps), its mode and device not yet known."""
    steps = steps_for(time_s, solver.dt)
    return AccuracyRow(
        scene.name,
        scene.grid,
        solver.start,
        scene.damping,
        time_s,
        v.backend,
        v.name,
        "?",
        "?",
        solver.dt,
        steps,
        solver.name,
        **pbd_fields(solver),
        ref_model=model_name(solver),
        stiffness=scene.stiffness,
        **environment.collect(),
        **fields,
    )


def run_accuracy(
    scene: Scene,
    variants: list[Variant],
    dts: list[float],
    time_s: float,
    on_progress: Callable[[str], None] | None = None,
    pbd_dts: list[float] | None = None,
    executor=None,
    skip: Callable[[Variant, Solver], bool] | None = None,
    on_row: Callable[[AccuracyRow], None] | None = None,
    exact: bool = True,
) -> AccuracyResult:
    """Every variant at every dt to `time_s`: cost, implementation and discretisation error.

    Verlet variants run `dts`, PBD variants `pbd_dts` (default the same), each with its own
    solver's other settings. Each model (the solver with its PBD method, iterations,
    substeps, relaxation) gets its own converged float64 reference, refined below its finest
    dt; when PBD is measured, Verlet's reference (with the first variant's start) is
    computed too (below min(dts)), every row's error against it is written (vs_verlet_*),
    and the distance between the converged answers of Verlet and each PBD model is returned
    in `differences`. With an `executor` (harness/executor.py) the references, then the
    rows, run as its tasks (in parallel over its jobs; every one in a worker process): a
    row whose worker crashed or ran past the limit says so in its status. Rows `skip` names
    are not run (--resume: the file has them); `on_row` gets each row as it is measured.
    `exact`: VBD rows are also compared with the exact implicit-Euler step (vs_exact_*)."""
    note = on_progress or (lambda what: None)
    dts = sorted(dts, reverse=True)
    pbd_dts = sorted(pbd_dts or dts, reverse=True)

    def levels(solver: Solver) -> list[float]:
        return pbd_dts if solver.name in ITERATIVE else dts

    for dt in dts + (pbd_dts if any(v.solver.name in ITERATIVE for v in variants) else []):
        steps_for(time_s, dt)  # refuse a bad --time before any work
    models: dict[tuple, tuple[Solver, float]] = {}  # key -> (solver, finest dt)
    verlet_key = None
    if variants:  # Verlet's first: every PBD model is compared with it
        verlet = as_verlet(variants[0].solver)
        verlet_key = model_key(scene, verlet)
        models[verlet_key] = (verlet, dts[-1])
    for v in variants:
        models.setdefault(model_key(scene, v.solver), (v.solver, levels(v.solver)[-1]))
    refs: dict[tuple, Reference] = {}
    run = runner(executor)
    pending, early = {}, {}
    if executor is not None:  # the levels every reference runs, side by side (the finest first)
        for key, (solver, finest) in models.items():
            safe = float64_state_fork_safe(solver)
            early[key] = {
                lvl: run(float64_state, scene, solver.replace(dt=dt), steps_for(time_s, dt), fork_safe=safe)
                for lvl, dt in ((lvl, finest / 2**lvl) for lvl in range(EARLY_LEVELS - 1, -1, -1))
            }
    else:
        for key, (solver, finest) in models.items():
            name = model_name(solver)
            note(f"converged float64 reference: {name}")
            on_level = lambda lvl, dt, name=name: note(f"reference {name} dt/2^{lvl} = {dt:.3g} s")  # noqa: E731
            pending[key] = run(converged_reference, scene, solver, time_s, finest, on_level=on_level)
    for key, levels_run in early.items():  # then each reference from them, the rows beside them
        solver, finest = models[key]
        note(f"converged float64 reference: {model_name(solver)}")
        runs_at = {}
        for lvl, got in levels_run.items():
            status, value = got()
            if status != "ok":
                raise ClothbenchError(f"the float64 reference {model_name(solver)} {status}: {value}")
            runs_at[lvl] = value
        pending[key] = run(converged_reference, scene, solver, time_s, finest, runs_at=runs_at)
    planned = []
    for v in variants:
        for dt in levels(v.solver):
            solver = v.solver.replace(dt=dt)
            if skip is not None and skip(v, solver):
                continue
            safe = fork_safe(v.backend, v.solver.name)
            planned.append((v, solver, run(_run_row, v, scene, solver, time_s, exact, fork_safe=safe)))
    for key, got in pending.items():
        status, value = got()
        if status != "ok":
            raise ClothbenchError(f"the float64 reference {model_name(models[key][0])} {status}: {value}")
        refs[key] = value
    verlet_ref = refs.get(verlet_key)
    rows: list[AccuracyRow] = []
    for v in variants:
        ref = refs[model_key(scene, v.solver)]
        mine = []
        for pv, solver, got in planned:
            if pv is not v:
                continue
            note(f"{v.backend} {v.solver.name} dt={solver.dt:.3g}")
            status, value = got()
            if status != "ok":
                row = _measure_failed(v, scene, solver, time_s, f"{status}: {value}")
                mine.append(_against(row, None, None, scene, solver, ref, verlet_ref))
            else:
                mine.append(_against(*value, scene, solver, ref, verlet_ref))
            if on_row is not None:
                on_row(mine[-1])
        fit_orders(mine)
        rows += mine
    named = {model_name(s): refs[k] for k, (s, _) in models.items()}
    # prev of a reference is at its own finest dt
    ref_bulk = {model_name(s): bulk(refs[k].pos, refs[k].prev, scene, refs[k].dt) for k, (s, _) in models.items()}
    differences = []
    if verlet_ref is not None:
        for k, (s, _) in models.items():
            if s.name in ITERATIVE:
                differences.append(model_difference(models[verlet_key][0], verlet_ref, s, refs[k]))
    first = next(iter(refs.values())) if refs else None
    return AccuracyResult(rows, first, references=named, differences=differences, ref_bulk=ref_bulk)


__all__ = [
    "dt_levels",
    "steps_for",
    "Reference",
    "converged_reference",
    "fit_order",
    "AccuracyRow",
    "AccuracyResult",
    "DOMINANCE",
    "discretisation_dominates",
    "fit_orders",
    "FITTED",
    "model_key",
    "ModelDifference",
    "model_difference",
    "structural_strain",
    "bulk",
    "run_accuracy",
]
