"""Self-collision (docs/semantics.md, "Self-collision"): the scene's [self_collision] table, and
the search for the pairs of particles it acts on, hashed or brute force, in one fixed order.

The pass itself (the response) is each backend's; this module holds what they share: which
pairs count (closer than the thickness, not stencil neighbours) and how they are found (a
uniform grid of cells rebuilt every step, sorted, not hashed with atomics). The brute-force
form is the definition; the hashed form finds the same pairs, in the same order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothbench.errors import SceneError
from clothbench.model.colliders.motion import refuse_unknown_keys
from clothbench.model.solver import FLOAT32_MAX, FLOAT32_TINY, finite_number

TOML_KEYS = ("thickness", "cell", "relaxation")
# The cell key is floor(x * inv_cell) with the cell enlarged by this factor: the float32 distance
# test and the key's own rounding may differ from exact arithmetic by a few ulp, and the margin
# keeps every pair the distance test accepts in adjacent cells (docs/semantics.md).
CELL_MARGIN = 1.0 + 2.0**-8
KEY_LIMIT = 1 << 20  # cell coordinates are clamped to [-KEY_LIMIT, KEY_LIMIT - 1]: clamping only merges cells
STENCIL_REACH = 2  # the stencil's farthest offset per axis (scene.OFFSETS: the bend springs)


@dataclass(frozen=True)
class SelfCollision:
    """[self_collision]: particles closer than `thickness` (m) that are not stencil neighbours
    are pushed apart by a Jacobi projection scaled by `relaxation`; `cell` (m) is the search
    grid's cell (>= thickness; default: the thickness)."""

    thickness: float
    cell: float | None = None
    relaxation: float = 1.0

    def __post_init__(self):
        if not finite_number(self.thickness) or self.thickness <= 0:
            raise SceneError(f"[self_collision] thickness must be a number > 0 (m), got {self.thickness!r}")
        if not FLOAT32_TINY <= self.thickness * self.thickness <= FLOAT32_MAX:
            raise SceneError(
                f"[self_collision] thickness {self.thickness!r} m: its square does not fit float32 "
                f"(from {math.sqrt(FLOAT32_TINY):.3g} to {math.sqrt(FLOAT32_MAX):.3g} m)"
            )
        if self.cell is None:
            object.__setattr__(self, "cell", float(self.thickness))
        if not finite_number(self.cell) or self.cell <= 0:
            raise SceneError(f"[self_collision] cell must be a number > 0 (m), got {self.cell!r}")
        if self.cell < self.thickness:
            raise SceneError(
                f"[self_collision] cell {self.cell!r} m is smaller than the thickness {self.thickness!r} m: "
                "the 27 cells around a particle would miss pairs (use cell >= thickness)"
            )
        if not finite_number(self.relaxation) or not 0 < self.relaxation <= 1:
            raise SceneError(f"[self_collision] relaxation must be in (0, 1], got {self.relaxation!r}")
        object.__setattr__(self, "thickness", float(self.thickness))
        object.__setattr__(self, "cell", float(self.cell))
        object.__setattr__(self, "relaxation", float(self.relaxation))

    @property
    def inv_cell(self) -> float:
        """1 / (cell * CELL_MARGIN), in float64: the key's factor before it is rounded once."""
        return 1.0 / (self.cell * CELL_MARGIN)


def sort_slots(particles: int) -> int:
    """The device passes' sort length (opencl, glsl-compute, cuda: a bitonic sort of (cell,
    index)): the particle count rounded up to a power of two."""
    return 1 << max(0, (particles - 1).bit_length())


def bitonic_stages(slots: int) -> list[tuple[int, int]]:
    """(j, k) of each compare-and-exchange stage of a bitonic sort of `slots` (a power of two)
    entries, in launch order: blocks k = 2, 4, .., slots, each at distances k/2, .., 1 (the
    schedule glsl-compute and cuda launch a stage at a time; opencl runs the short ones in
    local memory)."""
    blocks = [1 << e for e in range(1, slots.bit_length())]
    return [(k >> s, k) for k in blocks for s in range(1, k.bit_length())]


