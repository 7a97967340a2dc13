"""Accuracy and stability: how wrong each backend is, what a larger dt costs, and where it breaks.

Two errors, both as RMS and max per-particle position distance (m) at a stated simulated time:

- implementation error: a backend's state against the NumPy float64 run of the same scene,
  dt and steps (float32 rounding, FMA contraction, built-ins);
- discretisation error: against a converged float64 reference of the same scene at the same
  simulated time (converged_reference says how "converged" is decided).

Stability: the largest dt that stays stable, measured by bisection, beside the limit of the
linearised flat lattice (lattice_omega2: the dynamical matrix over Bloch wave vectors) and the
Gershgorin bound 24 k/m. docs/accuracy.md has the numbers and the reasoning.

Both solvers (docs/pbd.md): every measurement takes the solver as one more dimension. A PBD
line's discretisation error is against the converged reference of its *own* model (the same
method, iterations, substeps and relaxation, dt -> 0), and the difference between the two
models' converged answers is measured and reported beside it (model_difference). PBD's
stability is bisected like Verlet's, under a cap (PBD_CAP): "stable up to the cap".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np

from .backends import BackendOptions, availability, backend_class, create_backend
from .errors import ClothbenchError
from .harness.energy import energy_problem, energy_scale, total_energy
from .harness.simulate import position_error, reference, simulate
from .harness.timing import run_timed
from .scene import OFFSETS, PBD_METHODS, SOLVERS, Scene

F64 = BackendOptions(precision="f64")


# --- which runs -------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """One backend with one set of options and one solver: a line on every plot, a group of
    CSV rows. For solver "pbd", pbd_method and iterations (None: the scene's) say which PBD."""

    backend: str
    options: BackendOptions
    overrides: tuple[tuple[str, object], ...] = ()
    solver: str = "verlet"
    pbd_method: str | None = None
    iterations: int | None = None

    @property
    def pbd(self) -> bool:
        return self.solver == "pbd"

    def scene(self, base: Scene) -> Scene:
        """`base` with this variant's solver (and PBD method and iterations) applied."""
        if not self.pbd:
            return base.replace(solver="verlet")
        changes: dict = {"solver": "pbd"}
        if self.pbd_method is not None:
            changes["pbd_method"] = self.pbd_method
        if self.iterations is not None:
            changes["iterations"] = self.iterations
        return base.replace(**changes)

    def label(self, mode: str, scene: Scene | None = None) -> str:
        """'backend mode', with the mode as the backend names it (Backend.mode); a PBD mode
        names its method ('f32/pbd-jacobi'), and the label adds the iterations (and the
        substeps when more than one): 'numpy f32/pbd-jacobi/10it'."""
        if not self.pbd:
            return f"{self.backend} {mode}"
        s = self.scene(scene or Scene())
        if "pbd-" not in mode:
            mode = f"{mode}/pbd-{s.pbd_method}"
        sub = f"x{s.substeps}" if s.substeps > 1 else ""
        return f"{self.backend} {mode}/{s.iterations}it{sub}"


def backend_variants(
    names: list[str],
    solvers: tuple[str, ...] | list[str] = ("verlet",),
    pbd_methods: tuple[str | None, ...] | list[str | None] = (None,),
    iterations: tuple[int | None, ...] | list[int | None] = (None,),
) -> tuple[list[Variant], list[tuple[str, str]]]:
    """Every usable backend in `names` with each of its sweep_variants, per solver (PBD: per
    method and iteration count; None: the scene's); and (name, reason) for the ones that
    cannot run here, or have no class for a solver (named 'name (pbd)')."""
    usable, skipped = [], []
    for solver in solvers:
        if solver not in SOLVERS:
            raise ClothbenchError(f"unknown solver {solver!r} (known: {', '.join(SOLVERS)})")
        for name in names:
            avail = availability(name)
            if not avail.usable:
                if solver == solvers[0]:  # said once, not once per solver
                    skipped.append((name, avail.reason))
                continue
            try:
                cls = backend_class(name, solver)
            except Exception as e:  # a half-written backend module is reported, not fatal
                skipped.append((f"{name} ({solver})", f"cannot load its {solver} class: {type(e).__name__}: {e}"))
                continue
            if cls is None:
                skipped.append((f"{name} ({solver})", f"{name} has no {solver} solver"))
                continue
            pbd_runs = [(m, it) for m in pbd_methods for it in iterations] if solver == "pbd" else [(None, None)]
            for method, its in pbd_runs:
                for overrides in cls.sweep_variants:
                    usable.append(
                        Variant(name, BackendOptions(**overrides), tuple(overrides.items()), solver, method, its)
                    )
    return usable, skipped


# --- convergence ------------------------------------------------------------------------


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
    time_s: float,
    dt_finest: float,
    rtol: float = 0.02,
    max_levels: int = 5,
    on_level: Callable[[int, float], None] | None = None,
) -> Reference:
    """The float64 state at `time_s`, refined until it stops changing.

    Runs the NumPy float64 step at dt_finest/2, /4, ... and extrapolates each pair (Richardson,
    with the order the last three runs show, clamped to [0.5, 4]). It is converged when two
    successive extrapolations differ (max norm) by less than `rtol` times the smallest error it
    will be compared with: the float64 error of the finest measured dt. Not converged after
    `max_levels` halvings: the last extrapolation is returned with converged=False, and the
    caller says so (errors smaller than `uncertainty` then mean nothing).
    """
    runs = [reference(scene.replace(dt=dt_finest), steps_for(time_s, dt_finest))[0]]
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
        pos, prev = simulate("numpy", scene.replace(dt=dt), steps_for(time_s, dt), F64)
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
    iterations: int | None = None  # PBD only
    substeps: int | None = None  # PBD only
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

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        for k in ("pbd_method", "iterations", "substeps"):
            if d[k] is None:
                d[k] = ""
        return d


