"""docs/normals.md in NumPy: the per-particle normals a kernel computes, for its tests.

Evaluated in the documented order (a x b written out, |v|^2 as (x*x + y*y) + z*z, unit as a
division by sqrt, the faces summed in ring order), so in float32 it is what a strict kernel
must reproduce bit for bit, and in float64 the reference a fast kernel is measured against.
"""

from __future__ import annotations

import numpy as np

# The ring of neighbours of (r, c) as (d_row, d_col): face e is (x, RING[e], RING[e + 1]).
RING = ((-1, 0), (-1, -1), (0, -1), (1, 0), (1, 1), (0, 1))


def _unit(v: np.ndarray) -> np.ndarray:
    """v / |v| per row, or 0 where |v|^2 = 0."""
    l2 = (v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1]) + v[..., 2] * v[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / np.sqrt(l2)[..., None]
    u[l2 == 0] = 0
    return u


def grid_normals(pos: np.ndarray, n: int, dtype=np.float32) -> np.ndarray:
    """The normals of the n x n state `pos` ((n*n, 3 or 4)), in `dtype`: (n*n, 3)."""
    x = pos[:, :3].astype(dtype).reshape(n, n, 3)
    rows, cols = np.mgrid[0:n, 0:n]

    def neighbour(dr, dc):
        r, c = rows + dr, cols + dc
        ok = (r >= 0) & (r < n) & (c >= 0) & (c < n)
        return x[np.clip(r, 0, n - 1), np.clip(c, 0, n - 1)] - x, ok

    total = np.zeros_like(x)
    for e in range(6):
        a, ok_a = neighbour(*RING[e])
        c, ok_c = neighbour(*RING[(e + 1) % 6])
        face = np.stack(
            [
                a[..., 1] * c[..., 2] - a[..., 2] * c[..., 1],
                a[..., 2] * c[..., 0] - a[..., 0] * c[..., 2],
                a[..., 0] * c[..., 1] - a[..., 1] * c[..., 0],
            ],
            axis=-1,
        )
        total = total + np.where((ok_a & ok_c)[..., None], _unit(face), 0)  # a face outside adds 0
    return _unit(total).reshape(n * n, 3)
