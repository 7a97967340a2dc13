"""The NumPy reference of the VBD solver (docs/vbd.md): implicit Euler by Vertex Block Descent.

Same layout and the same element-wise, correctly rounded operations in the documented order as
the Verlet and PBD references, whose collider code it reuses, so a VBD kernel that follows
docs/vbd.md reproduces the float32 result bit for bit. Each colour's particles are updated
together from gathered neighbours: no neighbour shares their colour, so that is the in-place
Gauss-Seidel sweep exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clothbench.model.constraints import VERTEX_COLOURS, vertex_colours
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import Backend, BackendOptions
from clothbench.model.kernel_inputs import VbdConstants, pin_targets
from clothbench.backends.numpy.collide_mesh import Bodies
from clothbench.backends.numpy.pbd import NumpyPbdBackend
from clothbench.backends.numpy.self_collision import SelfCollisionPass
from clothbench.backends.numpy.verlet import COLLIDE, GridPlanes, collider_constants, dot3


def stencil_neighbours(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(12, n*n) neighbour index of each particle along each offset of the stencil (OFFSETS
    order) and whether that neighbour is inside the grid (where not, the index is the particle's
    own, never read)."""
    rows, cols = np.divmod(np.arange(n * n, dtype=np.int64), n)
    index = np.empty((len(OFFSETS), n * n), dtype=np.int64)
    inside = np.empty((len(OFFSETS), n * n), dtype=bool)
    for o, (dr, dc) in enumerate(OFFSETS):
        r, c = rows + dr, cols + dc
        inside[o] = (r >= 0) & (r < n) & (c >= 0) & (c < n)
        index[o] = np.where(inside[o], r * n + c, rows * n + cols)
    return index, inside


