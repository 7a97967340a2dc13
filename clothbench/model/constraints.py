"""The 12-spring stencil as distance constraints, for the Position Based Dynamics solver, and
as a graph of particles in 4 colours, for the Vertex Block Descent solver (vertex_colours).

Each spring of docs/semantics.md is one undirected constraint between particles i and
j = i + (dr, dc), taken once from its first endpoint along one of six directions. The
coloured Gauss-Seidel solver updates both endpoints of a constraint in place, so the
constraints are split into batches in which no particle appears twice: a batch can run in
parallel with no race, by construction.

The colouring: constraints along one direction form chains (a particle has at most one
constraint ahead of it and one behind it in that direction), and alternate links of a
chain never share a particle. So each direction needs two colours, chosen by the parity
of the link's position along its chain, and the 6 directions need 12. That is optimal: an
interior particle has 12 constraints, and the constraints at one particle must all have
different colours, so no colouring of this graph has fewer than 12 (docs/pbd.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from clothbench.model.scene import OFFSET_KIND, OFFSETS

# (dr, dc) of each undirected constraint direction, in batch order, and the kind of
# spring it is (0 structural, 1 shear, 2 bend: the index of its compliance)
DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1), (2, 2), (2, -2))
DIRECTION_KIND = tuple(OFFSET_KIND[OFFSETS.index(d)] for d in DIRECTIONS)


@dataclass(frozen=True)
class Batch:
    """Constraints that share no particle: i[k] -- j[k] with spring kind `kind`."""

    direction: tuple[int, int]
    parity: int
    kind: int
    i: np.ndarray  # first endpoints (int32)
    j: np.ndarray  # second endpoints (int32)


def _chain_position(rows: np.ndarray, cols: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """Position of the link starting at (row, col) along its chain in direction (dr, dc):
    consecutive links of one chain have consecutive positions."""
    if dr == 0:
        return cols // abs(dc)
    return rows // abs(dr)


def coloured_batches(n: int) -> list[Batch]:
    """The 12 independent batches of the n x n grid's constraints, in solve order."""
    rows, cols = np.divmod(np.arange(n * n, dtype=np.int64), n)
    batches = []
    for (dr, dc), kind in zip(DIRECTIONS, DIRECTION_KIND):
        inside = (rows + dr < n) & (cols + dc >= 0) & (cols + dc < n)
        r, c = rows[inside], cols[inside]
        parity = _chain_position(r, c, dr, dc) % 2
        for p in (0, 1):
            sel = parity == p
            i = (r[sel] * n + c[sel]).astype(np.int32)
            j = ((r[sel] + dr) * n + c[sel] + dc).astype(np.int32)
            batches.append(Batch((dr, dc), p, kind, i, j))
    return batches


def constraint_count(n: int) -> int:
    """Undirected constraints: half the springs as the chapter counts them."""
    return sum(len(b.i) for b in coloured_batches(n))


# Vertex Block Descent (docs/vbd.md) updates particles in place, so no two particles of one
# colour may share a spring. colour(row, col) = 2 (row mod 2) + ((col + row div 2) mod 2):
# the structural and shear neighbours (|dr|, |dc| <= 1, not both 0) differ in row parity
# (dr = +-1) or, in the same row, in column parity (dc = +-1); a bend neighbour (+-2, +-2)
# has the same row parity, and col + row div 2 changes by +-2 +- 1, an odd number. So no
# spring joins two particles of one colour. Four is the fewest possible: the four particles
# of a 2x2 cell are joined pairwise (its four sides structural, its two diagonals shear), so
# they need four colours. tests/test_vbd.py checks both for every n from 3 to 40.
VERTEX_COLOURS = 4


def vertex_colours(n: int) -> np.ndarray:
    """The colour (0..3) of each particle of the n x n grid, (n*n,) int32: the sweep order of
    docs/vbd.md."""
    rows, cols = np.divmod(np.arange(n * n, dtype=np.int64), n)
    return (2 * (rows % 2) + (cols + rows // 2) % 2).astype(np.int32)
