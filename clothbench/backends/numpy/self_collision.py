"""The NumPy reference of the self-collision pass (docs/semantics.md, "Self-collision"): a Jacobi
projection over the pairs colliders/self_contact.py finds, each particle's corrections summed
in ascending order of the other particle, in the working precision.

Shared by the Verlet and PBD references; each calls it at its place in the step.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.colliders.self_contact import brute_force_pairs, close_pairs, hashed_pairs, neighbour_table
from clothbench.model.scene import OFFSETS, Scene
from clothbench.model.kernel_inputs import SelfCollisionConstants

SEARCHES = ("hashed", "brute-force")  # the same pairs in the same order: the same bits


class SelfCollisionPass:
    """One pass over (3, n, n) planes, changed in place; `pushed` counts the pairs (from each
    end) that moved a particle, over every pass so far (the tests' proof that it acted)."""

    def __init__(self, scene: Scene, dtype, search: str = SEARCHES[0]):
        if search not in SEARCHES:
            raise ValueError(f"search must be one of {SEARCHES}, got {search!r}")
        self.n, self.search = scene.grid, search
        self.c = SelfCollisionConstants.of(scene, dtype)
        self.table = neighbour_table(OFFSETS)
        self.pushed = 0

    def pairs(self, xyz: np.ndarray):
        """(i, j, d, L2) of the pairs closer than the thickness, not neighbours, by (i, j)."""
        if self.search == "hashed":
            i, j = hashed_pairs(xyz, self.c.inv_cell)
        else:
            i, j = brute_force_pairs(len(xyz))
        return close_pairs(xyz, i, j, self.n, self.c.thickness2, self.table, self.c.exclude2)

    def __call__(self, x: np.ndarray, w: np.ndarray) -> None:
        flat = x.reshape(3, -1)
        wf = w.reshape(-1)
        i, j, d, length2 = self.pairs(flat.T)
        # a pinned particle does not move; a coincident pair has no direction and adds nothing
        act = (wf[i] > 0) & (length2 > 0)
        i, j, d, length2 = i[act], j[act], d[:, act], length2[act]
        self.pushed += len(i)
        if not len(i):
            return
        c = self.c
        length = np.sqrt(length2)
        share = wf[i] / (wf[i] + wf[j])  # the inverse-mass weight: i's part of the shortfall
        s = c.relax * (c.thickness - length)
        s = s * share
        s = s / length
        push = d * s  # (3, P): i's correction from j, along x_i - x_j
        moved, slot = np.unique(i, return_inverse=True)
        rank = np.arange(len(i)) - np.searchsorted(i, i)  # j's place among i's pairs (i is sorted)
        corr = np.zeros((3, len(moved)), dtype=flat.dtype)
        for r in range(int(rank.max()) + 1):  # ascending j: one fixed order of the sum
            sel = rank == r
            corr[:, slot[sel]] += push[:, sel]
        rows, cols = np.divmod(moved, self.n)
        x[:, rows, cols] = x[:, rows, cols] + corr  # x itself, whatever its layout
