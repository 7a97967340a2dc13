"""The NumPy reference of the PBD solver (docs/pbd.md), Jacobi and coloured Gauss-Seidel.

Same layout and the same element-wise, correctly rounded operations in the documented
order as the Verlet reference (numpy/verlet.py), whose collider code it reuses, so a PBD kernel
that follows docs/pbd.md reproduces the float32 Jacobi result bit for bit.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clothbench.model.constraints import coloured_batches
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Pbd
from clothbench.backends.base import Backend, BackendOptions
from clothbench.model.kernel_inputs import PbdConstants, pin_targets
from clothbench.backends.numpy.collide_mesh import Bodies
from clothbench.backends.numpy.self_collision import SelfCollisionPass
from clothbench.backends.numpy.verlet import (
    COLLIDE,
    GridPlanes,
    NumpyBackend,
    collider_constants,
    dot3,
    neighbour_regions,
)


class NumpyPbdBackend(GridPlanes, Backend):
    name = "numpy"
    device_timer = ""  # host code: the wall clock is its only clock
    # the same two precisions and one mode; meshes and motion too (docs/pbd.md, "Colliders,
    # motion and attached pins")
    capabilities = replace(
        NumpyBackend.capabilities,
        meshes=("verlet", "pbd"),
        moving_colliders=("verlet", "pbd"),
        boxes=("verlet", "pbd"),
        self_collision=("verlet", "pbd"),
    )

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        t = self.dtype = options.dtype
        n = scene.grid
        c = PbdConstants.of(scene, solver, t)  # the f64 reference takes them in float64
        self.dt, self.h, self.at, self.damp, self.relax = c.dt, c.h, c.at, c.damp, c.relax
        self.omega = c.omega
        self.gh = np.array(c.gh, dtype=t).reshape(3, 1, 1)
        self.stencil = [
            (*neighbour_regions(n, dr, dc), c.rest[kind], c.at[kind]) for (dr, dc), kind in zip(OFFSETS, OFFSET_KIND)
        ]
        counts = np.zeros((n, n), dtype=t)
        for i, _, _, _ in self.stencil:
            counts[i[1:]] += 1
        self.jacobi_scale = self.relax / counts  # relax / cnt, one division per particle
        self.batches = coloured_batches(n)
        self.batch_rest = [c.rest[b.kind] for b in self.batches]
        self.colliders = collider_constants(scene, t)
        # meshes and moving colliders: collide_mesh.Bodies, one "step" of it per substep; the
        # attached pins are predict's, so its scene is this one without the attachment
        self.substep_seconds = solver.dt / solver.substeps  # float64: substep j ends at j * this
        colliding = scene.replace(pin_attach=None)
        needed = Bodies.needed(colliding)
        self.bodies = Bodies(colliding, self.substep_seconds, t, collider_constants, COLLIDE) if needed else None
        self.pinned = scene.pinned() if scene.pin_attach is not None else None
        self.substeps_done = 0  # since the last upload: the clock of the poses and pin targets
        # [self_collision]: per substep after the constraint iterations, before the colliders
        self.self_collision = SelfCollisionPass(scene, t) if scene.self_collision is not None else None
        self.pos = self.vel = np.zeros((3, n, n), dtype=t)
        self.w, self.free = np.zeros((n, n), dtype=t), np.zeros((n, n), dtype=bool)

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos = self.planes(pos)
        self.vel = (self.pos - self.planes(prev)) / self.dt
        self.set_inverse_mass(pos)
        self.substeps_done = 0  # the uploaded state is at t = 0: moving bodies start over
        if self.bodies is not None:
            self.bodies.steps = 0

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state(self.pos), self.state(self.pos - self.vel * self.dt)

    def advance(self, steps: int) -> None:
        with np.errstate(all="ignore"):  # 0/0 is masked below; a blow-up is the harness's
            for _ in range(steps * self.solver.substeps):
                self._substep()

    def _substep(self) -> None:
        x, free = self.pos, self.free
        # predict: pinned particles stay and have no velocity
        v = np.where(free, self.vel + self.gh, 0).astype(self.dtype)
        xs = np.where(free, x + v * self.h, x).astype(self.dtype)
        self.substeps_done += 1
        if self.pinned is not None:  # attached pins: their target at the end of the substep
            time = self.substeps_done * self.substep_seconds
            xs.reshape(3, -1)[:, self.pinned] = pin_targets(self.scene, time, self.dtype).T
        if self.solver.method == "jacobi":
            xs = self._jacobi(xs)
        else:
            xs = self._coloured(xs)
        self.contact_then_collide(xs)  # the poses at the end of the substep
        v = (xs - x) / self.h
        self.vel = v * self.damp
        self.pos = xs

    def _jacobi(self, x: np.ndarray) -> np.ndarray:
        w, scale = self.w, self.jacobi_scale
        lam = [np.zeros(w[i[1:]].shape, dtype=self.dtype) for i, _, _, _ in self.stencil]
        x_before, lam_before = x, lam  # the iterate before this one, for Chebyshev
        chebyshev = self.solver.chebyshev_rho > 0
        for k in range(self.solver.iterations):
            corr = np.zeros_like(x)
            lam_next = []
            for (i, j, rest, at), lam_o in zip(self.stencil, lam):
                d = x[i] - x[j]
                length2 = dot3(d, d)
                length = np.sqrt(length2)
                denom = (w[i[1:]] + w[j[1:]]) + at
                valid = (length2 > 0) & (denom > 0)
                dlam = ((-(length - rest)) - at * lam_o) / denom
                dlam[~valid] = 0
                lam_next.append(lam_o + dlam * scale[i[1:]])  # the share of dlam the position takes
                s = (w[i[1:]] * dlam) / length
                s[~valid] = 0
                corr[i] += d * s
            x_next = x + corr * scale  # a new array: the ping-pong of the GPU form
            if chebyshev and k > 0:  # y = omega (y - before) + before, positions and lambda alike
                omega = self.omega[k]
                x_next = omega * (x_next - x_before) + x_before
                lam_next = [omega * (a - b) + b for a, b in zip(lam_next, lam_before)]
            x_before, lam_before = x, lam
            x, lam = x_next, lam_next
        return x

    def _coloured(self, x: np.ndarray) -> np.ndarray:
        n2 = self.scene.particles
        flat = x.reshape(3, n2).copy()
        w = self.w.reshape(n2)
        lam = [np.zeros(len(b.i), dtype=self.dtype) for b in self.batches]
        for _ in range(self.solver.iterations):
            for batch, rest, lam_b in zip(self.batches, self.batch_rest, lam):
                i, j, at = batch.i, batch.j, self.at[batch.kind]
                d = flat[:, i] - flat[:, j]
                length2 = dot3(d, d)
                length = np.sqrt(length2)
                denom = (w[i] + w[j]) + at
                valid = (length2 > 0) & (denom > 0)
                dlam = ((-(length - rest)) - at * lam_b) / denom
                dlam[~valid] = 0
                lam_b += dlam
                si = (w[i] * dlam) / length
                sj = (w[j] * dlam) / length
                si[~valid] = 0
                sj[~valid] = 0
                # a batch shares no particle, so these scattered writes never collide
                flat[:, i] = flat[:, i] + d * si
                flat[:, j] = flat[:, j] - d * sj
        return flat.reshape(x.shape)
