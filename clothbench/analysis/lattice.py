"""The linearised stability limit: the dynamical matrix of the infinite flat lattice over
Bloch wave vectors, its largest frequency, the Gershgorin bound 24 k/m, and the dt limit of
explicit Verlet with the lagged-velocity damping (docs/accuracy.md)."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from clothbench.model.scene import OFFSETS, Scene


def _spring_block(dr: int, dc: int, stretch: float) -> np.ndarray:
    """Linearised stiffness (units of k) of the spring at offset (dr, dc) at `stretch`."""
    e = np.array([dc, 0.0, dr]) / math.hypot(dr, dc)  # col -> x, row -> z
    along = np.outer(e, e)
    return along + (1.0 - 1.0 / stretch) * (np.eye(3) - along)


def dynamical_matrix(q: np.ndarray, stretch: float = 1.0) -> np.ndarray:
    """D(q) / (k/m) for Bloch wave vectors q (..., 2) = (q_col, q_row), as (..., 3, 3).

    The infinite lattice of the 12-spring stencil, every spring at `stretch` times its rest
    length. Linearising the spring force about a spring of direction e and length L gives the
    stiffness k [e e^T + (1 - rest/L)(I - e e^T)]: along the spring k, across it the tension.
    At rest length (stretch 1) the sheet has no stiffness out of its plane.
    """
    q = np.asarray(q, dtype=np.float64)
    out = np.zeros(q.shape[:-1] + (3, 3))
    for dr, dc in OFFSETS:
        out += (1.0 - np.cos(q[..., 0] * dc + q[..., 1] * dr))[..., None, None] * _spring_block(dr, dc, stretch)
    return out


@lru_cache(maxsize=16)
def lattice_omega2(stretch: float = 1.0) -> float:
    """max over q of the largest eigenvalue of D(q), in units of k/m (10.25 at stretch 1).

    A 61x61 grid over [0, pi]^2 (the lattice's mirror symmetries cover the rest of the
    Brillouin zone), then the best point refined by zooming in eight times."""
    lo, hi = np.zeros(2), np.full(2, math.pi)
    best, width = None, math.pi
    for _ in range(9):
        a = np.linspace(lo[0], hi[0], 61)
        b = np.linspace(lo[1], hi[1], 61)
        qs = np.stack(np.meshgrid(a, b, indexing="ij"), axis=-1)
        w = np.linalg.eigvalsh(dynamical_matrix(qs, stretch))[..., -1]
        i = np.unravel_index(np.argmax(w), w.shape)
        best = float(w[i])
        width /= 10
        centre = qs[i]
        lo = np.clip(centre - width, 0, math.pi)
        hi = np.clip(centre + width, 0, math.pi)
    return best


GERSHGORIN = 24.0  # omega^2 <= 24 k/m: 12 springs, each adding k to the diagonal and k off it


def omega_max(k: float, m: float, stretch: float = 1.0) -> float:
    """Largest natural frequency (rad/s) of the infinite flat lattice at `stretch`."""
    return math.sqrt(lattice_omega2(stretch) * k / m)


def gershgorin_omega(k: float, m: float) -> float:
    return math.sqrt(GERSHGORIN * k / m)


def dt_limit(omega: float, damping_rate: float = 0.0) -> float:
    """Largest stable dt of x' = 2x - x_p - w^2 dt^2 x - beta dt (x - x_p) (Verlet with the
    lagged-velocity drag beta = 12 b / m): the Jury condition w^2 dt^2 + 2 beta dt < 4.
    With beta = 0 this is w dt < 2."""
    if damping_rate == 0.0:
        return 2.0 / omega
    beta = damping_rate
    return (-beta + math.sqrt(beta * beta + 4 * omega * omega)) / (omega * omega)


def damping_rate(scene: Scene) -> float:
    """beta = 12 b / m: an interior particle's drag rate (the damping acts once per spring)."""
    return 12 * scene.damping / scene.mass


def predicted_dt_max(scene: Scene, stretch: float = 1.0) -> float:
    """Flat-lattice (at `stretch`) stability limit of `scene`'s k, m and b."""
    return dt_limit(omega_max(scene.stiffness, scene.mass, stretch), damping_rate(scene))


def gershgorin_dt_max(scene: Scene) -> float:
    return dt_limit(gershgorin_omega(scene.stiffness, scene.mass), damping_rate(scene))


def finite_grid_omega2(n: int, stretch: float = 1.0) -> float:
    """The largest eigenvalue (units of k/m) of the free n x n grid's stiffness matrix at
    `stretch` (dense, so n <= ~30): at most lattice_omega2, approaching it as n grows."""
    dim = 3 * n * n
    K = np.zeros((dim, dim))
    for dr, dc in OFFSETS:
        block = _spring_block(dr, dc, stretch)
        for r in range(n):
            for c in range(n):
                if 0 <= r + dr < n and 0 <= c + dc < n:
                    i, j = 3 * (r * n + c), 3 * ((r + dr) * n + c + dc)
                    K[i : i + 3, i : i + 3] += block
                    K[i : i + 3, j : j + 3] -= block
    return float(np.linalg.eigvalsh(K)[-1])


__all__ = [
    "dynamical_matrix",
    "lattice_omega2",
    "GERSHGORIN",
    "omega_max",
    "gershgorin_omega",
    "dt_limit",
    "damping_rate",
    "predicted_dt_max",
    "gershgorin_dt_max",
    "finite_grid_omega2",
]