def model_name(scene: Scene) -> str:
    """The model a converged reference is of: 'verlet', or 'pbd-jacobi/10it (relaxation 1.5)'."""
    if scene.solver != "pbd":
        return "verlet"
    sub = f"x{scene.substeps}" if scene.substeps > 1 else ""
    relax = f", relaxation {scene.relaxation:g}" if scene.pbd_method == "jacobi" else ""
    comp = "" if scene.compliance is None else f", compliance {list(scene.compliance)}"
    return f"pbd-{scene.pbd_method}/{scene.iterations}it{sub}{relax}{comp}"


def model_key(scene: Scene) -> Scene:
    """What identifies a model: the scene without its dt (and with the PBD fields that do not
    apply to Verlet reset), so every dt of one model shares one converged reference."""
    s = scene.replace(dt=Scene.dt, steps=Scene.steps)
    if s.solver != "pbd":
        s = s.replace(pbd_method=Scene.pbd_method, iterations=Scene.iterations,
                      substeps=Scene.substeps, relaxation=Scene.relaxation, compliance=None)
    return s


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


DOMINANCE = 10.0  # a point enters the order fit when discretisation is 10x everything else


def discretisation_dominates(row: AccuracyRow, ref: Reference) -> bool:
    """Whether row's error to the converged reference is discretisation error: at least
    DOMINANCE times its implementation error (rounding, which in float32 grows as dt shrinks)
    and times the reference's own uncertainty."""
    unc = ref.uncertainty if math.isfinite(ref.uncertainty) else 0.0
    return (
        row.status == "ok"
        and row.disc_rms > DOMINANCE * row.impl_rms
        and row.disc_max > DOMINANCE * unc
    )


def structural_strain(pos: np.ndarray, scene: Scene) -> float:
    """Mean |L/rest - 1| over the structural springs: how stretched the cloth is. A solver
    that under-resolves its constraints (PBD at few iterations) shows it as extra strain."""
    n = scene.grid
    x = pos[:, :3].astype(np.float64).reshape(n, n, 3)
    lengths = np.concatenate(
        [np.linalg.norm(x[:, 1:] - x[:, :-1], axis=2).ravel(), np.linalg.norm(x[1:] - x[:-1], axis=2).ravel()]
    )
    return float(np.abs(lengths / scene.spacing - 1).mean())


def bulk(pos: np.ndarray, prev: np.ndarray, scene: Scene) -> tuple[float, float]:
    """(mean structural strain, kinetic energy in J) of a state: what a softer or more
    damped model changes, and what position error alone does not separate."""
    with np.errstate(all="ignore"):
        return structural_strain(pos, scene), total_energy(pos, prev, scene).kinetic


