"""Total energy of a state, and the energy-growth bound every command shares.

Verlet keeps two positions, x(t) and x(t - dt), so the energy is measured as the scheme
sees it, at the half step between them (in float64, whatever the working precision, except
in the blow-up check: see watched_energy):

- kinetic: sum of m |v|^2 / 2 with the Verlet velocity estimate v = (x - x_prev) / dt;
- gravitational: sum of -m g . x, averaged over x and x_prev (for a constant force this
  average makes Verlet's energy exactly constant);
- spring: sum over springs of k (L - rest)(L_prev - rest) / 2, the product of the two
  stretches rather than the mean of their squares: for a linear spring that is the energy
  position Verlet conserves exactly, so a stable undamped run shows no O((w dt)^2) ripple
  from the fast spring modes, only the slow drift of the nonlinear geometry.

Pinned particles (w = 0) do not move, so they hold no kinetic energy and their constant
potential is left out; a spring to a pinned particle still counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from clothbench.model.scene import OFFSETS, Scene
from clothbench.model.solver import ITERATIVE, Solver

# Each spring once: the offsets pointing "forward" (the stencil lists both ends).
FORWARD = tuple(o for o in OFFSETS if o[0] > 0 or (o[0] == 0 and o[1] > 0))

# A run is blown up once its total energy exceeds the start by ENERGY_GROWTH times the
# energy scale of the scene (see energy_scale): a stable cloth only converts energy
# (gravity -> motion -> springs) and damping removes it; sphere contacts add a little.
ENERGY_GROWTH = 1.0
# Floor of the scale: the whole cloth moving at FLOOR_SPEED, so a scene with no gravity
# and no initial motion still has a finite bound.
FLOOR_SPEED = 0.1  # m/s


@dataclass(frozen=True)
class Energy:
    kinetic: float
    spring: float
    gravity: float

    @property
    def total(self) -> float:
        return self.kinetic + self.spring + self.gravity

    def watched(self, solver: Solver) -> float:
        """The energy the blow-up check watches. PBD's constraints are as stiff as its
        iterations make them, not k, so k*(L - rest)^2/2 is not its energy: there only
        kinetic + gravitational energy is watched (a stable PBD step only loses it). VBD's
        too: a sweep short of convergence leaves its springs softer than k, and k times their
        stretch is not energy it holds (docs/vbd.md, "Blow-up detection")."""
        return self.total if solver.name not in ITERATIVE else self.kinetic + self.gravity


# Every array below is planar, (3, rows, n) in float64: x, y and z each contiguous, and the
# sums go over blocks of BLOCK_ROWS rows of particles. The state's (n*n, 4) rows made the sums
# over a component axis of length 3 strided (1.4 s a state at 2048^2); whole planar arrays
# took 0.6 s, and 1.5-6 s in a sweep's row process, where each temporary of 34-100 MB was a
# fresh mapping of memory the VM's host had taken back (docs/timing.md, "What a row costs
# besides its timed steps"). A block's temporaries are a few MiB: they stay in the caches and
# in the process's heap.
BLOCK_ROWS = 64
PARTICLES_PER_BLOCK = 1 << 17  # the same for the checks that go particle by particle
REACH = max(dr for dr, _ in FORWARD)  # rows past a block that its springs reach


def _grid(a: np.ndarray, n: int, dtype) -> np.ndarray:
    return np.ascontiguousarray(a[:, :3].T, dtype=dtype).reshape(3, -1, n)


def _squares(d: np.ndarray) -> np.ndarray:
    """|d|^2 of planar vectors d (squared in place), summed x, y, z in that order."""
    np.multiply(d, d, out=d)
    total = d[0] + d[1]
    total += d[2]
    return total


def _lengths(x: np.ndarray, dr: int, dc: int, rows: int) -> np.ndarray:
    """Lengths of the springs (dr >= 0, dc) from the first `rows` rows of the block x."""
    n = x.shape[2]
    a = x[:, :rows, max(0, -dc) : n - max(0, dc)]
    b = x[:, dr : dr + rows, max(0, dc) : n + min(0, dc)]
    lengths = _squares(b - a)
    return np.sqrt(lengths, out=lengths)


def total_energy(
    pos: np.ndarray, prev: np.ndarray, scene: Scene, dt: float, springs: bool = True, dtype=np.float64
) -> Energy:
    """Kinetic, spring and gravitational energy (J) of the state (pos, prev) of `scene`,
    prev taken dt before pos. With `springs` false the spring term, four fifths of the work, is
    not computed (NaN): for a check that does not watch it (watched_energy). `dtype` is the
    arithmetic's precision; every sum is accumulated in float64 either way."""
    n, m, k = scene.grid, scene.mass, scene.stiffness
    g = scene.gravity
    rest = dict(zip(OFFSETS, scene.rest_lengths()))
    kinetic = gravity = 0.0
    spring = 0.0 if springs else math.nan
    for r0 in range(0, n, BLOCK_ROWS):
        r1 = min(n, r0 + BLOCK_ROWS)
        end = min(n, r1 + REACH) if springs else r1  # the rows the block's springs reach
        x, xp = _grid(pos[r0 * n : end * n], n, dtype), _grid(prev[r0 * n : end * n], n, dtype)
        rows = r1 - r0
        free = pos[r0 * n : r1 * n, 3] != 0
        own, own_prev = x[:, :rows], xp[:, :rows]
        v = (own - own_prev) / dt
        kinetic += 0.5 * m * float(_squares(v).reshape(-1)[free].sum(dtype=np.float64))
        mid = 0.5 * (own + own_prev)
        lift = ((mid[0] * g[0] + mid[1] * g[1]) + mid[2] * g[2]).reshape(-1)[free]
        gravity -= m * float(lift.sum(dtype=np.float64))
        for dr, dc in FORWARD if springs else ():
            count = min(rows, n - dr - r0)  # the block's rows whose spring (dr, dc) ends in the grid
            if count <= 0:
                continue
            s_now = _lengths(x, dr, dc, count) - rest[(dr, dc)]
            s_prev = _lengths(xp, dr, dc, count) - rest[(dr, dc)]
            spring += 0.5 * k * float((s_now * s_prev).sum(dtype=np.float64))
    return Energy(kinetic, spring, gravity)


