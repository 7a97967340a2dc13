"""The NumPy reference of the PBD solver (docs/pbd.md), Jacobi and coloured Gauss-Seidel.

Same layout and the same element-wise, correctly rounded operations in the documented
order as the Verlet reference (numpy.py), whose collider code it reuses, so a PBD kernel
that follows docs/pbd.md reproduces the float32 Jacobi result bit for bit.
"""

from __future__ import annotations

import numpy as np

from ..constraints import coloured_batches
from ..scene import OFFSETS, Scene
from .base import Backend, BackendOptions
from ..harness.environment import cpu_model
from .numpy import COLLIDE, collider_constants, dot3, neighbour_regions
from .numpy import probe  # noqa: F401  (same availability as the Verlet reference)

KIND_OF_OFFSET = (0,) * 4 + (1,) * 4 + (2,) * 4  # structural, shear, bend (OFFSETS order)


class NumpyPbdBackend(Backend):
    name = "numpy"
    sweep_variants = ({"precision": "f32"}, {"precision": "f64"})

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        t = self.dtype = options.dtype
        n = scene.grid
        h = scene.dt / scene.substeps
        self.dt = t(scene.dt)
        self.h = t(h)
        self.gh = np.array([g * h for g in scene.gravity], dtype=t).reshape(3, 1, 1)
        compliance = scene.pbd_compliance()
        self.at = [t(c / (h * h)) for c in compliance]
        self.damp = t(max(0.0, 1.0 - 12.0 * scene.damping * h / scene.mass))
        self.relax = t(scene.relaxation)
        rest = [t(r) for r in scene.rest_lengths()]
        self.stencil = [
            (*neighbour_regions(n, dr, dc), rest[o], self.at[KIND_OF_OFFSET[o]])
            for o, (dr, dc) in enumerate(OFFSETS)
        ]
        counts = np.zeros((n, n), dtype=t)
        for i, _, _, _ in self.stencil:
            counts[i[1:]] += 1
        self.jacobi_scale = self.relax / counts  # relax / cnt, one division per particle
        self.batches = coloured_batches(n)
        self.batch_rest = [t(scene.rest_lengths()[[0, 4, 8][b.kind]]) for b in self.batches]
        self.colliders = [collider_constants(c, t) for c in scene.colliders]
        self.pos = np.zeros((3, n, n), dtype=t)
        self.vel = np.zeros((3, n, n), dtype=t)
        self.w = np.zeros((n, n), dtype=t)
        self.free = np.zeros((n, n), dtype=bool)

    @property
    def device(self) -> str:
        return cpu_model()

    @property
    def mode(self) -> str:
        return f"{self.options.precision}/pbd-{self.scene.pbd_method}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        n = self.scene.grid
        x = np.ascontiguousarray(pos[:, :3].T.reshape(3, n, n), dtype=self.dtype)
        xp = np.ascontiguousarray(prev[:, :3].T.reshape(3, n, n), dtype=self.dtype)
        self.pos = x
        self.vel = (x - xp) / self.dt
        self.w = np.ascontiguousarray(pos[:, 3].reshape(n, n), dtype=self.dtype)
        self.free = self.w != 0

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        n2 = self.scene.particles
        prev = self.pos - self.vel * self.dt
        out = []
        for plane in (self.pos, prev):
            a = np.empty((n2, 4), dtype=self.dtype)
            a[:, :3] = plane.reshape(3, n2).T
            a[:, 3] = self.w.reshape(n2)
            out.append(a)
        return out[0], out[1]

    def advance(self, steps: int) -> None:
        with np.errstate(all="ignore"):  # 0/0 is masked below; a blow-up is the harness's
            for _ in range(steps * self.scene.substeps):
                self._substep()

    def _substep(self) -> None:
        x, free = self.pos, self.free
        # predict: pinned particles stay and have no velocity
        v = np.where(free, self.vel + self.gh, 0).astype(self.dtype)
        xs = np.where(free, x + v * self.h, x).astype(self.dtype)
        if self.scene.pbd_method == "jacobi":
            xs = self._jacobi(xs)
        else:
            xs = self._coloured(xs)
        for kind, constants in self.colliders:
            COLLIDE[kind](xs, free, **constants)
        v = (xs - x) / self.h
        self.vel = v * self.damp
        self.pos = xs

    def _jacobi(self, x: np.ndarray) -> np.ndarray:
        w = self.w
        lam = [np.zeros(w[i[1:]].shape, dtype=self.dtype) for i, _, _, _ in self.stencil]
        for _ in range(self.scene.iterations):
            corr = np.zeros_like(x)
            for (i, j, rest, at), lam_o in zip(self.stencil, lam):
                d = x[i] - x[j]
                length2 = dot3(d, d)
                length = np.sqrt(length2)
                denom = (w[i[1:]] + w[j[1:]]) + at
                valid = (length2 > 0) & (denom > 0)
                dlam = ((-(length - rest)) - at * lam_o) / denom
                dlam[~valid] = 0
                lam_o += dlam
                s = (w[i[1:]] * dlam) / length
                s[~valid] = 0
                corr[i] += d * s
            x = x + corr * self.jacobi_scale  # a new array: the ping-pong of the GPU form
        return x

    def _coloured(self, x: np.ndarray) -> np.ndarray:
        n2 = self.scene.particles
        flat = x.reshape(3, n2).copy()
        w = self.w.reshape(n2)
        lam = [np.zeros(len(b.i), dtype=self.dtype) for b in self.batches]
        for _ in range(self.scene.iterations):
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
