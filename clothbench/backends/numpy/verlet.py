"""The NumPy reference: docs/semantics.md, vectorised over the grid, float32 or float64.

Every operation below is an element-wise, correctly rounded NumPy operation performed in
the order the semantics fix, so a kernel that does the same operations in the same order
(without FMA contraction) reproduces the float32 result bit for bit.
The float64 run is the reference every accuracy figure is measured against.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.colliders.kinds import KINDS
from clothbench.environment import cpu_model
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.model.kernel_inputs import VerletConstants, collider_rows
from clothbench.backends.numpy.collide_mesh import Bodies
from clothbench.backends.numpy.self_collision import SelfCollisionPass


def probe() -> Availability:
    return Availability(True, device=cpu_model())


def neighbour_regions(n: int, dr: int, dc: int):
    """Slices (rows, cols) of the particles i that have neighbour i + (dr, dc), and of those
    neighbours, so that a neighbour outside the grid is skipped rather than added as zero."""
    i_rows = slice(max(0, -dr), n - max(0, dr))
    i_cols = slice(max(0, -dc), n - max(0, dc))
    j_rows = slice(max(0, dr), n + min(0, dr))
    j_cols = slice(max(0, dc), n + min(0, dc))
    return (slice(None), i_rows, i_cols), (slice(None), j_rows, j_cols)


class GridPlanes:
    """The state as (3, n, n) component planes and an (n, n) inverse mass: the same arithmetic
    as (n*n, 4) rows, with faster slicing. Shared by the Verlet and PBD references."""

    @property
    def device(self) -> str:
        return cpu_model()

    def planes(self, state: np.ndarray) -> np.ndarray:
        n = self.scene.grid
        return np.ascontiguousarray(state[:, :3].T.reshape(3, n, n), dtype=self.dtype)

    def set_inverse_mass(self, pos: np.ndarray) -> None:
        n = self.scene.grid
        self.w = np.ascontiguousarray(pos[:, 3].reshape(n, n), dtype=self.dtype)
        self.free = self.w != 0

    @property
    def self_collision_pass(self):
        """The [self_collision] pass as a function of the positions (changed in place), or None."""
        if self.self_collision is None:
            return None
        return lambda x: self.self_collision(x, self.w)

    def contact_then_collide(self, x: np.ndarray) -> None:
        """x (3, n, n) in place: the [self_collision] pass where the scene has it, then every
        collider in the order of colliders/kinds.py, meshes after the planes (Bodies: per-step
        poses and attached pins first). The end of a Verlet step and of a PBD or VBD substep."""
        contact = self.self_collision_pass
        if self.bodies is not None:
            self.bodies.collide(x, self.free, contact)
            return
        if contact is not None:
            contact(x)
        for kind, constants in self.colliders:
            COLLIDE[kind](x, self.free, **constants)

    def state(self, planes: np.ndarray) -> np.ndarray:
        """(n*n, 4) rows of `planes` with the inverse mass as w."""
        n2 = self.scene.particles
        a = np.empty((n2, 4), dtype=self.dtype)
        a[:, :3] = planes.reshape(3, n2).T
        a[:, 3] = self.w.reshape(n2)
        return a


class NumpyBackend(GridPlanes, Backend):
    name = "numpy"
    device_timer = ""  # host code: the wall clock is its only clock
    # one mode, no --strict: it is what --strict is measured against
    capabilities = Capabilities(
        precisions=("f32", "f64"),
        strict=False,
        sweep_variants=({"precision": "f32"}, {"precision": "f64"}),
        meshes=("verlet",),
        moving_colliders=("verlet",),  # pbd.py adds "pbd" to its copy
        boxes=("verlet",),
        self_collision=("verlet",),
        mesh_collisions=("naive",),  # its chunked loop gives the naive loop's bits (collide_mesh.py)
    )

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        t = self.dtype = options.dtype
        n = scene.grid
        c = VerletConstants.of(scene, solver, t)  # the f64 reference takes them in float64
        self.dt, self.dt2, self.k, self.b = c.dt, c.dt2, c.k, c.b
        self.gravity = np.array(c.g, dtype=t).reshape(3, 1, 1)
        self.springs = [(*neighbour_regions(n, dr, dc), c.rest[kind]) for (dr, dc), kind in zip(OFFSETS, OFFSET_KIND)]
        self.colliders = collider_constants(scene, t)
        # meshes, moving colliders, attached pins (collide_mesh.py); None: the scene has none
        self.bodies = Bodies(scene, solver.dt, t, collider_constants, COLLIDE) if Bodies.needed(scene) else None
        # [self_collision]: after the pins are placed, before the colliders; None: no pass
        self.self_collision = SelfCollisionPass(scene, t) if scene.self_collision is not None else None
        self.pos = self.prev = np.zeros((3, n, n), dtype=t)
        self.w, self.free = np.zeros((n, n), dtype=t), np.zeros((n, n), dtype=bool)

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos, self.prev = self.planes(pos), self.planes(prev)
        self.set_inverse_mass(pos)
        if self.bodies is not None:
            self.bodies.steps = 0  # the uploaded state is at t = 0: moving bodies start over

    def advance(self, steps: int) -> None:
        # 0/0 for coincident particles is replaced below; overflow in a blow-up is the
        # harness's to report, not NumPy's to warn about
        with np.errstate(all="ignore"):
            for _ in range(steps):
                self.pos, self.prev = self._step(self.pos, self.prev), self.pos

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state(self.pos), self.state(self.prev)

    def _step(self, pos: np.ndarray, prev: np.ndarray) -> np.ndarray:
        # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
        vel = (pos - prev) / self.dt
        bv = self.b * vel
        force = np.zeros_like(pos)
        for i, j, rest in self.springs:  # step 5: the 12 neighbours, in OFFSETS order
            d = pos[j] - pos[i]
            length2 = dot3(d, d)
            length = np.sqrt(length2)
            s = (self.k * (length - rest)) / length
            s[length2 == 0] = 0  # coincident particles: no direction, no spring force
            force[i] += s * d - bv[i]
        # step 6: Verlet, acceleration = gravity + force * inverse mass
        force *= self.w
        force += self.gravity
        force *= self.dt2
        new = 2 * pos
        new -= prev
        new += force
        np.copyto(new, pos, where=~self.free)  # pinned particles do not move
        self.contact_then_collide(new)
        return new


def collider_constants(scene: Scene, t, time: float = 0.0) -> list[tuple[str, dict]]:
    """(kind, constants) of every collider in the order the step applies them, from
    kernel_inputs.collider_rows in the working precision, shaped for (3, n, n) planes."""
    rows = collider_rows(scene, t, time)  # time: the poses of moving colliders
    return [
        (kind.name, ARGUMENTS[kind.name](*block))
        for kind in KINDS
        for block in rows[kind.plural].reshape(-1, kind.rows, 4)
    ]


def _vec(row):
    return row[:3].reshape(3, 1, 1)


# Each kind's float4 rows (kernel_inputs.collider_rows) as its response's arguments: arrays
# and scalars only, which CuPy's peer moves to its device (peers/cupy_numpy.py).
ARGUMENTS = {
    "sphere": lambda s: {"c": _vec(s), "r": s[3]},  # (centre, radius)
    "cylinder": lambda a, u, radial_r: {  # (start, length), (axis, r), (radial_r, 0)
        "a": _vec(a),
        "u": _vec(u),
        "length": a[3],
        "r": u[3],
        "radial_r": _vec(radial_r),
    },
    "box": lambda c, ax0, ax1, ax2: {  # (centre, 0), (axis i, half extent i)
        "c": _vec(c),
        "ax0": _vec(ax0),
        "ax1": _vec(ax1),
        "ax2": _vec(ax2),
        "h0": ax0[3],
        "h1": ax1[3],
        "h2": ax2[3],
    },
    "plane": lambda p, nrm: {"p0": _vec(p), "nrm": _vec(nrm)},  # (point, 0), (unit normal, 0)
}


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(a.x*b.x + a.y*b.y) + a.z*b.z, the association every kernel uses."""
    out = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