def watched_energy(pos: np.ndarray, prev: np.ndarray, scene: Scene, solver: Solver) -> Energy:
    """total_energy with the terms Energy.watched(solver) and energy_scale read: no spring
    term for PBD and VBD (ITERATIVE), which the check leaves out. Computed in the state's own
    precision (float32 for a float32 run, sums in float64): the check compares it with a bound
    a whole energy scale above the start (ENERGY_GROWTH), and float32's error in it is about
    1e-7 of the energy the state holds (tests/test_accuracy.py holds it under 1e-6), while at
    2048^2 it costs under half of float64's (0.16 s against 0.37 a state on the Zen 4: ten
    checks a row, docs/timing.md)."""
    dtype = np.promote_types(pos.dtype, np.float32)
    return total_energy(pos, prev, scene, solver.dt, springs=solver.name not in ITERATIVE, dtype=dtype)


def energy_scale(
    scene: Scene,
    solver: Solver,
    pos: np.ndarray | None = None,
    prev: np.ndarray | None = None,
    e: Energy | None = None,
) -> float:
    """What a stable run of `scene` can plausibly move around (J): the energy of lifting the
    free particles by the size of the sheet, plus the kinetic and elastic energy at the start
    (`e`, the start's energy where the caller has it), plus the cloth moving at FLOOR_SPEED."""
    if pos is None:
        pos, prev = solver.initial_state(scene, np.float64)
    free_mass = scene.mass * int((pos[:, 3] != 0).sum())
    g = math.sqrt(sum(c * c for c in scene.gravity))
    xyz = pos[:, :3]  # a maximum and a minimum are exact in any precision: no float64 copy
    extent = max(scene.size, float(np.linalg.norm(xyz.max(axis=0).astype(np.float64) - xyz.min(axis=0))))
    if e is None:
        e = watched_energy(pos, prev, scene, solver)
    spring = abs(e.spring) if solver.name not in ITERATIVE else 0.0
    return free_mass * g * extent + abs(e.kinetic) + spring + 0.5 * free_mass * FLOOR_SPEED**2


