"""The measured stability limit: the largest dt that stays stable, by bisection, on three
scenes (flat, stretched, crumpled), beside the linearised limits of lattice.py.

Every solver: PBD's and VBD's stability is bisected like Verlet's, under a cap (PBD_CAP):
"stable up to the cap". docs/accuracy.md has the numbers and the reasoning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothbench import environment
from clothbench.analysis.lattice import gershgorin_dt_max, predicted_dt_max
from clothbench.backends import create_backend
from clothbench.errors import ClothbenchError
from clothbench.harness import faults
from clothbench.harness.energy import ENERGY_GROWTH, energy_bound, energy_past, energy_problem, total_energy
from clothbench.harness.plan import Variant
from clothbench.model.scene import Scene
from clothbench.model.solver import ITERATIVE, Solver

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
        name=f"stability-{kind}",
        grid=grid,
        stiffness=stiffness,
        damping=damping,
        gravity=(0.0, 0.0, 0.0),
        pin_indices=pins,
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
    pos: np.ndarray,
    prev: np.ndarray,
    scene: Scene,
    solver: Solver,
    step: int,
    start: tuple[np.ndarray, np.ndarray],
) -> str | None:
    """energy_problem for a run released from `start`, for either solver.

    For PBD the watched energy is kinetic + gravitational (energy.py: its constraints are not
    k-springs), but a PBD cloth released from a strained start (stretched, crumpled) turns the
    strain into motion, as Verlet's does. So the bound also holds the start's elastic energy,
    sum C^2 / (2 compliance): the XPBD potential, k (L - rest)^2 / 2 at the default
    compliance 1/k. Without it the crumpled sheet springing open reads as a blow-up. VBD is
    watched the same way (energy.py), its start's strain energy that of the springs, k."""
    if solver.name not in ITERATIVE:
        return energy_problem(pos, prev, scene, solver, step, start=start)
    e0, limit = energy_bound(scene, solver, start)
    stiffness = 1.0 / max(min(solver.compliance_for(scene)), 1e-300) if solver.name == "pbd" else scene.stiffness
    springs = scene.replace(stiffness=stiffness)
    limit += ENERGY_GROWTH * abs(total_energy(*start, springs, solver.dt).spring)
    return energy_past(
        pos, prev, scene, solver, e0, limit, "kinetic + gravitational energy", "start energy + strain energy + scale"
    )


def is_stable(
    variant: Variant,
    scene: Scene,
    solver: Solver,
    start: tuple[np.ndarray, np.ndarray],
    steps: int,
    chunk: int = 100,
) -> tuple[bool, str | None]:
    """Run `steps` steps of `scene` stepped by `solver` from `start` on the variant's backend
    and options; (stable, what went wrong if not).

    Unstable: a position not finite, or the total energy past its bound (stability_problem).
    The harness's runaway-speed rule (100 m/s + 2 g t) is left out here on purpose: it is not
    scale-free, and a stiff sheet released from a squeezed start legitimately moves faster
    than 100 m/s at k = 1e5 (speeds grow as sqrt(k/m)), which would read as instability. The
    energy rule scales with the scene, so the measured dt * sqrt(k/m) does not depend on k.
    """
    dtype = variant.options.dtype
    with create_backend(variant.backend, scene, solver, variant.options) as b:
        b.upload(start[0].astype(dtype), start[1].astype(dtype))
        done = 0
        while done < steps:
            c = min(chunk, steps - done)
            b.advance(c)
            done += c
            pos, prev = b.read()
            if not (np.isfinite(pos[:, :3]).all() and np.isfinite(prev[:, :3]).all()):
                return False, f"step <= {done}: a position is not finite (NaN or Inf)"
            problem = stability_problem(pos, prev, scene, solver, done, start)
            if problem:
                return False, f"step <= {done}: {problem}"
        return True, None


@dataclass
@environment.with_columns  # then where and when it was measured
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
    """Bisection (in log dt) of the variant's solver's dt for the largest stable one, to a
    bracket hi/lo < 1 + rtol.

    Starts from [0.5, 1.2] x the flat-lattice prediction and widens until the bracket holds.
    With a `cap` (default PBD_CAP for a PBD variant, none for Verlet) the cap is tried first:
    stable there, the row says "stable up to the cap" (capped) without bisecting; otherwise
    the bracket never widens past it. check_60hz also runs dt = 1/60 s for the same steps and
    writes the verdict to at_60hz."""
    faults.inject(variant.backend)  # a test's fault switch, in the row's worker (harness/faults.py)
    scene = stability_scene(kind, stiffness, grid, damping)
    solver = variant.solver
    pbd = solver.name in ITERATIVE  # PBD or VBD: capped, no lattice prediction
    if cap is None and pbd:
        cap = PBD_CAP
    start = stability_state(scene, kind, seed)
    flat = predicted_dt_max(scene)
    probes = 0
    last_problem = ""

    def stable(dt: float) -> bool:
        nonlocal probes, last_problem
        probes += 1
        ok, problem = is_stable(variant, scene, solver.replace(dt=dt), start, steps)
        if not ok:
            last_problem = problem
        return ok

    at_60hz = ""
    if check_60hz:
        ok, problem = is_stable(variant, scene, solver.replace(dt=DT_60HZ), start, steps)
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
    pbd_fields = dict(iterations=solver.iterations) if pbd else {}
    if solver.name == "pbd":
        pbd_fields["pbd_method"] = solver.method
    return StabilityRow(
        kind,
        stiffness,
        damping,
        grid,
        steps,
        variant.backend,
        variant.name,
        lo,
        hi,
        predicted_for(kind, scene) if not pbd else None,
        flat,
        gershgorin_dt_max(scene),
        probes,
        last_problem,
        solver=solver.name,
        capped=capped,
        cap=cap,
        at_60hz=at_60hz,
        **pbd_fields,
        **environment.collect(),
    )


__all__ = [
    "STABILITY_SCENES",
    "STRETCH",
    "stability_scene",
    "stability_state",
    "predicted_for",
    "PBD_CAP",
    "DT_60HZ",
    "stability_problem",
    "is_stable",
    "StabilityRow",
    "measure_stability_limit",
]
