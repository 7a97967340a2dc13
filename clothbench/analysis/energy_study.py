"""The energy study (`clothbench energy`): hard case 6 at a study's length, every backend mode.

Two runs of the drape per mode, from rest, the energy (harness/energy.py, float64 of the
mode's own state) read every `every` steps:

- undamped (b = 0): position Verlet is symplectic, so the energy stays within a band, 1 % of
  the sheet's gravitational scale M |g| size, for 100,000 steps (50 s simulated); the row's
  `worst_drift_j` is the largest |E - E0| seen, `band_j` the band;
- damped (the scene's b): the lagged drag only removes energy, so between two readings it never
  rises by more than rounding, 16 u x the energy scale (u = 2^-24 or 2^-53): `max_rise_j`
  against `rounding_j`; and by the end it has lost most of the swing (`e0_j - e_end_j`).

docs/accuracy.md ("Energy") has the reasoning and the figures; results/energy/ the committed
study, which tests/hard_cases/test_energy.py reads, and runs each check's short form itself.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from clothbench import environment
from clothbench.errors import ClothbenchError
from clothbench.harness.energy import energy_scale, total_energy
from clothbench.harness.plan import Variant
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver

BAND = 0.01  # of M |g| size: the undamped drift allowed (measured 0.36 % f64, 0.43 % f32 at 8x8)
ROUNDING_ULPS = 16  # the damped energy's rise allowed between readings, in u x energy scale
CASES = ("undamped", "damped")


@dataclass
@environment.with_columns  # then where and when it was measured
class EnergyRow:
    backend: str
    label: str
    case: str  # undamped or damped
    scene: str
    grid: int
    dt: float
    damping: float
    steps: int
    every: int  # steps between readings
    status: str  # ok, or what stopped it (a blow-up with its step, an error)
    e0_j: float = float("nan")  # the start's energy (the float64 start)
    e_end_j: float = float("nan")
    worst_drift_j: float = float("nan")  # max |E - E0| over the readings
    band_j: float = float("nan")  # undamped: BAND x M |g| size
    max_rise_j: float = float("nan")  # the largest rise between two readings
    rounding_j: float = float("nan")  # damped: ROUNDING_ULPS u x the energy scale

    def share(self) -> float:
        """The reading as a share of its bound (at most 1: it holds): the undamped run's worst
        drift over its band, the damped run's largest rise over rounding (at most 0: its energy
        never rose between two readings)."""
        if self.case == "undamped":
            return self.worst_drift_j / self.band_j
        return self.max_rise_j / self.rounding_j

    def as_dict(self) -> dict:
        return asdict(self)


def energies(variant: Variant, scene: Scene, solver: Solver, steps: int, every: int) -> np.ndarray:
    """The total energy (J) after every `every` steps of `scene` from its start on `variant`."""
    from clothbench.backends import create_backend

    out = []
    with create_backend(variant.backend, scene, solver, variant.options) as b:
        b.upload(*b.initial_state())
        for k in range(steps // every):
            b.advance(every)
            pos, prev = b.read()
            if not np.isfinite(pos[:, :3]).all():
                raise ClothbenchError(f"a position is not finite by step {(k + 1) * every}")
            out.append(total_energy(pos, prev, scene, solver.dt).total)
    return np.array(out)


def band(scene: Scene) -> float:
    """BAND x the sheet's gravitational scale: its free mass x |g| x its size (J)."""
    free_mass = scene.mass * (scene.particles - len(scene.pinned()))
    return BAND * free_mass * abs(scene.gravity[1]) * scene.size


def rounding(variant: Variant, scene: Scene, solver: Solver) -> float:
    """ROUNDING_ULPS units of the mode's rounding x the scene's energy scale (J)."""
    return ROUNDING_ULPS * float(np.finfo(variant.options.dtype).eps / 2) * energy_scale(scene, solver)


def measure_energy(variant: Variant, scene: Scene, solver: Solver, case: str, steps: int, every: int) -> EnergyRow:
    """One row: `case` (undamped: b = 0; damped: the scene's b) for `steps` steps."""
    run = scene.replace(damping=0.0) if case == "undamped" else scene
    row = EnergyRow(
        variant.backend,
        variant.name,
        case,
        scene.name,
        scene.grid,
        solver.dt,
        run.damping,
        steps,
        every,
        "ok",
        **environment.collect(),
    )
    row.e0_j = total_energy(*solver.initial_state(run, np.float64), run, solver.dt).total
    try:
        e = energies(variant, run, solver, steps, every)
    except ClothbenchError as err:
        row.status = f"failed: {err}"
        return row
    row.e_end_j = float(e[-1])
    row.worst_drift_j = float(np.abs(e - row.e0_j).max())
    row.max_rise_j = float(np.diff(e).max()) if len(e) > 1 else float("nan")
    if case == "undamped":
        row.band_j = band(run)
    else:
        row.rounding_j = rounding(variant, run, solver)
    return row