# (E0, scale) of starts given by another process (remember_start): a sweep row's process is
# fresh, and the float64 start of 2048^2 is 1.5-2 s of it (mostly fresh memory, docs/timing.md)
_given: dict[tuple[Scene, Solver], tuple[float, float]] = {}


def start_energy(scene: Scene, solver: Solver) -> tuple[float, float]:
    """(E0, scale): the watched energy of the solver's float64 start of `scene` and its
    energy_scale, what energy_bound measures a run from; once a process."""
    given = _given.get((scene, solver))
    return given if given is not None else _start(scene, solver)


def remember_start(scene: Scene, solver: Solver, values: tuple[float, float]) -> None:
    """Take start_energy(scene, solver) as `values`, computed by another process (the sweep's,
    once a grid, for each row's own process)."""
    _given[(scene, solver)] = values


@lru_cache(maxsize=32)
def _start(scene: Scene, solver: Solver) -> tuple[float, float]:
    pos, prev = solver.initial_state(scene, np.float64)
    e = watched_energy(pos, prev, scene, solver)
    return e.watched(solver), energy_scale(scene, solver, pos, prev, e)


def energy_bound(
    scene: Scene, solver: Solver, start: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[float, float]:
    """(E0, limit): the start's total energy and the largest total a stable run reaches.

    `start` is the initial (pos, prev) when the run did not start from solver.initial_state()."""
    if start is None:
        e0, scale = start_energy(scene, solver)
    else:
        e = watched_energy(*start, scene, solver)
        e0, scale = e.watched(solver), energy_scale(scene, solver, *start, e)
    return e0, e0 + ENERGY_GROWTH * scale


def energy_problem(
    pos: np.ndarray,
    prev: np.ndarray,
    scene: Scene,
    solver: Solver,
    step: int,
    start: tuple[np.ndarray, np.ndarray] | None = None,
) -> str | None:
    """None while the total energy stays under the bound, else what is wrong (one line).

    Same signature as harness.health.state_problem, so it can be chained after it."""
    e0, limit = energy_bound(scene, solver, start)
    return energy_past(
        pos, prev, scene, solver, e0, limit, "total energy", "a stable run only loses energy; try a smaller dt"
    )


def energy_past(
    pos: np.ndarray, prev: np.ndarray, scene: Scene, solver: Solver, e0: float, limit: float, what: str, bound: str
) -> str | None:
    """None while the energy the check watches (Energy.watched) stays within `limit`, else
    what is wrong in one line, naming the energy as `what` and saying what the bound is as
    `bound`: the test every energy check ends in."""
    with np.errstate(all="ignore"):
        e = watched_energy(pos, prev, scene, solver).watched(solver)
    if not math.isfinite(e):
        return f"the {what} is not finite"
    if e > limit:
        return f"the {what} grew from {e0:.4g} J to {e:.4g} J, past the bound {limit:.4g} J ({bound})"
    return None


# --- fast impact -----------------------------------------------------------------------
#
# The sphere collider only sees where a particle lands: x_new inside the sphere is pushed out
# along the line from the centre. A particle that moves D per step can land past the centre
# once D > r (and is pushed out through the far side), and can jump the sphere entirely once
# D > 2r. So the rule: when a free particle's displacement per step |x - x_prev| reaches the
# radius of the smallest sphere, contacts can tunnel; warn and say what dt would catch it.


def max_step_displacement(pos: np.ndarray, prev: np.ndarray) -> tuple[float, int]:
    """(largest |x - x_prev| of a free particle (m), that particle's index: the first such, or
    the first NaN, as np.argmax over the whole sheet), in blocks of PARTICLES_PER_BLOCK."""
    best, at = -math.inf, 0
    for start in range(0, len(pos), PARTICLES_PER_BLOCK):
        p, q = pos[start : start + PARTICLES_PER_BLOCK], prev[start : start + PARTICLES_PER_BLOCK]
        d = np.sqrt(((p[:, :3].astype(np.float64) - q[:, :3]) ** 2).sum(axis=1))
        d[p[:, 3] == 0] = 0.0
        i = int(np.argmax(d))
        if math.isnan(d[i]):
            return float(d[i]), start + i
        if d[i] > best:
            best, at = float(d[i]), start + i
    return best, at


# The screen before the exact scan: in the state's own precision (float32 for a float32 run),
# a quarter of the float64 scan's time at 2048^2 (0.03 against 0.11 s, after every chunk).
# Its rounding is within a few float32 ulps of |d|^2, far inside this margin, so a step the
# exact scan finds at or past the radius is never screened out.
SCREEN_MARGIN = 1e-3


def largest_step_squared(pos: np.ndarray, prev: np.ndarray) -> float:
    """The largest |x - x_prev|^2 of a free particle in the state's precision (0 with none; a
    NaN is passed over: the exact scan, max_step_displacement, names it), in blocks."""
    worst = 0.0
    for start in range(0, len(pos), PARTICLES_PER_BLOCK):
        p, q = pos[start : start + PARTICLES_PER_BLOCK], prev[start : start + PARTICLES_PER_BLOCK]
        d = (p - q)[:, :3]
        d2 = np.einsum("ij,ij->i", d, d)
        d2[p[:, 3] == 0] = 0.0
        worst = max(worst, float(np.nanmax(d2, initial=0.0)))
    return worst


def fast_impact_warning(pos: np.ndarray, prev: np.ndarray, scene: Scene, dt: float) -> str | None:
    """A warning (one line) if a particle moves as far per step as the smallest sphere's
    radius, so the collider could let it through; None otherwise or with no spheres."""
    if not scene.spheres:
        return None
    r = min(s.radius for s in scene.spheres)
    if largest_step_squared(pos, prev) < (1.0 - SCREEN_MARGIN) * r * r:
        return None  # no particle near the radius: the exact scan below would say so too
    d, i = max_step_displacement(pos, prev)
    if not math.isfinite(d) or d < r:
        return None
    speed = d / dt
    return (
        f"fast impact: particle {i} moves {d:.3g} m per step ({speed:.3g} m/s), at least the "
        f"sphere radius {r:.3g} m, so it can pass through the sphere; use dt < {r / speed:.2g} s"
    )


def predicted_fast_impact(scene: Scene, solver: Solver) -> str | None:
    """Before a run: the free-fall speed a particle reaches by the bottom of the lowest-reaching
    sphere, times dt, against the smallest radius (the same rule, predicted from the scene)."""
    if not scene.spheres:
        return None
    g = np.array(scene.gravity)
    gn = float(np.linalg.norm(g))
    if gn == 0:
        return None
    down = g / gn
    pos, prev = solver.initial_state(scene, np.float64)
    free = pos[:, 3] != 0
    if not free.any():
        return None
    xyz = pos[free, :3]
    v0 = float(np.sqrt((((pos[free, :3] - prev[free, :3]) / solver.dt) ** 2).sum(axis=1)).max())
    # the deepest point any sphere reaches along gravity, measured from the highest particle
    drop = max(float(np.dot(np.array(s.center), down)) + s.radius for s in scene.spheres)
    drop -= float((xyz @ down).min())
    speed = math.sqrt(v0 * v0 + 2 * gn * max(drop, 0.0))
    r = min(s.radius for s in scene.spheres)
    if speed * solver.dt < r:
        return None
    return (
        f"fast impact: falling freely the cloth reaches {speed:.3g} m/s, {speed * solver.dt:.3g} m "
        f"per step, at least the sphere radius {r:.3g} m; use dt < {r / speed:.2g} s"
    )


__all__ = [
    "Energy",
    "total_energy",
    "energy_scale",
    "energy_bound",
    "start_energy",
    "remember_start",
    "energy_problem",
    "max_step_displacement",
    "fast_impact_warning",
    "predicted_fast_impact",
]
