"""What every kernel takes from the scene and solver, as every backend passes it, the
peers included: the numbers, computed in float64 and rounded once to the working precision
(float32, or float64 for the NumPy reference; docs/semantics.md and docs/pbd.md,
"Constants"), and the collider table.

A backend chooses only how they reach its kernel: arguments (opencl, cuda --generic),
uniforms (GL --generic), exact literals compiled in (the specialised GL and CUDA kernels),
or plain values (NumPy and the peers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clothbench.scene import OFFSET_KIND, Scene
from clothbench.solver import Pbd, Solver

# float4 rows per collider, by collider_rows' keys
ROWS_PER_COLLIDER = {"spheres": 1, "cylinders": 3, "planes": 2}


def collider_rows(scene: Scene, dtype=np.float32) -> dict[str, np.ndarray]:
    """The colliders as the kernels take them, float64 values rounded once to `dtype` rows of
    four, in the order the step applies them: spheres (centre, radius); cylinders (start,
    length), (unit axis, radius), (radial_r, 0); planes (point, 0), (unit normal, 0)."""

    def rows(values) -> np.ndarray:
        return np.array(values, dtype=np.float64).reshape(-1, 4).astype(dtype)

    def cylinder(c):
        radial_r = (e * c.radius for e in c.radial)  # multiplied in float64, rounded once
        return ((*c.start, c.length), (*c.axis, c.radius), (*radial_r, 0.0))

    return {
        "spheres": rows([(*s.center, s.radius) for s in scene.spheres]),
        "cylinders": rows([row for c in scene.cylinders for row in cylinder(c)]),
        "planes": rows([row for p in scene.planes for row in ((*p.point, 0.0), (*p.unit_normal, 0.0))]),
    }


def rest_by_kind(scene: Scene, dtype=np.float32) -> tuple:
    """The three distinct rest lengths, structural h, shear sqrt(2) h and bend 2 sqrt(2) h,
    rounded once: the kernels take one per kind and pick it by offset (scene.OFFSET_KIND)."""
    rest = [dtype(r) for r in scene.rest_lengths()]
    kinds = tuple(rest[OFFSET_KIND.index(k)] for k in range(3))
    assert all(r == kinds[k] for k, r in zip(OFFSET_KIND, rest)), "stencil order changed"
    return kinds


@dataclass(frozen=True)
class VerletConstants:
    """docs/semantics.md, "Constants": the Verlet step's numbers, rounded once to the working
    precision (float32 unless the NumPy reference asks for float64)."""

    dt: np.floating
    dt2: np.floating  # dt * dt in float64, rounded once
    k: np.floating
    b: np.floating
    g: tuple  # gravity, three components
    rest: tuple  # rest lengths: structural, shear, bend

    @classmethod
    def of(cls, scene: Scene, solver: Solver, dtype=np.float32) -> "VerletConstants":
        t = dtype
        return cls(
            dt=t(solver.dt),
            dt2=t(solver.dt * solver.dt),
            k=t(scene.stiffness),
            b=t(scene.damping),
            g=tuple(t(g) for g in scene.gravity),
            rest=rest_by_kind(scene, t),
        )


@dataclass(frozen=True)
class PbdConstants:
    """docs/pbd.md, "Constants": computed in float64 from the scene and solver, rounded once
    to the working precision."""

    dt: np.floating
    h: np.floating  # dt / substeps
    gh: tuple  # g * h, three components
    at: tuple  # compliance / h^2: structural, shear, bend
    rest: tuple  # rest lengths: structural, shear, bend
    damp: np.floating  # 1 - 12 b h / m, clamped at 0
    relax: np.floating  # Jacobi over-relaxation

    @classmethod
    def of(cls, scene: Scene, solver: Pbd, dtype=np.float32) -> "PbdConstants":
        t = dtype
        h = solver.dt / solver.substeps
        return cls(
            dt=t(solver.dt),
            h=t(h),
            gh=tuple(t(g * h) for g in scene.gravity),
            at=tuple(t(c / (h * h)) for c in solver.compliance_for(scene)),
            rest=rest_by_kind(scene, t),
            damp=t(max(0.0, 1.0 - 12.0 * scene.damping * h / scene.mass)),
            relax=t(solver.relaxation),
        )
