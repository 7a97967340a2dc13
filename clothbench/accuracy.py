"""Accuracy and stability: how wrong each backend is, what a larger dt costs, and where it breaks.

Two errors, both as RMS and max per-particle position distance (m) at a stated simulated time:

- implementation error: a backend's state against the NumPy float64 run of the same scene,
  dt and steps (float32 rounding, FMA contraction, built-ins);
- discretisation error: against a converged float64 reference of the same scene at the same
  simulated time (converged_reference says how "converged" is decided).

Stability: the largest dt that stays stable, measured by bisection, beside the limit of the
linearised flat lattice (lattice_omega2: the dynamical matrix over Bloch wave vectors) and the
Gershgorin bound 24 k/m. docs/accuracy.md has the numbers and the reasoning.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable

import numpy as np

from .backends import BACKENDS, BackendOptions, availability, create_backend
from .errors import ClothbenchError
from .harness.energy import energy_problem
from .harness.simulate import position_error, reference, simulate
from .harness.timing import run_timed
from .scene import OFFSETS, Scene

F64 = BackendOptions(precision="f64")


# --- which runs -------------------------------------------------------------------------


@dataclass(frozen=True)
class Variant:
    """One backend with one set of options: a line on every plot, a group of CSV rows."""

    backend: str
    options: BackendOptions
    overrides: tuple[tuple[str, object], ...] = ()

    def label(self, mode: str) -> str:
        """'backend mode', with the mode as the backend names it (Backend.mode)."""
        return f"{self.backend} {mode}"


def backend_variants(names: list[str]) -> tuple[list[Variant], list[tuple[str, str]]]:
    """Every usable backend in `names` with each of its sweep_variants; and (name, reason)
    for the ones that cannot run here."""
    usable, skipped = [], []
    for name in names:
        avail = availability(name)
        if not avail.usable:
            skipped.append((name, avail.reason))
            continue
        entry = BACKENDS[name]
        cls = getattr(importlib.import_module(f"clothbench.backends.{entry.module}"), entry.cls)
        for overrides in cls.sweep_variants:
            usable.append(Variant(name, BackendOptions(**overrides), tuple(overrides.items())))
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
    for level in range(1, max_levels + 1):
        dt = dt_finest / 2**level
        if on_level:
            on_level(level, dt)
        runs.append(simulate("numpy", scene.replace(dt=dt), steps_for(time_s, dt), F64)[0])
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
                return Reference(best, dt, level, order, change, True)
    if not extrapolated:
        return Reference(runs[-1], dt_finest / 2**max_levels, max_levels, order, float("nan"), False)
    change = _max(extrapolated[-1], extrapolated[-2]) if len(extrapolated) >= 2 else float("nan")
    return Reference(extrapolated[-1], dt_finest / 2**max_levels, max_levels, order, change, False)


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
    status: str = "ok"  # "ok", or "unstable at step N: ..."
    ms_per_step: float = float("nan")
    ms_per_sim_s: float = float("nan")  # cost: milliseconds of compute per simulated second
    impl_rms: float = float("nan")
    impl_max: float = float("nan")
    disc_rms: float = float("nan")
    disc_max: float = float("nan")
    ref_dt: float = float("nan")
    ref_converged: bool = False
    ref_uncertainty: float = float("nan")
    order: float = float("nan")  # fitted over this backend/mode's rows, same in each
    order_points: int = 0  # how many of its dts the fit used (discretisation_dominates)
    in_fit: bool = False  # whether this row is one of them

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class AccuracyResult:
    rows: list[AccuracyRow]
    reference: Reference
    skipped: list[tuple[str, str]] = field(default_factory=list)

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


def run_accuracy(
    scene: Scene,
    variants: list[Variant],
    dts: list[float],
    time_s: float,
    on_progress: Callable[[str], None] | None = None,
) -> AccuracyResult:
    """Every variant at every dt to `time_s`: cost, implementation and discretisation error."""
    note = on_progress or (lambda what: None)
    dts = sorted(dts, reverse=True)
    for dt in dts:
        steps_for(time_s, dt)  # refuse a bad --time before any work
    note("converged float64 reference")
    ref = converged_reference(
        scene, time_s, dts[-1], on_level=lambda lvl, dt: note(f"reference dt/2^{lvl} = {dt:.3g} s")
    )
    rows: list[AccuracyRow] = []
    for v in variants:
        mine = []
        for dt in dts:
            s = scene.replace(dt=dt)
            steps = steps_for(time_s, dt)
            note(f"{v.backend} dt={dt:.3g}")
            try:
                with create_backend(v.backend, s, v.options) as b:
                    result = run_timed(b, s, steps, raise_on_blowup=False)
            except Exception as e:  # a broken backend is a row saying so, not a dead command
                label = mine[0].label if mine else v.label(str(dict(v.overrides)))
                mine.append(
                    AccuracyRow(
                        scene.name, scene.grid, scene.start, scene.damping, time_s, v.backend,
                        label, "?", "?", dt, steps, status=f"error: {type(e).__name__}: {e}",
                    )
                )
                continue
            row = AccuracyRow(
                scene.name, scene.grid, scene.start, scene.damping, time_s, v.backend,
                v.label(result.mode), result.mode, result.device, dt, steps,
                ref_dt=ref.dt, ref_converged=ref.converged, ref_uncertainty=ref.uncertainty,
            )
            row.ms_per_step = result.ms_per_step
            row.ms_per_sim_s = result.ms_per_step / dt
            if result.blowup is not None:
                row.status = f"unstable at step {result.blowup.step}: {result.blowup.what}"
            else:
                row.impl_rms, row.impl_max = position_error(result.pos, reference(s, steps)[0])
                row.disc_rms, row.disc_max = position_error(result.pos, ref.pos)
            mine.append(row)
        used = [r for r in mine if discretisation_dominates(r, ref)]
        order = fit_order([r.dt for r in used], [r.disc_rms for r in used])
        for r in mine:
            r.order = order
            r.order_points = len(used)
            r.in_fit = r in used
        rows += mine
    return AccuracyResult(rows, ref)


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


def is_stable(
    variant: Variant, scene: Scene, start: tuple[np.ndarray, np.ndarray], steps: int, chunk: int = 100
) -> tuple[bool, str | None, str]:
    """Run `steps` steps of `scene` from `start`; (stable, what went wrong if not, the
    backend's mode).

    Unstable: a position not finite, or the total energy past its bound (energy_problem).
    The harness's runaway-speed rule (100 m/s + 2 g t) is left out here on purpose: it is not
    scale-free, and a stiff sheet released from a squeezed start legitimately moves faster
    than 100 m/s at k = 1e5 (speeds grow as sqrt(k/m)), which would read as instability.
    The energy rule scales with the scene, so the measured dt * sqrt(k/m) does not depend on k.
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
            problem = energy_problem(pos, prev, scene, done, start=start)
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
    dt_unstable: float  # the smallest dt found unstable
    predicted: float | None  # the linearised limit that applies to this scene, if any
    flat_predicted: float  # the flat-lattice limit for the same k, m, b
    gershgorin: float  # the limit from omega^2 = 24 k/m
    probes: int
    note: str = ""

    @property
    def ratio(self) -> float | None:
        """measured / predicted (the applicable prediction)."""
        return self.dt_stable / self.predicted if self.predicted else None

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        d["ratio"] = self.ratio
        d["ratio_to_flat"] = self.dt_stable / self.flat_predicted
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
) -> StabilityRow:
    """Bisection (in log dt) for the largest stable dt, to a bracket hi/lo < 1 + rtol.

    Starts from [0.5, 1.2] x the flat-lattice prediction and widens until the bracket holds."""
    base = stability_scene(kind, stiffness, grid, damping)
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

    lo, hi = 0.5 * flat, 1.2 * flat
    while not stable(lo):
        hi, lo = lo, lo / 2
        if lo < 1e-4 * flat:
            raise ClothbenchError(f"{kind} k={stiffness:g} on {variant.backend}: unstable at every dt tried")
    while stable(hi):
        lo, hi = hi, hi * 2
        if hi > 100 * flat:
            raise ClothbenchError(f"{kind} k={stiffness:g} on {variant.backend}: stable at every dt tried")
    while hi / lo > 1 + rtol:
        mid = math.sqrt(lo * hi)
        if stable(mid):
            lo = mid
        else:
            hi = mid
    scene = base.replace(dt=lo)
    return StabilityRow(
        kind, stiffness, damping, grid, steps, variant.backend,
        variant.label(mode), lo, hi,
        predicted_for(kind, scene), flat, gershgorin_dt_max(scene), probes, last_problem,
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
]
