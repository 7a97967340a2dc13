"""What every kernel takes from the scene and solver, as every backend passes it, the
peers included: the numbers, computed in float64 and rounded once to the working precision
(float32, or float64 for the NumPy reference; docs/semantics.md, docs/pbd.md and docs/vbd.md,
"Constants"), and the collider table.

A backend chooses only how they reach its kernel: arguments (opencl, cuda --generic),
uniforms (GL --generic), exact literals compiled in (the specialised GL and CUDA kernels),
or plain values (NumPy and the peers).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from clothbench.model.colliders.kinds import KINDS
from clothbench.model.colliders.motion import pose
from clothbench.model.colliders.self_contact import rest_exclusion
from clothbench.model.scene import OFFSET_KIND, Scene, body_pose
from clothbench.model.solver import Pbd, Solver, Vbd

# float4 rows per collider, by collider_rows' keys (colliders/kinds.py)
ROWS_PER_COLLIDER = {kind.plural: kind.rows for kind in KINDS}


def collider_rows(scene: Scene, dtype=np.float32, time: float = 0.0) -> dict[str, np.ndarray]:
    """The colliders as the kernels take them, float64 values rounded once to `dtype` rows of
    four, by kind (colliders/kinds.py `plural`) in the order the step applies them: spheres
    (centre, radius); cylinders (start, length), (unit axis, radius), (radial_r, 0); boxes
    (centre, 0), (axis i, half extent i) for i = 0, 1, 2, axis i being column i of its
    rotation; planes (point, 0), (unit normal, 0).
    A moving collider's rows are its pose at `time` (docs/semantics.md, "Moving colliders"):
    computed in float64 per step and rounded once, the same layout."""

    def rows(values) -> np.ndarray:
        return np.array(values, dtype=np.float64).reshape(-1, 4).astype(dtype)

    def placed(anchor, motion, *directions):
        # a fixed collider keeps the file's numbers exactly; a moving one its pose at `time`
        if motion is None:
            return (anchor, *directions)
        rot, trans = pose(anchor, np.eye(3), motion, time)
        return (tuple(trans), *(tuple(rot @ np.array(d, dtype=np.float64)) for d in directions))

    def cylinder(c):
        start, axis, radial = placed(c.start, c.motion, c.axis, c.radial)
        radial_r = (e * c.radius for e in radial)  # multiplied in float64, rounded once
        return ((*start, c.length), (*axis, c.radius), (*radial_r, 0.0))

    def box(b):
        rot, center = b.pose_at(time)  # fixed: the file's centre and rotation exactly
        return ((*center, 0.0), *((*rot[:, i], h) for i, h in enumerate(b.half_extents)))

    def plane(p):
        point, normal = placed(p.point, p.motion, p.unit_normal)
        return ((*point, 0.0), (*normal, 0.0))

    layout = {
        "sphere": lambda s: ((*placed(s.center, s.motion)[0], s.radius),),
        "cylinder": cylinder,
        "box": box,
        "plane": plane,
    }
    return {
        kind.plural: rows([row for c in getattr(scene, kind.plural) for row in layout[kind.name](c)]) for kind in KINDS
    }


def pose_rows(body, time: float, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) of a mesh or frame at `time` as a kernel takes them: the 3x3 rotation (row i is
    row i of R) and the translation, float64 per step, rounded once."""
    rot, trans = body_pose(body, time)
    return np.asarray(rot, dtype=np.float64).astype(dtype), np.asarray(trans, dtype=np.float64).astype(dtype)


def pin_targets(scene: Scene, time: float, dtype=np.float32) -> np.ndarray:
    """(pins, 3) positions at `time` of the pinned particles of a scene whose pins follow a
    body ([pins] attach): R(time) offset + T(time) in float64, rounded once, where offset is
    the particle's initial position in the body's frame, R(0)^T (x0 - T(0)). With [[pins]]
    groups each follows its own body, and a group that attaches to none stays at x0."""
    if not scene.pin_groups:
        rot, trans = body_pose(scene.body(scene.pin_attach), time)
        return (pin_offsets(scene) @ rot.T + trans).astype(dtype)
    out = scene.initial_state(np.float64)[0][scene.pinned(), :3]
    for slots, body, offsets in group_offsets(scene):
        rot, trans = body_pose(scene.body(body), time)
        out[slots] = offsets @ rot.T + trans
    return out.astype(dtype)


@lru_cache(maxsize=16)
def pin_offsets(scene: Scene) -> np.ndarray:
    """(pins, 3) body-frame offsets of the attached pins, float64, taken once per scene."""
    x0 = scene.initial_state(np.float64)[0][scene.pinned(), :3]
    rot0, trans0 = body_pose(scene.body(scene.pin_attach), 0.0)
    return (x0 - trans0) @ rot0  # rows: R0^T (x0 - T0)


@lru_cache(maxsize=16)
def group_offsets(scene: Scene) -> list[tuple[np.ndarray, str, np.ndarray]]:
    """Per attaching pinned set: its rows among scene.pinned(), its body, and its body-frame
    offsets (float64, taken once per scene)."""
    pinned = scene.pinned()
    x0 = scene.initial_state(np.float64)[0][:, :3]
    out = []
    for group in scene.pin_sets():
        particles = np.array(sorted(scene.pinned_by(group)), dtype=np.int64)
        if group.attach is None or not len(particles):
            continue
        rot0, trans0 = body_pose(scene.body(group.attach), 0.0)
        out.append((np.searchsorted(pinned, particles), group.attach, (x0[particles] - trans0) @ rot0))
    return out


