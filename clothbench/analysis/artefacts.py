"""What PBD gets wrong against the mass-spring model: softness and numerical damping.

Measured where chaos does not matter, on the NumPy float64 reference: the strain of the cloth
at rest (settled with light damping), and the energy an undamped run gains or loses.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from clothbench.analysis.convergence import F64, structural_strain
from clothbench.harness.energy import total_energy
from clothbench.harness.simulate import simulate
from clothbench.model.scene import Scene
from clothbench.model.solver import PBD_METHODS, Pbd, Solver, as_verlet
from clothbench.variant_names import model_name

SETTLE_DAMPING = 0.005  # N s/m: near critical for the hanging sheet's swing, settled in SETTLE_S
SETTLE_S = 3.0  # s: the largest speed left is below 0.03 m/s and the strain steady to 4 digits
SWING_S = 2.0  # s of undamped motion over which the energy change is measured
ITERATIONS = (3, 10, 30, 100)  # PBD iteration counts: from unresolved to converged constraints
DTS = (1 / 60, 1 / 120, 1 / 240)  # PBD time steps: from a 60 Hz frame down


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


def _settle_and_swing(scene: Scene, solver: Solver) -> tuple[float, float, float, float]:
    """(hanging strain, settle speed, energy change, ms per simulated second) of `scene`
    stepped by `solver`. The energy is the k-spring one whatever the solver (for XPBD at
    compliance 1/k, its C^2 / 2 compliance potential)."""
    dt = solver.dt
    rest = scene.replace(damping=SETTLE_DAMPING)
    pos, prev = simulate("numpy", rest, solver, max(1, round(SETTLE_S / dt)), F64)
    speed = float(np.sqrt(((pos[:, :3] - prev[:, :3]) ** 2).sum(axis=1)).max() / dt)
    strain = structural_strain(pos, rest)
    swing = scene.replace(damping=0.0)
    e0 = total_energy(*solver.initial_state(swing, np.float64), swing, dt).total
    t0 = time.perf_counter()
    steps = max(1, round(SWING_S / dt))
    pos, prev = simulate("numpy", swing, solver, steps, F64)
    ms = 1e3 * (time.perf_counter() - t0) / (steps * dt)
    with np.errstate(all="ignore"):
        e = total_energy(pos, prev, swing, dt).total
    g = math.sqrt(sum(c * c for c in scene.gravity)) or 1.0
    scale = scene.mass * int((pos[:, 3] != 0).sum()) * g * scene.size
    return strain, speed, (e - e0) / scale, ms


def solver_artefacts(
    scene: Scene,
    pbd: Pbd,
    methods: tuple[str, ...] = PBD_METHODS,
    iterations: tuple[int, ...] = ITERATIONS,
    dts: tuple[float, ...] = DTS,
    on_progress: Callable[[str], None] | None = None,
) -> list[ArtefactRow]:
    """Softness and damping of PBD against Verlet, on the NumPy float64 reference.

    Verlet runs at pbd's dt and start. Each PBD method (pbd's other settings) runs every
    iteration count at dts[0], and pbd's iteration count at the other dts: softness comes
    from too few iterations (the constraints are not resolved: the cloth at rest stretches
    more than k says), extra damping from the large step (the implicit position projection
    removes energy; at converged iterations it remains). The energy change is only a damping
    measure where the strain is about right (strain_ratio near 1): an over-stretched cloth
    holds more k-spring energy than it was given."""
    note = on_progress or (lambda what: None)
    verlet = as_verlet(pbd)
    note("verlet: settle and swing")
    v_strain, v_speed, v_energy, v_ms = _settle_and_swing(scene, verlet)
    rows = [
        ArtefactRow(
            scene.name, scene.grid, "verlet", "verlet", "", None, verlet.dt, v_strain, 1.0, v_speed, v_energy, v_ms
        )
    ]
    for method in methods:
        runs = [(it, dts[0]) for it in iterations] + [(pbd.iterations, dt) for dt in dts[1:]]
        for it, dt in dict.fromkeys(runs):
            s = pbd.replace(method=method, iterations=it, dt=dt)
            note(f"pbd-{method} {it} it, dt {dt:.3g}: settle and swing")
            strain, speed, energy, ms = _settle_and_swing(scene, s)
            rows.append(
                ArtefactRow(
                    scene.name,
                    scene.grid,
                    model_name(s),
                    "pbd",
                    method,
                    it,
                    dt,
                    strain,
                    strain / v_strain if v_strain > 0 else float("nan"),
                    speed,
                    energy,
                    ms,
                )
            )
    return rows


__all__ = ["SETTLE_DAMPING", "SETTLE_S", "SWING_S", "ITERATIONS", "DTS", "ArtefactRow", "solver_artefacts"]
