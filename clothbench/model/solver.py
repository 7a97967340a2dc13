"""The solver settings: how a scene is stepped, kept apart from what is simulated.

A `Scene` (scene.py) is the model: the cloth, its constants, colliders and pins. A solver
is the integrator and its settings: `Verlet` (docs/semantics.md), `Pbd` (docs/pbd.md) or
`Vbd` (docs/vbd.md), each with its time step and how the run starts. The run length (steps) is a third thing,
passed beside both; `scene.Setup` holds all three as a scene file describes them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from clothbench.errors import SceneError

FLOAT32_MAX = 3.4028234663852886e38
FLOAT32_TINY = 1.1754943508222875e-38  # smallest normal float32

STARTS = ("rest", "second-order")
SOLVERS = ("verlet", "pbd", "vbd")
PBD_METHODS = ("jacobi", "coloured")
# What --solvers accepts: a solver, or pbd with its method ("pbd" alone: the file's method).
SOLVER_SPECS = ("verlet", "pbd", *(f"pbd-{m}" for m in PBD_METHODS), "vbd")
# the solvers that iterate within a substep: what --iterations and --substeps apply to
ITERATIVE = ("pbd", "vbd")


def finite_number(x) -> bool:
    """A real number (not a bool) that is finite: what a scene or solver setting must be."""
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _positive_int(value, name: str) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise SceneError(f"{name} must be an integer >= 1, got {value!r}")


@dataclass(frozen=True)
class Stepping:
    """What every solver has: the time step and how the run starts."""

    dt: float = 5e-4  # s
    start: str = "rest"  # or "second-order": x_prev = x + g dt^2 / 2

    name = "?"

    def __post_init__(self):
        _validate_common(self)

    @property
    def spec(self) -> str:
        """The solver as --solvers spells it."""
        return self.name

    def replace(self, **changes):
        return dataclasses.replace(self, **changes)

    def initial_state(self, scene, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) of `scene` as this solver starts it, computed in float64 and rounded
        once, so every backend starts from the same bits."""
        if self.start != "second-order":
            return scene.initial_state(dtype)
        # x_prev = x - v0*dt + a0*dt^2/2 with v0 = 0 and a0 = g (the flat sheet is at rest
        # length, so springs add nothing): makes the start second-order accurate.
        return scene.initial_state(dtype, shift=tuple(0.5 * g * self.dt * self.dt for g in scene.gravity))


@dataclass(frozen=True)
class Verlet(Stepping):
    """The chapter's mass-spring step with Verlet integration (docs/semantics.md)."""

    name = "verlet"


@dataclass(frozen=True)
class Pbd(Stepping):
    """Position Based Dynamics, XPBD form (docs/pbd.md)."""

    method: str = "jacobi"  # or "coloured" Gauss-Seidel
    # one substep of ten passes at the scenes' own dt (0.5 ms): at a 60 Hz step ten substeps of
    # one pass are far closer for the same cost (docs/pbd-study.md), but a substep of 50 us
    # moves a resting float32 sheet at y = 1 m by less than half an ulp, so it never starts to
    # fall (docs/pbd.md): substeps are for large steps, set in [pbd]
    iterations: int = 10  # constraint passes per substep
    substeps: int = 1
    relaxation: float = 1.5  # Jacobi over-relaxation of the averaged correction
    compliance: tuple[float, float, float] | None = None  # m/N per kind; None: 1/stiffness
    chebyshev_rho: float = 0.0  # Jacobi: spectral radius estimate of Chebyshev acceleration; 0: off

    name = "pbd"

    def __post_init__(self):
        _validate_common(self)
        if self.method not in PBD_METHODS:
            raise SceneError(f"pbd method must be one of {', '.join(PBD_METHODS)}, got {self.method!r}")
        _positive_int(self.iterations, "iterations")
        _positive_int(self.substeps, "substeps")
        if not finite_number(self.relaxation) or not 0 < self.relaxation < 2:
            raise SceneError(f"relaxation must be in (0, 2), got {self.relaxation!r}")
        if not finite_number(self.chebyshev_rho) or not 0 <= self.chebyshev_rho < 1:
            raise SceneError(f"chebyshev_rho must be in [0, 1) (0: no acceleration), got {self.chebyshev_rho!r}")
        if self.compliance is not None:
            c = self.compliance
            if not isinstance(c, (list, tuple)) or len(c) != 3 or not all(finite_number(v) for v in c):
                raise SceneError(f"compliance must be three finite numbers, got {c!r}")
            object.__setattr__(self, "compliance", tuple(float(v) for v in c))
            if min(self.compliance) < 0:
                raise SceneError(f"compliance must be >= 0, got {list(self.compliance)}")

    @property
    def spec(self) -> str:
        return f"pbd-{self.method}"

    def chebyshev_omega(self) -> tuple[float, ...]:
        """The Chebyshev weight of each Jacobi iteration (chebyshev_omega)."""
        return chebyshev_omega(self.chebyshev_rho, self.iterations)

    def compliance_for(self, scene) -> tuple[float, float, float]:
        """XPBD compliance (m/N) of structural, shear and bend constraints."""
        if self.compliance is not None:
            return self.compliance
        if scene.stiffness == 0:
            raise SceneError("the pbd solver needs stiffness > 0 or an explicit [pbd] compliance")
        return (1.0 / scene.stiffness,) * 3