@dataclass(frozen=True)
class MeshConstants:
    """docs/semantics.md, "Triangle mesh": what a kernel takes of one mesh, fixed for the run
    (the body frame does not change when the mesh moves): per triangle its corners a, b, c and
    its seven pseudo-normals (face, a, b, c, ab, ac, bc), float32 as rounded once on the host;
    the mesh's box; the margin and its square (float64, rounded once); closed or open."""

    geometry: object  # colliders.mesh.MeshGeometry (its bvh for the accelerated traversal)
    corners: np.ndarray  # (T, 3, 3)
    normals: np.ndarray  # (T, 7, 3)
    lo: np.ndarray  # (3,) box of every corner
    hi: np.ndarray
    margin: np.floating
    margin2: np.floating
    closed: bool

    @classmethod
    def of(cls, mesh, dtype=np.float32) -> "MeshConstants":
        g = mesh.geometry
        return cls(
            geometry=g,
            corners=g.corners.astype(dtype),
            normals=g.normals.astype(dtype),
            lo=g.lo.astype(dtype),
            hi=g.hi.astype(dtype),
            margin=dtype(mesh.margin),
            margin2=dtype(mesh.margin * mesh.margin),
            closed=g.closed,
        )


def rest_by_kind(scene: Scene, dtype=np.float32) -> tuple:
    """The three distinct rest lengths, structural h, shear sqrt(2) h and bend 2 sqrt(2) h,
    rounded once: the kernels take one per kind and pick it by offset (scene.OFFSET_KIND)."""
    rest = [dtype(r) for r in scene.rest_lengths()]
    kinds = tuple(rest[OFFSET_KIND.index(k)] for k in range(3))
    assert all(r == kinds[k] for k, r in zip(OFFSET_KIND, rest)), "stencil order changed"
    return kinds


def substep_constants(scene: Scene, solver: Pbd | Vbd, dtype=np.float32) -> tuple[float, dict]:
    """(h, what every substepping solver's constants hold): the substep h = dt / substeps in
    float64, for the solver's own products of it, and dt, h, the rest lengths and each
    iteration's Chebyshev weight, rounded once to `dtype` (docs/pbd.md, docs/vbd.md)."""
    t, h = dtype, solver.dt / solver.substeps
    omega = tuple(t(w) for w in solver.chebyshev_omega())
    return h, dict(dt=t(solver.dt), h=t(h), rest=rest_by_kind(scene, t), omega=omega)


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
    omega: tuple  # Jacobi: the Chebyshev weight of each iteration (all 1: no acceleration)

    @classmethod
    def of(cls, scene: Scene, solver: Pbd, dtype=np.float32) -> "PbdConstants":
        t = dtype
        h, shared = substep_constants(scene, solver, t)
        return cls(
            **shared,
            gh=tuple(t(g * h) for g in scene.gravity),
            at=tuple(t(c / (h * h)) for c in solver.compliance_for(scene)),
            damp=t(max(0.0, 1.0 - 12.0 * scene.damping * h / scene.mass)),
            relax=t(solver.relaxation),
        )


@dataclass(frozen=True)
class SelfCollisionConstants:
    """docs/semantics.md, "Self-collision": the pass's numbers, computed in float64 from the
    scene's [self_collision] and rounded once to the working precision."""

    thickness: np.floating
    thickness2: np.floating  # thickness * thickness in float64, rounded once
    relax: np.floating
    inv_cell: np.floating  # 1 / (cell * CELL_MARGIN): the grid's cell key is floor(x * inv_cell)
    exclude2: int  # pairs dr^2 + dc^2 < exclude2 apart on the grid are excluded (closer at rest)

    @classmethod
    def of(cls, scene: Scene, dtype=np.float32) -> "SelfCollisionConstants":
        c, t = scene.self_collision, dtype
        return cls(
            thickness=t(c.thickness),
            thickness2=t(c.thickness * c.thickness),
            relax=t(c.relaxation),
            inv_cell=t(c.inv_cell),
            exclude2=rest_exclusion(c.thickness, scene.spacing),
        )


@dataclass(frozen=True)
class VbdConstants:
    """docs/vbd.md, "Constants": computed in float64 from the scene and solver, rounded once
    to the working precision."""

    dt: np.floating
    h: np.floating  # dt / substeps
    gh2: tuple  # g * h^2, three components: gravity's share of the inertial target
    mh2: np.floating  # m / h^2: the inertia's stiffness
    bh: np.floating  # b / h: one spring's share of the implicit damping's stiffness
    k: np.floating
    rest: tuple  # rest lengths: structural, shear, bend
    omega: tuple  # the Chebyshev weight of each sweep (all 1: no acceleration)

    @classmethod
    def of(cls, scene: Scene, solver: Vbd, dtype=np.float32) -> "VbdConstants":
        t = dtype
        h, shared = substep_constants(scene, solver, t)
        return cls(
            **shared,
            gh2=tuple(t(g * h * h) for g in scene.gravity),
            mh2=t(scene.mass / (h * h)),
            bh=t(scene.damping / h),
            k=t(scene.stiffness),
        )
