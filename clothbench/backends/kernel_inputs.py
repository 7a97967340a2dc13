"""What every kernel takes from the scene, as every GPU backend passes it: the numbers,
computed in float64 and rounded once to float32 (docs/semantics.md and docs/pbd.md,
"Constants"), and the collider table.

A backend chooses only how they reach its kernel: arguments (opencl, cuda --generic),
uniforms (GL --generic) or exact literals compiled in (the specialised GL and CUDA kernels).
The NumPy references (numpy.py, numpy_pbd.py) round the same values to their working
precision themselves: they are the semantics these follow.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import Scene

# float4 rows per collider, by collider_rows' keys
ROWS_PER_COLLIDER = {"spheres": 1, "cylinders": 3, "planes": 2}


def collider_rows(scene: Scene) -> dict[str, np.ndarray]:
    """The colliders as the kernels take them, float64 values rounded once to float32 rows of
    float4, in the order the step applies them: spheres (centre, radius); cylinders (start,
    length), (unit axis, radius), (radial_r, 0); planes (point, 0), (unit normal, 0)."""

    def rows(values) -> np.ndarray:
        return np.array(values, dtype=np.float64).reshape(-1, 4).astype(np.float32)

    def cylinder(c):
        radial_r = (e * c.radius for e in c.radial)  # multiplied in float64, rounded once
        return ((*c.start, c.length), (*c.axis, c.radius), (*radial_r, 0.0))

    return {
        "spheres": rows([(*s.center, s.radius) for s in scene.spheres]),
        "cylinders": rows([row for c in scene.cylinders for row in cylinder(c)]),
        "planes": rows([row for p in scene.planes for row in ((*p.point, 0.0), (*p.unit_normal, 0.0))]),
    }


def rest_by_kind(scene: Scene) -> tuple[np.float32, np.float32, np.float32]:
    """The three distinct rest lengths, structural h, shear sqrt(2) h and bend 2 sqrt(2) h,
    rounded once: the kernels take one per kind and pick it by offset (o / 4)."""
    rest = [np.float32(r) for r in scene.rest_lengths()]
    kinds = (rest[0], rest[4], rest[8])  # structural, shear, bend: OFFSETS order
    assert all(r == kinds[o // 4] for o, r in enumerate(rest)), "stencil order changed"
    return kinds


@dataclass(frozen=True)
class VerletConstants:
    """docs/semantics.md, "Constants": the Verlet step's numbers, rounded once to float32."""

    dt: np.float32
    dt2: np.float32  # dt * dt in float64, rounded once
    k: np.float32
    b: np.float32
    g: tuple  # gravity, three components
    rest: tuple  # rest lengths: structural, shear, bend

    @classmethod
    def of(cls, scene: Scene) -> "VerletConstants":
        f32 = np.float32
        return cls(
            dt=f32(scene.dt),
            dt2=f32(scene.dt * scene.dt),
            k=f32(scene.stiffness),
            b=f32(scene.damping),
            g=tuple(f32(g) for g in scene.gravity),
            rest=rest_by_kind(scene),
        )


@dataclass(frozen=True)
class PbdConstants:
    """docs/pbd.md, "Constants": computed in float64 from the scene, rounded once to float32,
    exactly as the NumPy reference (numpy_pbd.py) rounds them."""

    dt: np.float32
    h: np.float32  # dt / substeps
    gh: tuple  # g * h, three components
    at: tuple  # compliance / h^2: structural, shear, bend
    rest: tuple  # rest lengths: structural, shear, bend
    damp: np.float32  # 1 - 12 b h / m, clamped at 0
    relax: np.float32  # Jacobi over-relaxation

    @classmethod
    def of(cls, scene: Scene) -> "PbdConstants":
        f32 = np.float32
        h = scene.dt / scene.substeps
        return cls(
            dt=f32(scene.dt),
            h=f32(h),
            gh=tuple(f32(g * h) for g in scene.gravity),
            at=tuple(f32(c / (h * h)) for c in scene.pbd_compliance()),
            rest=rest_by_kind(scene),
            damp=f32(max(0.0, 1.0 - 12.0 * scene.damping * h / scene.mass)),
            relax=f32(scene.relaxation),
        )