@dataclass(frozen=True)
class Vbd(Stepping):
    """Implicit Euler by Vertex Block Descent (docs/vbd.md): per-vertex 3x3 Newton steps on
    the step's incremental potential, Gauss-Seidel over the grid's 4 vertex colours."""

    iterations: int = 10  # sweeps over the 4 colours per substep
    substeps: int = 1
    chebyshev_rho: float = 0.0  # spectral radius estimate of Chebyshev acceleration; 0: off

    name = "vbd"

    def __post_init__(self):
        _validate_common(self)
        _positive_int(self.iterations, "iterations")
        _positive_int(self.substeps, "substeps")
        if not finite_number(self.chebyshev_rho) or not 0 <= self.chebyshev_rho < 1:
            raise SceneError(f"chebyshev_rho must be in [0, 1) (0: no acceleration), got {self.chebyshev_rho!r}")

    def chebyshev_omega(self) -> tuple[float, ...]:
        """The Chebyshev weight of each sweep (chebyshev_omega)."""
        return chebyshev_omega(self.chebyshev_rho, self.iterations)


Solver = Verlet | Pbd | Vbd


def chebyshev_omega(rho: float, iterations: int) -> tuple[float, ...]:
    """The Chebyshev weight of each iteration (Wang 2015), float64: 1 for the first (it has no
    iterate before it), 2 / (2 - rho^2) for the second, then 4 / (4 - rho^2 omega). All 1 with
    rho = 0. PBD's Jacobi passes and VBD's sweeps take the same weights."""
    rho2, omega = rho**2, []
    for k in range(iterations):
        omega.append(1.0 if k == 0 else 2.0 / (2.0 - rho2) if k == 1 else 4.0 / (4.0 - rho2 * omega[-1]))
    return tuple(omega)


def _validate_common(s: Stepping) -> None:
    if not finite_number(s.dt):
        raise SceneError(f"dt must be a finite number, got {s.dt!r}")
    if s.dt <= 0:
        raise SceneError(f"dt must be > 0, got {s.dt!r}")
    if s.dt > FLOAT32_MAX:
        raise SceneError(f"dt {s.dt!r} is too large for float32 (max {FLOAT32_MAX:.4g})")
    dt2 = float(np.float32(s.dt)) ** 2
    if not dt2 >= FLOAT32_TINY:  # the step's dt^2 term: 0 (or denormal) in float32, the cloth never moves
        raise SceneError(
            f"dt {s.dt!r} is too small for float32: dt^2 = {s.dt * s.dt:.3g} is below its smallest normal "
            f"{FLOAT32_TINY:.4g} (the cloth would never move)"
        )
    if dt2 > FLOAT32_MAX:
        raise SceneError(f"dt {s.dt!r} is too large for float32: dt^2 overflows (max {FLOAT32_MAX:.4g})")
    if s.start not in STARTS:
        raise SceneError(f"start must be one of {', '.join(STARTS)}, got {s.start!r}")


def as_verlet(solver: Solver) -> Verlet:
    """The Verlet solver with the same dt and start as `solver`."""
    return Verlet(dt=solver.dt, start=solver.start)


def as_pbd(solver: Solver, pbd: Pbd | None = None, method: str | None = None) -> Pbd:
    """A PBD solver with `solver`'s dt and start, `pbd`'s settings (default: `solver`'s own
    if it is one, else the defaults) and `method` where given."""
    settings = pbd if pbd is not None else solver if isinstance(solver, Pbd) else Pbd()
    changes = {"dt": solver.dt, "start": solver.start}
    if method is not None:
        changes["method"] = method
    return settings.replace(**changes)


def as_vbd(solver: Solver, vbd: Vbd | None = None) -> Vbd:
    """A VBD solver with `solver`'s dt and start and `vbd`'s settings (default: `solver`'s own
    if it is one, else the defaults)."""
    settings = vbd if vbd is not None else solver if isinstance(solver, Vbd) else Vbd()
    return settings.replace(dt=solver.dt, start=solver.start)


def check_spec(spec: str) -> str:
    if spec not in SOLVER_SPECS:
        raise SceneError(f"unknown solver {spec!r} (known: {', '.join(SOLVER_SPECS)})")
    return spec


def solver_for_spec(spec: str, solver: Solver, pbd: Pbd | None = None, vbd: Vbd | None = None) -> Solver:
    """The solver a --solvers entry stands for, with `solver`'s dt and start; "pbd" alone
    keeps the method of `pbd` (the scene file's [pbd] table), "vbd" the settings of `vbd`."""
    name, _, method = check_spec(spec).partition("-")
    if name == "verlet":
        return as_verlet(solver)
    if name == "vbd":
        return as_vbd(solver, vbd)
    return as_pbd(solver, pbd, method or None)