def self_collision_from_toml(table, where: str) -> SelfCollision | None:
    """The [self_collision] table (None when the file has none), every key checked."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise SceneError(f"{where}: [self_collision] must be a table")
    refuse_unknown_keys(table, TOML_KEYS, where, "[self_collision]")
    if "thickness" not in table:
        raise SceneError(f"{where}: [self_collision] needs thickness (m)")
    try:
        return SelfCollision(**table)
    except SceneError as e:
        raise SceneError(f"{where}: {e}") from None


def neighbour_table(offsets) -> np.ndarray:
    """(5, 5) booleans: [dr + 2, dc + 2] is a stencil offset (`offsets`: scene.OFFSETS)."""
    table = np.zeros((2 * STENCIL_REACH + 1,) * 2, dtype=bool)
    for dr, dc in offsets:
        table[dr + STENCIL_REACH, dc + STENCIL_REACH] = True
    return table


def rest_exclusion(thickness: float, spacing: float) -> int:
    """E = ceil((thickness / h)^2), float64 on the host: particles (dr, dc) apart on the grid
    with dr^2 + dc^2 < E lie closer than the thickness in the flat sheet at rest, and are
    excluded like neighbours (below 2h, E <= 4 excludes only stencil neighbours)."""
    return math.ceil((thickness / spacing) ** 2)


def not_neighbours(i: np.ndarray, j: np.ndarray, n: int, table: np.ndarray, exclude2: int) -> np.ndarray:
    """Whether particles i and j of an n x n grid are neither joined by a spring nor closer at
    rest than the thickness (dr^2 + dc^2 < exclude2; i != j assumed)."""
    dr = j // n - i // n
    dc = j % n - i % n
    near = (np.abs(dr) <= STENCIL_REACH) & (np.abs(dc) <= STENCIL_REACH)
    joined = dr * dr + dc * dc < exclude2
    joined[near] |= table[dr[near] + STENCIL_REACH, dc[near] + STENCIL_REACH]
    return ~joined


def brute_force_pairs(count: int) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair (i, j), i != j, ascending i then j: the definition's candidates."""
    i, j = np.divmod(np.arange(count * count, dtype=np.int64), count)
    keep = i != j
    return i[keep], j[keep]


def cell_keys(xyz: np.ndarray, inv_cell) -> np.ndarray:
    """(P, 3) int64 cell coordinates floor(x * inv_cell), in the positions' precision, clamped."""
    k = np.floor(xyz * xyz.dtype.type(inv_cell))
    return np.clip(k, -KEY_LIMIT, KEY_LIMIT - 1).astype(np.int64)


def _cell_id(k: np.ndarray) -> np.ndarray:
    shifted = k + KEY_LIMIT  # 0 .. 2^21 - 1 per axis
    return shifted[:, 0] + (shifted[:, 1] << 21) + (shifted[:, 2] << 42)


def hashed_pairs(xyz: np.ndarray, inv_cell) -> tuple[np.ndarray, np.ndarray]:
    """The ordered pairs (i, j) of particles in the same or adjacent cells, in the cells' order,
    some perhaps twice or with i == j: a superset of the pairs closer than the cell
    (docs/semantics.md); close_pairs puts the survivors in order, once each. xyz (P, 3); a
    particle with a coordinate that is not finite is in no pair."""
    finite = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    keys = cell_keys(xyz[finite], inv_cell)
    ids = _cell_id(keys)
    order = np.argsort(ids, kind="stable")  # particles by cell: a sort, so the same on every run
    sorted_ids = ids[order]
    members = finite[order]
    cells, starts, counts = np.unique(sorted_ids, return_index=True, return_counts=True)
    found_i, found_j = [], []
    for delta in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij")).reshape(3, -1).T:
        target = _cell_id(np.clip(keys + delta, -KEY_LIMIT, KEY_LIMIT - 1))
        at = np.minimum(np.searchsorted(cells, target), len(cells) - 1)
        hit = cells[at] == target
        per = np.where(hit, counts[at], 0)
        i = np.repeat(finite, per)
        first = np.repeat(np.where(hit, starts[at], 0), per)
        offset = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
        found_i.append(i)
        found_j.append(members[first + offset])
    return np.concatenate(found_i), np.concatenate(found_j)


def close_pairs(xyz: np.ndarray, i: np.ndarray, j: np.ndarray, n: int, thickness2, table: np.ndarray, exclude2: int):
    """Of the candidate pairs (i, j), those closer than the thickness that are not neighbours,
    by ascending i then j, each once whatever the search found: (i, j, d = x_i - x_j as (3, P), L2)."""
    i, j = i[i != j], j[i != j]
    d = xyz[i].T - xyz[j].T  # per component
    length2 = (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]
    keep = np.flatnonzero((length2 < thickness2) & not_neighbours(i, j, n, table, exclude2))
    _, once = np.unique(i[keep] * len(xyz) + j[keep], return_index=True)  # sorted by (i, j)
    keep = keep[once]
    return i[keep], j[keep], d[:, keep], length2[keep]


def contact_measure(xyz: np.ndarray, n: int, spacing: float, contact: SelfCollision, offsets) -> tuple[int, float]:
    """The end-of-run measure, in float64: the number of particle pairs (each once) closer than
    the thickness that are not stencil neighbours, and the smallest distance between two such
    particles, capped at the cell size (the search sees no farther)."""
    x = np.asarray(xyz, dtype=np.float64)
    i, j = hashed_pairs(x, 1.0 / (contact.cell * CELL_MARGIN))
    once = i < j
    _, first = np.unique(i[once] * len(x) + j[once], return_index=True)
    i, j = i[once][first], j[once][first]
    table = neighbour_table(offsets)
    apart = not_neighbours(i, j, n, table, rest_exclusion(contact.thickness, spacing))
    d = x[i[apart]] - x[j[apart]]
    dist = np.sqrt(np.einsum("pk,pk->p", d, d))
    close = int(np.count_nonzero(dist < contact.thickness))
    return close, float(min(dist.min(), contact.cell)) if len(dist) else contact.cell