def model_difference(a_scene: Scene, a: Reference, b_scene: Scene, b: Reference) -> ModelDifference:
    rms, mx = position_error(a.pos, b.pos)
    unc = [u for u in (a.uncertainty, b.uncertainty) if math.isfinite(u)]
    return ModelDifference(
        model_name(a_scene), model_name(b_scene), rms, mx, max(unc) if unc else float("nan"),
        a.converged and b.converged,
    )


def run_accuracy(
    scene: Scene,
    variants: list[Variant],
    dts: list[float],
    time_s: float,
    on_progress: Callable[[str], None] | None = None,
    pbd_dts: list[float] | None = None,
) -> AccuracyResult:
    """Every variant at every dt to `time_s`: cost, implementation and discretisation error.

    Verlet variants run `dts`, PBD variants `pbd_dts` (default the same). Each model (the
    solver with its PBD method, iterations, substeps, relaxation) gets its own converged
    float64 reference, refined below its finest dt; when PBD is measured, Verlet's reference
    is computed too (below min(dts)), every row's error against it is written (vs_verlet_*),
    and the distance between the converged answers of Verlet and each PBD model is returned
    in `differences`."""
    note = on_progress or (lambda what: None)
    dts = sorted(dts, reverse=True)
    pbd_dts = sorted(pbd_dts or dts, reverse=True)
    for dt in dts + (pbd_dts if any(v.pbd for v in variants) else []):
        steps_for(time_s, dt)  # refuse a bad --time before any work
    verlet_scene = scene.replace(solver="verlet")
    models: dict[Scene, tuple[Scene, float]] = {}  # key -> (scene, finest dt)
    if variants:  # Verlet's first: every PBD model is compared with it
        models[model_key(verlet_scene)] = (verlet_scene, dts[-1])
    for v in variants:
        s = v.scene(scene)
        models.setdefault(model_key(s), (s, (pbd_dts if v.pbd else dts)[-1]))
    refs: dict[Scene, Reference] = {}
    for key, (s, finest) in models.items():
        name = model_name(s)
        note(f"converged float64 reference: {name}")
        refs[key] = converged_reference(
            s, time_s, finest, on_level=lambda lvl, dt, name=name: note(f"reference {name} dt/2^{lvl} = {dt:.3g} s")
        )
    verlet_ref = refs.get(model_key(verlet_scene))
    rows: list[AccuracyRow] = []
    for v in variants:
        vscene = v.scene(scene)
        ref = refs[model_key(vscene)]
        mine = []
        pbd_fields = (
            dict(pbd_method=vscene.pbd_method, iterations=vscene.iterations, substeps=vscene.substeps)
            if v.pbd else {}
        )
        for dt in pbd_dts if v.pbd else dts:
            s = vscene.replace(dt=dt)
            steps = steps_for(time_s, dt)
            note(f"{v.backend} {vscene.solver} dt={dt:.3g}")
            try:
                with create_backend(v.backend, s, v.options) as b:
                    result = run_timed(b, s, steps, raise_on_blowup=False)
            except Exception as e:  # a broken backend is a row saying so, not a dead command
                label = mine[0].label if mine else v.label(str(dict(v.overrides)), scene)
                mine.append(
                    AccuracyRow(
                        scene.name, scene.grid, scene.start, scene.damping, time_s, v.backend,
                        label, "?", "?", dt, steps, vscene.solver, **pbd_fields,
                        status=f"error: {type(e).__name__}: {e}", ref_model=model_name(vscene),
                    )
                )
                continue
            row = AccuracyRow(
                scene.name, scene.grid, scene.start, scene.damping, time_s, v.backend,
                v.label(result.mode, scene), result.mode, result.device, dt, steps, vscene.solver,
                **pbd_fields, ref_model=model_name(vscene), ref_dt=ref.dt,
                ref_converged=ref.converged, ref_uncertainty=ref.uncertainty,
            )
            row.ms_per_step = result.ms_per_step
            row.ms_per_sim_s = result.ms_per_step / dt
            if result.blowup is not None:
                row.status = f"unstable at step {result.blowup.step}: {result.blowup.what}"
            else:
                row.impl_rms, row.impl_max = position_error(result.pos, reference(s, steps)[0])
                row.disc_rms, row.disc_max = position_error(result.pos, ref.pos)
                if verlet_ref is not None:
                    row.vs_verlet_rms, row.vs_verlet_max = position_error(result.pos, verlet_ref.pos)
                row.strain, row.kinetic_j = bulk(result.pos, result.prev, s)
            mine.append(row)
        used = [r for r in mine if discretisation_dominates(r, ref)]
        order = fit_order([r.dt for r in used], [r.disc_rms for r in used])
        for r in mine:
            r.order = order
            r.order_points = len(used)
            r.in_fit = r in used
        rows += mine
    named = {model_name(s): refs[k] for k, (s, _) in models.items()}
    ref_bulk = {}
    for k, (s, _) in models.items():
        r = refs[k]
        ref_bulk[model_name(s)] = bulk(r.pos, r.prev, s.replace(dt=r.dt))  # prev is at r.dt
    differences = []
    if verlet_ref is not None:
        for k, (s, _) in models.items():
            if s.solver == "pbd":
                differences.append(model_difference(verlet_scene, verlet_ref, s, refs[k]))
    first = next(iter(refs.values())) if refs else None
    return AccuracyResult(rows, first, references=named, differences=differences, ref_bulk=ref_bulk)