class NumpyVbdBackend(GridPlanes, Backend):
    name = "numpy"
    device_timer = ""  # host code: the wall clock is its only clock
    # the PBD reference's precisions, mode and scene features: VBD collides with the same code
    capabilities = replace(
        NumpyPbdBackend.capabilities,
        meshes=(*NumpyPbdBackend.capabilities.meshes, "vbd"),
        moving_colliders=(*NumpyPbdBackend.capabilities.moving_colliders, "vbd"),
        boxes=(*NumpyPbdBackend.capabilities.boxes, "vbd"),  # COLLIDE is the kinds table's: boxes included
        self_collision=(*NumpyPbdBackend.capabilities.self_collision, "vbd"),
    )

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        t = self.dtype = options.dtype
        n = scene.grid
        c = self.constants = VbdConstants.of(scene, solver, t)  # the f64 reference takes them in float64
        self.dt, self.h, self.omega = c.dt, c.h, c.omega
        self.gh2 = np.array(c.gh2, dtype=t).reshape(3, 1, 1)
        self.neighbour, self.inside = stencil_neighbours(n)
        self.rest = np.array([c.rest[kind] for kind in OFFSET_KIND], dtype=t)
        count = self.inside.sum(axis=0).astype(t)  # the springs each particle has: exact
        self.cb = count * c.bh  # cnt * bh: the particle's implicit damping stiffness
        self.diagonal = c.mh2 + self.cb  # inertia and damping: the Hessian's diagonal
        self.colour = vertex_colours(n)
        self.colliders = collider_constants(scene, t)
        # meshes and moving colliders as in the PBD reference: one "step" of Bodies per substep
        self.substep_seconds = solver.dt / solver.substeps
        colliding = scene.replace(pin_attach=None)
        needed = Bodies.needed(colliding)
        self.bodies = Bodies(colliding, self.substep_seconds, t, collider_constants, COLLIDE) if needed else None
        self.pinned = scene.pinned() if scene.pin_attach is not None else None
        self.substeps_done = 0
        # [self_collision]: per substep after the iterations, before the colliders (as PBD's)
        self.self_collision = SelfCollisionPass(scene, t) if scene.self_collision is not None else None
        self.pos = self.vel = np.zeros((3, n, n), dtype=t)
        self.w, self.free = np.zeros((n, n), dtype=t), np.zeros((n, n), dtype=bool)
        self.sweep_order: list[np.ndarray] = []

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos = self.planes(pos)
        self.vel = (self.pos - self.planes(prev)) / self.dt
        self.set_inverse_mass(pos)
        free = self.free.reshape(-1)
        # the free particles of each colour, in colour order (what a sweep updates), with their
        # neighbours along the stencil and whether each is inside the grid
        self.sweep_order = []
        for c in range(VERTEX_COLOURS):
            idx = np.flatnonzero(free & (self.colour == c))
            self.sweep_order.append((idx, self.neighbour[:, idx], self.inside[:, idx]))
        self.substeps_done = 0
        if self.bodies is not None:
            self.bodies.steps = 0

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state(self.pos), self.state(self.pos - self.vel * self.dt)

    def advance(self, steps: int) -> None:
        with np.errstate(all="ignore"):  # a blow-up is the harness's to report
            for _ in range(steps * self.solver.substeps):
                self._substep()

    def _substep(self) -> None:
        x, free = self.pos, self.free
        # predict: the inertial target y = x + v h + g h^2, and the first iterate
        v = np.where(free, self.vel, 0).astype(self.dtype)
        y = ((x + v * self.h) + self.gh2).astype(self.dtype)
        xs = np.where(free, y, x).astype(self.dtype)
        self.substeps_done += 1
        if self.pinned is not None:  # attached pins: their target at the end of the substep
            time = self.substeps_done * self.substep_seconds
            xs.reshape(3, -1)[:, self.pinned] = pin_targets(self.scene, time, self.dtype).T
        xs = self.solve(xs, y, x)
        self.contact_then_collide(xs)  # the poses at the end of the substep
        self.vel = (xs - x) / self.h
        self.pos = xs

    def solve(self, xs: np.ndarray, y: np.ndarray, x0: np.ndarray) -> np.ndarray:
        """The substep's iterations: `iterations` sweeps over the colours, each particle one
        3x3 Newton step, with Chebyshev extrapolation where chebyshev_rho > 0."""
        n2 = self.scene.particles
        flat, y, x0 = xs.reshape(3, n2), y.reshape(3, n2), x0.reshape(3, n2)
        free = self.free.reshape(n2)
        chebyshev = self.solver.chebyshev_rho > 0
        before = None  # the input of the sweep before this one, for Chebyshev
        for k in range(self.solver.iterations):
            sweep_input = flat.copy() if chebyshev else None
            for idx, neighbour, inside in self.sweep_order:
                if len(idx):
                    flat[:, idx] = self.newton_step(flat, idx, neighbour, inside, y, x0)
            if chebyshev and k > 0:  # x = omega (x - before) + before, free particles only
                flat[:, free] = self.omega[k] * (flat[:, free] - before[:, free]) + before[:, free]
            if chebyshev:
                before = sweep_input
        return flat.reshape(xs.shape)

    def newton_step(self, flat, idx, neighbour, inside, y, x0) -> np.ndarray:
        """The positions of particles `idx` after one 3x3 Newton step each on the incremental
        potential, the others held (docs/vbd.md, "One particle's step"). The gradient f and the
        six entries of H are rows of one array, so a spring that does not count leaves all
        nine as they were in one select."""
        c, t = self.constants, self.dtype
        xi = flat[:, idx]
        acc = np.empty((9, len(idx)), dtype=t)  # f.x, f.y, f.z, Hxx, Hyy, Hzz, Hxy, Hxz, Hyz
        acc[:3] = (xi - y[:, idx]) * c.mh2 + (xi - x0[:, idx]) * self.cb[idx]  # inertia, then damping
        acc[3:6] = self.diagonal[idx]
        acc[6:] = 0
        term = np.empty_like(acc)
        for o in range(len(OFFSETS)):
            d = xi - flat[:, neighbour[o]]
            length2 = dot3(d, d)
            on = inside[o] & (length2 > 0)  # outside the grid or coincident: nothing added
            s = c.k * (t(1) - self.rest[o] / np.sqrt(length2))
            a = np.where(s > 0, s, t(0)).astype(t)  # the clamped isotropic part: k max(1 - rest/L, 0)
            bd = ((c.k - a) / length2) * d  # bx, by, bz
            np.multiply(d, s, out=term[:3])
            np.multiply(bd, d, out=term[3:6])
            term[3:6] += a  # a + bx * d.x, ...: one addition of two rounded terms, either order
            np.multiply(bd[0], d[1], out=term[6])
            np.multiply(bd[0], d[2], out=term[7])
            np.multiply(bd[1], d[2], out=term[8])
            acc = np.where(on, acc + term, acc)
        step, ok = ldlt_solve(*acc[3:], acc[:3])
        return np.where(ok, xi - step, xi)


def ldlt_solve(hxx, hyy, hzz, hxy, hxz, hyz, f):
    """(H^-1 f, ok) for symmetric 3x3 H by its LDL^T factorisation in docs/vbd.md's order; ok
    where every pivot is > 0 (always, for the positive definite H of a finite state)."""
    d0 = hxx
    l10 = hxy / d0
    l20 = hxz / d0
    d1 = hyy - l10 * hxy
    tt = hyz - l20 * hxy
    l21 = tt / d1
    d2 = (hzz - l20 * hxz) - l21 * tt
    z0 = f[0]
    z1 = f[1] - l10 * z0
    z2 = (f[2] - l20 * z0) - l21 * z1
    p2 = z2 / d2
    p1 = z1 / d1 - l21 * p2
    p0 = (z0 / d0 - l10 * p1) - l20 * p2
    return np.stack([p0, p1, p2]), (d0 > 0) & (d1 > 0) & (d2 > 0)
