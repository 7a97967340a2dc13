"""The exact answer VBD converges to: each substep's implicit-Euler step solved by a full Newton
method with a sparse linear solve, in float64 (docs/vbd.md, "The exact step").

It is the NumPy VBD reference with its sweeps replaced: the same predict (inertial target,
pins), the same colliders after the solve and the same update, so VBD with enough iterations
and this differ only by what VBD has not converged. The Newton iteration minimises the same
incremental potential over every free particle at once: the full Hessian of the springs where
it is positive definite along the step, else the clamped form VBD uses, with a backtracking
line search on the potential; it stops when the Newton step is at most TOLERANCE in every
coordinate, and that step (the distance to the solution, to first order) is the residual
recorded for the substep.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from clothbench.model.constraints import coloured_batches
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import BackendOptions
from clothbench.model.kernel_inputs import VbdConstants
from clothbench.backends.numpy.vbd import NumpyVbdBackend

TOLERANCE = 1e-12  # m: the largest coordinate of the last Newton step
MAX_NEWTON = 100
ARMIJO = 1e-4  # the sufficient decrease of the line search


class ExactImplicitStep(NumpyVbdBackend):
    """The NumPy VBD backend whose substep solve is exact (float64 only)."""

    name = "exact implicit"

    def __init__(self, scene: Scene, solver: Vbd):
        super().__init__(scene, solver, BackendOptions(precision="f64"))
        c = VbdConstants.of(scene, solver, np.float64)
        self.k, self.mh2 = float(c.k), float(c.mh2)
        batches = coloured_batches(scene.grid)
        self.spring_i = np.concatenate([b.i for b in batches]).astype(np.int64)
        self.spring_j = np.concatenate([b.j for b in batches]).astype(np.int64)
        self.spring_rest = np.concatenate([np.full(len(b.i), c.rest[b.kind]) for b in batches])
        self.residuals: list[float] = []  # per substep: the last Newton step's largest coordinate (m)
        self.newton_iterations: list[int] = []

    def solve(self, xs: np.ndarray, y: np.ndarray, x0: np.ndarray) -> np.ndarray:
        n2 = self.scene.particles
        x = xs.reshape(3, n2).T.copy()  # (n2, 3)
        y, x0 = y.reshape(3, n2).T, x0.reshape(3, n2).T
        free = np.flatnonzero(self.free.reshape(n2))
        dofs = (3 * free[:, None] + np.arange(3)).reshape(-1)
        for iteration in range(1, MAX_NEWTON + 1):
            grad = self.gradient(x, y, x0)[dofs]
            step = self.descent(x, grad, dofs, exact=True)
            size = float(np.abs(step).max(initial=0.0))
            if size <= TOLERANCE:
                self.residuals.append(size)
                self.newton_iterations.append(iteration)
                return x.T.reshape(xs.shape).copy()
            x = self.line_search(x, y, x0, grad, step, dofs)
        raise ClothbenchError(f"the exact implicit step did not converge in {MAX_NEWTON} Newton iterations")

    def descent(self, x: np.ndarray, grad: np.ndarray, dofs: np.ndarray, exact: bool) -> np.ndarray:
        """The Newton step -H^-1 grad over the free coordinates; with `exact`, the full Hessian's
        where that is a descent direction, else the clamped (positive definite) one's."""
        hessian = self.hessian(x, clamped=not exact)[dofs][:, dofs]
        # the Hessian is symmetric, so SuperLU orders it by minimum degree on its own pattern
        # (A^T + A = A): 0.31 s a solve on the 64^2 drape's 12,282 unknowns, 0.55 s with the
        # default COLAMD (the Zen 3, 2026-12-06)
        step = spsolve(hessian.tocsc(), -grad, permc_spec="MMD_AT_PLUS_A")
        if exact and not (np.all(np.isfinite(step)) and grad @ step < 0):
            return self.descent(x, grad, dofs, exact=False)
        return step

    def line_search(self, x, y, x0, grad, step, dofs) -> np.ndarray:
        """x + alpha step, alpha halved from 1 until the potential decreases enough (Armijo). A
        step too small for the potential's rounding to tell is taken whole."""
        if np.abs(step).max() < 1e-8:
            trial = x.copy()
            trial.reshape(-1)[dofs] += step
            return trial
        e0, slope, alpha = self.potential(x, y, x0), float(grad @ step), 1.0
        for _ in range(60):
            trial = x.copy()
            trial.reshape(-1)[dofs] += alpha * step
            if self.potential(trial, y, x0) <= e0 + ARMIJO * alpha * slope:
                return trial
            alpha *= 0.5
        raise ClothbenchError("the exact implicit step's line search found no decrease")

    def springs(self, x: np.ndarray):
        d = x[self.spring_i] - x[self.spring_j]
        length = np.sqrt((d * d).sum(axis=1))
        return d, length

    def potential(self, x, y, x0) -> float:
        """The incremental potential (docs/vbd.md) up to a constant: inertia, damping, springs."""
        free = self.free.reshape(-1)
        _, length = self.springs(x)
        inertia = 0.5 * self.mh2 * ((x - y)[free] ** 2).sum()
        damping = 0.5 * (self.cb[free, None] * (x - x0)[free] ** 2).sum()
        return float(inertia + damping + 0.5 * self.k * ((length - self.spring_rest) ** 2).sum())

    def gradient(self, x, y, x0) -> np.ndarray:
        d, length = self.springs(x)
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(length > 0, self.k * (1 - self.spring_rest / length), 0.0)
        force = d * s[:, None]
        grad = self.mh2 * (x - y) + self.cb[:, None] * (x - x0)
        np.add.at(grad, self.spring_i, force)
        np.add.at(grad, self.spring_j, -force)
        return grad.reshape(-1)

    def hessian(self, x, clamped: bool) -> sp.csr_matrix:
        n2 = self.scene.particles
        d, length = self.springs(x)
        on = length > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            iso = np.where(on, self.k * (1 - self.spring_rest / length), 0.0)
            if clamped:
                iso = np.maximum(iso, 0.0)
            rank1 = np.where(on, (self.k - iso) / (length * length), 0.0)
        block = iso[:, None, None] * np.eye(3) + rank1[:, None, None] * d[:, :, None] * d[:, None, :]
        a = np.arange(3)
        rows, cols, vals = [], [], []
        for p, q, sign in ((self.spring_i, self.spring_i, 1), (self.spring_j, self.spring_j, 1),
                           (self.spring_i, self.spring_j, -1), (self.spring_j, self.spring_i, -1)):  # fmt: skip
            rows.append((3 * p[:, None, None] + a[None, :, None]).repeat(3, axis=2).reshape(-1))
            cols.append((3 * q[:, None, None] + a[None, None, :]).repeat(3, axis=1).reshape(-1))
            vals.append((sign * block).reshape(-1))
        diagonal = np.repeat(self.diagonal, 3)
        rows.append(np.arange(3 * n2))
        cols.append(np.arange(3 * n2))
        vals.append(diagonal)
        return sp.coo_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n2, 3 * n2)
        ).tocsr()


@lru_cache(maxsize=16)
def exact_implicit(scene: Scene, solver: Vbd, steps: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(pos, prev, worst residual in m) after `steps` exact implicit-Euler steps of `scene`
    with `solver`'s dt, substeps, start, pins and colliders (its iterations do not matter)."""
    stepper = ExactImplicitStep(scene, solver)
    stepper.upload(*stepper.initial_state())
    stepper.advance(steps)
    pos, prev = stepper.read()
    for a in (pos, prev):
        a.setflags(write=False)
    return pos, prev, max(stepper.residuals, default=0.0)