# --- what PBD gets wrong: softness and damping -------------------------------------------

SETTLE_DAMPING = 0.005  # N s/m: near critical for the hanging sheet's swing, settled in SETTLE_S
SETTLE_S = 3.0  # s: the largest speed left is below 0.03 m/s and the strain steady to 4 digits
SWING_S = 2.0  # s of undamped motion over which the energy change is measured


@dataclass
class ArtefactRow:
    """One solver setting against the mass-spring model, measured where chaos does not
    matter: the strain of the cloth at rest (settled with light damping), and the energy an
    undamped run gains or loses."""

    scene: str
    grid: int
    model: str
    solver: str
    pbd_method: str
    iterations: int | None
    dt: float
    hanging_strain: float  # mean structural strain at rest after SETTLE_S
    strain_ratio: float  # hanging_strain / Verlet's: > 1 is a softer (stretchier) cloth
    settle_speed: float  # largest particle speed left after SETTLE_S (m/s)
    energy_change: float  # (E(SWING_S) - E(0)) / (M g L), b = 0, E with k-springs
    ms_per_sim_s: float  # cost of the swing run, numpy float64 (indicative only)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        if d["iterations"] is None:
            d["iterations"] = ""
        return d


def _settle_and_swing(scene: Scene) -> tuple[float, float, float, float]:
    """(hanging strain, settle speed, energy change, ms per simulated second) of `scene`."""
    import time

    rest = scene.replace(damping=SETTLE_DAMPING)
    pos, prev = simulate("numpy", rest, max(1, round(SETTLE_S / rest.dt)), F64)
    speed = float(np.sqrt(((pos[:, :3] - prev[:, :3]) ** 2).sum(axis=1)).max() / rest.dt)
    strain = structural_strain(pos, rest)
    swing = scene.replace(damping=0.0)
    springs = swing.replace(solver="verlet")  # E with the k-spring (XPBD: C^2 / 2 compliance) potential
    e0 = total_energy(*swing.initial_state(np.float64), springs).total
    t0 = time.perf_counter()
    steps = max(1, round(SWING_S / swing.dt))
    pos, prev = simulate("numpy", swing, steps, F64)
    ms = 1e3 * (time.perf_counter() - t0) / (steps * swing.dt)
    with np.errstate(all="ignore"):
        e = total_energy(pos, prev, springs).total
    g = math.sqrt(sum(c * c for c in scene.gravity)) or 1.0
    scale = scene.mass * int((pos[:, 3] != 0).sum()) * g * scene.size
    return strain, speed, (e - e0) / scale, ms