def collide_sphere(x, free, c, r) -> None:
    d = x - c
    length2 = dot3(d, d)
    length = np.sqrt(length2)
    inside = (length < r) & free
    if not inside.any():
        return
    pushed = c + d * (r / length)
    # a particle exactly at the centre has no direction: push it straight up
    at_center = inside & (length2 == 0)
    pushed[1][at_center] = c[1, 0, 0] + r
    pushed[0][at_center] = c[0, 0, 0]
    pushed[2][at_center] = c[2, 0, 0]
    np.copyto(x, pushed, where=inside)


def collide_cylinder(x, free, a, u, length, r, radial_r) -> None:
    d = x - a
    t = dot3(d, u)  # axial coordinate (m) from the start cap
    q = u * t
    p = d - q  # radial vector
    rho2 = dot3(p, p)
    rho = np.sqrt(rho2)
    inside = (t > 0) & (t < length) & (rho < r) & free
    if not inside.any():
        return
    # push out the shortest way: through the side, or through the nearer cap
    side = r - rho
    to_end = length - t
    through_side = (side <= t) & (side <= to_end)
    through_start = ~through_side & (t <= to_end)
    pushed_side = (a + q) + p * (r / rho)
    on_axis = rho2 == 0
    pushed_side[:, on_axis] = ((a + q) + radial_r)[:, on_axis]
    pushed = np.where(through_side, pushed_side, np.where(through_start, x - q, x + u * to_end))
    np.copyto(x, pushed, where=inside)


def collide_box(x, free, c, ax0, ax1, ax2, h0, h1, h2) -> None:
    """docs/semantics.md, "Box": a particle strictly inside is moved along the axis of least
    penetration to the face on its side (ties to the lower axis, the + face at l == 0)."""
    d = x - c
    l0, l1, l2 = dot3(d, ax0), dot3(d, ax1), dot3(d, ax2)  # its coordinates along the box's axes
    p0, p1, p2 = h0 - np.abs(l0), h1 - np.abs(l1), h2 - np.abs(l2)  # depth through each pair of faces
    inside = (p0 > 0) & (p1 > 0) & (p2 > 0) & free
    if not inside.any():
        return
    take1 = p1 < p0
    least = np.where(take1, p1, p0)
    take2 = p2 < least
    lk = np.where(take2, l2, np.where(take1, l1, l0))
    hk = np.where(take2, h2, np.where(take1, h1, h0))
    axis = np.where(take2, ax2, np.where(take1, ax1, ax0))
    s = np.where(lk >= 0, hk, -hk)
    np.copyto(x, x + axis * (s - lk), where=inside)


def collide_plane(x, free, p0, nrm) -> None:
    dist = dot3(x - p0, nrm)
    inside = (dist < 0) & free
    if inside.any():
        np.copyto(x, x - nrm * dist, where=inside)


# each kind's response in the reference, by the name colliders/kinds.py gives it
COLLIDE = {kind.name: globals()[kind.function("numpy")] for kind in KINDS}