def solver_artefacts(
    scene: Scene,
    methods: tuple[str, ...] = PBD_METHODS,
    iterations: tuple[int, ...] = (3, 10, 30, 100),
    dts: tuple[float, ...] = (1 / 60, 1 / 120, 1 / 240),
    on_progress: Callable[[str], None] | None = None,
) -> list[ArtefactRow]:
    """Softness and damping of PBD against Verlet, on the NumPy float64 reference.

    Verlet runs at the scene's dt. Each PBD method runs every iteration count at dts[0], and
    the scene's iteration count at the other dts: softness comes from too few iterations
    (the constraints are not resolved: the cloth at rest stretches more than k says), extra
    damping from the large step (the implicit position projection removes energy; at
    converged iterations it remains). The energy change is only a damping measure where the
    strain is about right (strain_ratio near 1): an over-stretched cloth holds more k-spring
    energy than it was given."""
    note = on_progress or (lambda what: None)
    base = scene.replace(solver="verlet")
    note("verlet: settle and swing")
    v_strain, v_speed, v_energy, v_ms = _settle_and_swing(base)
    rows = [
        ArtefactRow(scene.name, scene.grid, "verlet", "verlet", "", None, base.dt, v_strain, 1.0,
                    v_speed, v_energy, v_ms)
    ]
    for method in methods:
        runs = [(it, dts[0]) for it in iterations] + [(scene.iterations, dt) for dt in dts[1:]]
        for it, dt in dict.fromkeys(runs):
            s = scene.replace(solver="pbd", pbd_method=method, iterations=it, dt=dt)
            note(f"pbd-{method} {it} it, dt {dt:.3g}: settle and swing")
            strain, speed, energy, ms = _settle_and_swing(s)
            rows.append(
                ArtefactRow(scene.name, scene.grid, model_name(s), "pbd", method, it, dt, strain,
                            strain / v_strain if v_strain > 0 else float("nan"), speed, energy, ms)
            )
    return rows


# --- linearised stability ---------------------------------------------------------------


def dynamical_matrix(q: np.ndarray, stretch: float = 1.0) -> np.ndarray:
    """D(q) / (k/m) for Bloch wave vectors q (..., 2) = (q_col, q_row), as (..., 3, 3).

    The infinite lattice of the 12-spring stencil, every spring at `stretch` times its rest
    length. Linearising the spring force about a spring of direction e and length L gives the
    stiffness k [e e^T + (1 - rest/L)(I - e e^T)]: along the spring k, across it the tension.
    At rest length (stretch 1) the sheet has no stiffness out of its plane.
    """
    q = np.asarray(q, dtype=np.float64)
    out = np.zeros(q.shape[:-1] + (3, 3))
    tension = 1.0 - 1.0 / stretch
    for dr, dc in OFFSETS:
        e = np.array([dc, 0.0, dr]) / math.hypot(dr, dc)  # col -> x, row -> z
        along = np.outer(e, e)
        block = along + tension * (np.eye(3) - along)
        out += (1.0 - np.cos(q[..., 0] * dc + q[..., 1] * dr))[..., None, None] * block
    return out


@lru_cache(maxsize=16)
def lattice_omega2(stretch: float = 1.0) -> float:
    """max over q of the largest eigenvalue of D(q), in units of k/m (10.25 at stretch 1).

    A 61x61 grid over [0, pi]^2 (the lattice's mirror symmetries cover the rest of the
    Brillouin zone), then the best point refined by zooming in eight times."""
    lo, hi = np.zeros(2), np.full(2, math.pi)
    best, width = None, math.pi
    for _ in range(9):
        a = np.linspace(lo[0], hi[0], 61)
        b = np.linspace(lo[1], hi[1], 61)
        qs = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1)
        w = np.linalg.eigvalsh(dynamical_matrix(qs, stretch))[..., -1]
        i = np.unravel_index(np.argmax(w), w.shape)
        best = float(w[i])
        width /= 10
        centre = qs[i]
        lo = np.clip(centre - width, 0, math.pi)
        hi = np.clip(centre + width, 0, math.pi)
    return best


GERSHGORIN = 24.0  # omega^2 <= 24 k/m: 12 springs, each adding k to the diagonal and k off it


def omega_max(k: float, m: float, stretch: float = 1.0) -> float:
    """Largest natural frequency (rad/s) of the infinite flat lattice at `stretch`."""
    return math.sqrt(lattice_omega2(stretch) * k / m)


def gershgorin_omega(k: float, m: float) -> float:
    return math.sqrt(GERSHGORIN * k / m)


def dt_limit(omega: float, damping_rate: float = 0.0) -> float:
    """Largest stable dt of x' = 2x - x_p - w^2 dt^2 x - beta dt (x - x_p) (Verlet with the
    lagged-velocity drag beta = 12 b / m): the Jury condition w^2 dt^2 + 2 beta dt < 4.
    With beta = 0 this is w dt < 2."""
    if damping_rate == 0.0:
        return 2.0 / omega
    beta = damping_rate
    return (-beta + math.sqrt(beta * beta + 4 * omega * omega)) / (omega * omega)


def damping_rate(scene: Scene) -> float:
    """beta = 12 b / m: an interior particle's drag rate (the damping acts once per spring)."""
    return 12 * scene.damping / scene.mass


def predicted_dt_max(scene: Scene, stretch: float = 1.0) -> float:
    """Flat-lattice (at `stretch`) stability limit of `scene`'s k, m and b."""
    return dt_limit(omega_max(scene.stiffness, scene.mass, stretch), damping_rate(scene))


def gershgorin_dt_max(scene: Scene) -> float:
    return dt_limit(gershgorin_omega(scene.stiffness, scene.mass), damping_rate(scene))


def finite_grid_omega2(n: int, stretch: float = 1.0) -> float:
    """The largest eigenvalue (units of k/m) of the free n x n grid's stiffness matrix at
    `stretch` (dense, so n <= ~30): at most lattice_omega2, approaching it as n grows."""
    dim = 3 * n * n
    K = np.zeros((dim, dim))
    tension = 1.0 - 1.0 / stretch
    for dr, dc in OFFSETS:
        e = np.array([dc, 0.0, dr]) / math.hypot(dr, dc)
        block = np.outer(e, e) + tension * (np.eye(3) - np.outer(e, e))
        for r in range(n):
            for c in range(n):
                if 0 <= r + dr < n and 0 <= c + dc < n:
                    i, j = 3 * (r * n + c), 3 * ((r + dr) * n + c + dc)
                    K[i : i + 3, i : i + 3] += block
                    K[i : i + 3, j : j + 3] -= block
    return float(np.linalg.eigvalsh(K)[-1])


# --- measured stability -----------------------------------------------------------------

STABILITY_SCENES = ("flat", "stretched", "crumpled")
STRETCH = 1.5  # the stretched scene's strain: every spring at 1.5x its rest length
SQUEEZE = 0.6  # the crumpled scene: the sheet squeezed to 60 % in its plane, then buckled
PERTURBATION = 1e-3  # in-plane perturbation of the flat scene, as a fraction of h


def stability_scene(kind: str, stiffness: float, grid: int = 24, damping: float = 0.002) -> Scene:
    """The scene of a stability measurement: no gravity (a uniform acceleration does not
    change the internal dynamics). The stretched sheet is held by a border two particles
    deep, so every free particle has all 12 springs and the uniform stretch is an exact
    equilibrium (with one row, the missing bend springs pull the second row inwards)."""
    if kind not in STABILITY_SCENES:
        raise ClothbenchError(f"unknown stability scene {kind!r} (known: {', '.join(STABILITY_SCENES)})")
    pins: tuple[int, ...] = ()
    if kind == "stretched":
        n = grid
        border = (0, 1, n - 2, n - 1)
        pins = tuple(i for i in range(n * n) if i // n in border or i % n in border)
    return Scene(
        name=f"stability-{kind}", grid=grid, stiffness=stiffness, damping=damping,
        gravity=(0.0, 0.0, 0.0), pin_indices=pins,
    )


def stability_state(scene: Scene, kind: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The float64 start of a stability run, at rest (prev = pos).

    flat: the sheet at rest length with a random in-plane displacement of PERTURBATION * h,
    so only the linearised in-plane modes are excited. stretched: scaled by STRETCH about its
    centre in its plane (border pinned there), plus the same small perturbation in all three
    directions. crumpled: squeezed to SQUEEZE in its plane and given a random out-of-plane
    displacement of h, so it buckles, folds and springs shorten, lengthen and line up.
    """
    rng = np.random.default_rng(seed)
    pos, _ = scene.initial_state(np.float64)
    h = scene.spacing
    xyz = pos[:, :3]
    centre = xyz.mean(axis=0)
    if kind == "flat":
        xyz[:, [0, 2]] += PERTURBATION * h * rng.uniform(-1, 1, (len(xyz), 2))
    elif kind == "stretched":
        xyz[:, [0, 2]] = centre[[0, 2]] + STRETCH * (xyz[:, [0, 2]] - centre[[0, 2]])
        free = pos[:, 3] != 0
        xyz[free] += PERTURBATION * h * rng.uniform(-1, 1, (int(free.sum()), 3))
    elif kind == "crumpled":
        xyz[:, [0, 2]] = centre[[0, 2]] + SQUEEZE * (xyz[:, [0, 2]] - centre[[0, 2]])
        xyz[:, 1] += h * rng.uniform(-1, 1, len(xyz))
    return pos, pos.copy()


def predicted_for(kind: str, scene: Scene) -> float | None:
    """The linearised prediction that applies to a stability scene (None for crumpled)."""
    if kind == "flat":
        return predicted_dt_max(scene)
    if kind == "stretched":
        return predicted_dt_max(scene, STRETCH)
    return None


PBD_CAP = 0.1  # s: the largest dt the PBD bisection tries; stable there = "stable up to the cap"
DT_60HZ = 1.0 / 60.0  # the frame time at which PBD is claimed to stay stable and Verlet not


def stability_problem(
    pos: np.ndarray, prev: np.ndarray, scene: Scene, step: int, start: tuple[np.ndarray, np.ndarray]
) -> str | None:
    """energy_problem for a run released from `start`, for either solver.

    For PBD the watched energy is kinetic + gravitational (energy.py: its constraints are not
    k-springs), but a PBD cloth released from a strained start (stretched, crumpled) turns the
    strain into motion, as Verlet's does. So the bound's scale also holds the start's elastic
    energy, sum C^2 / (2 compliance): the XPBD potential, k (L - rest)^2 / 2 at the default
    compliance 1/k. Without it the crumpled sheet springing open reads as a blow-up."""
    if scene.solver != "pbd":
        return energy_problem(pos, prev, scene, step, start=start)
    springs = scene.replace(solver="verlet", stiffness=1.0 / max(min(scene.pbd_compliance()), 1e-300))
    e0 = total_energy(*start, scene).watched(scene)
    limit = e0 + energy_scale(springs, *start)
    with np.errstate(all="ignore"):
        e = total_energy(pos, prev, scene).watched(scene)
    if not math.isfinite(e):
        return "the kinetic energy is not finite"
    if e > limit:
        return (
            f"the kinetic + gravitational energy grew from {e0:.4g} J to {e:.4g} J, past the "
            f"bound {limit:.4g} J (start energy + strain energy + scale)"
        )
    return None


def is_stable(
    variant: Variant, scene: Scene, start: tuple[np.ndarray, np.ndarray], steps: int, chunk: int = 100
) -> tuple[bool, str | None, str]:
    """Run `steps` steps of `scene` from `start`; (stable, what went wrong if not, the
    backend's mode).

    Unstable: a position not finite, or the total energy past its bound (energy_problem;
    for PBD stability_problem). The harness's runaway-speed rule (100 m/s + 2 g t) is left out
    here on purpose: it is not scale-free, and a stiff sheet released from a squeezed start
    legitimately moves faster than 100 m/s at k = 1e5 (speeds grow as sqrt(k/m)), which
    would read as instability. The energy rule scales with the scene, so the measured
    dt * sqrt(k/m) does not depend on k.
    """
    dtype = variant.options.dtype
    with create_backend(variant.backend, scene, variant.options) as b:
        b.upload(start[0].astype(dtype), start[1].astype(dtype))
        done = 0
        while done < steps:
            c = min(chunk, steps - done)
            b.advance(c)
            done += c
            pos, prev = b.read()
            if not (np.isfinite(pos[:, :3]).all() and np.isfinite(prev[:, :3]).all()):
                return False, f"step <= {done}: a position is not finite (NaN or Inf)", b.mode
            problem = stability_problem(pos, prev, scene, done, start)
            if problem:
                return False, f"step <= {done}: {problem}", b.mode
        return True, None, b.mode


@dataclass
class StabilityRow:
    kind: str
    stiffness: float
    damping: float
    grid: int
    steps: int
    backend: str
    label: str
    dt_stable: float  # the largest dt found stable
    dt_unstable: float  # the smallest dt found unstable (NaN: stable up to the cap)
    predicted: float | None  # the linearised limit that applies to this scene, if any
    flat_predicted: float  # the flat-lattice limit (explicit Verlet) for the same k, m, b
    gershgorin: float  # the limit from omega^2 = 24 k/m
    probes: int
    note: str = ""
    solver: str = "verlet"
    pbd_method: str = ""  # PBD only
    iterations: int | None = None  # PBD only
    capped: bool = False  # stable at the cap: the true limit is at least dt_stable
    cap: float | None = None  # the largest dt tried (PBD); None: no cap
    at_60hz: str = ""  # "stable" or "unstable (step <= N: ...)" at dt = 1/60 s, same steps

    @property
    def ratio(self) -> float | None:
        """measured / predicted (the applicable prediction)."""
        return self.dt_stable / self.predicted if self.predicted else None

    @property
    def stable_at_60hz(self) -> bool | None:
        return None if not self.at_60hz else self.at_60hz == "stable"

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["ratio"] = self.ratio
        d["ratio_to_flat"] = self.dt_stable / self.flat_predicted
        d["stable_at_60hz"] = self.stable_at_60hz
        if d["iterations"] is None:
            d["iterations"] = ""
        return d


def measure_stability_limit(
    variant: Variant,
    kind: str,
    stiffness: float,
    steps: int = 2000,
    grid: int = 24,
    damping: float = 0.002,
    rtol: float = 0.005,
    seed: int = 0,
    cap: float | None = None,
    check_60hz: bool = False,
) -> StabilityRow:
    """Bisection (in log dt) for the largest stable dt, to a bracket hi/lo < 1 + rtol.

    Starts from [0.5, 1.2] x the flat-lattice prediction and widens until the bracket holds.
    With a `cap` (default PBD_CAP for a PBD variant, none for Verlet) the cap is tried first:
    stable there, the row says "stable up to the cap" (capped) without bisecting; otherwise
    the bracket never widens past it. check_60hz also runs dt = 1/60 s for the same steps and
    writes the verdict to at_60hz."""
    base = variant.scene(stability_scene(kind, stiffness, grid, damping))
    if cap is None and variant.pbd:
        cap = PBD_CAP
    start = stability_state(base, kind, seed)
    flat = predicted_dt_max(base)
    probes = 0
    last_problem = ""
    mode = "?"

    def stable(dt: float) -> bool:
        nonlocal probes, last_problem, mode
        probes += 1
        ok, problem, mode = is_stable(variant, base.replace(dt=dt), start, steps)
        if not ok:
            last_problem = problem
        return ok

    at_60hz = ""
    if check_60hz:
        ok, problem, mode = is_stable(variant, base.replace(dt=DT_60HZ), start, steps)
        at_60hz = "stable" if ok else f"unstable ({problem})"

    capped = False
    if cap is not None and stable(cap):
        lo, hi, capped = cap, float("nan"), True
        last_problem = f"stable up to the cap ({cap:g} s): the limit is at least that"
    else:
        lo, hi = 0.5 * flat, 1.2 * flat
        if cap is not None:
            lo, hi = min(lo, cap / 2), min(hi, cap)
        while not stable(lo):
            hi, lo = lo, lo / 2
            if lo < 1e-4 * flat:
                raise ClothbenchError(f"{kind} k={stiffness:g} on {variant.backend}: unstable at every dt tried")
        while (cap is None or hi < cap) and stable(hi):  # the cap is known unstable
            lo, hi = hi, hi * 2
            if cap is not None:
                hi = min(hi, cap)
            elif hi > 100 * flat:
                raise ClothbenchError(f"{kind} k={stiffness:g} on {variant.backend}: stable at every dt tried")
        while hi / lo > 1 + rtol:
            mid = math.sqrt(lo * hi)
            if stable(mid):
                lo = mid
            else:
                hi = mid
    scene = base.replace(dt=lo)
    pbd = dict(pbd_method=base.pbd_method, iterations=base.iterations) if variant.pbd else {}
    return StabilityRow(
        kind, stiffness, damping, grid, steps, variant.backend,
        variant.label(mode, base), lo, hi,
        predicted_for(kind, scene) if not variant.pbd else None, flat, gershgorin_dt_max(scene),
        probes, last_problem, solver=base.solver, capped=capped, cap=cap, at_60hz=at_60hz, **pbd,
    )


__all__ = [
    "Variant",
    "backend_variants",
    "dt_levels",
    "steps_for",
    "converged_reference",
    "fit_order",
    "run_accuracy",
    "AccuracyRow",
    "AccuracyResult",
    "dynamical_matrix",
    "lattice_omega2",
    "omega_max",
    "gershgorin_omega",
    "dt_limit",
    "predicted_dt_max",
    "gershgorin_dt_max",
    "finite_grid_omega2",
    "stability_scene",
    "stability_state",
    "is_stable",
    "measure_stability_limit",
    "StabilityRow",
    "stability_problem",
    "PBD_CAP",
    "DT_60HZ",
    "model_name",
    "model_difference",
    "ModelDifference",
    "structural_strain",
    "solver_artefacts",
    "ArtefactRow",
]
