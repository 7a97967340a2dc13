"""Is a state still a simulation? Blow-up detection shared by every command.

A run is declared blown up when a position is NaN or Inf, or when its total energy grows
past what the scene can plausibly hold (harness/energy.py): a stable cloth only converts
energy (gravity to motion to springs) and damping removes it, while an explicit step past
its stability limit gains energy exponentially and crosses the bound within a few dozen
steps. Energy, unlike a speed limit, needs no tuning to the stiffness: a stiff cloth may
move fast legitimately.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.colliders.motion import euler_degrees
from clothbench.model.colliders.self_contact import contact_measure
from clothbench.model.scene import OFFSETS, Scene
from clothbench.model.solver import Solver
from clothbench.harness.energy import PARTICLES_PER_BLOCK, energy_problem


def state_problem(pos: np.ndarray, prev: np.ndarray, scene: Scene, solver: Solver, step: int) -> str | None:
    """None if the state after `step` steps is healthy, else what is wrong with it."""
    xyz = pos[:, :3]
    if not np.isfinite(xyz).all() or not np.isfinite(prev[:, :3]).all():
        bad = int(np.argmax(~np.isfinite(xyz).all(axis=1)))
        return f"particle {bad} is not finite (NaN or Inf)"
    if scene.pin_attach is not None:
        # pins that follow a body do work on the cloth (twist wrings it, pile and carried drag
        # it): its energy is not bounded by its start's, so only a non-finite state is a blow-up
        return None
    return energy_problem(pos, prev, scene, solver, step)


def self_contact(pos: np.ndarray, scene: Scene) -> tuple[int, float] | None:
    """Of a scene with [self_collision]: the pairs of particles that are not neighbours closer
    than the thickness, and their smallest distance (m, capped at the cell); None without it."""
    if scene.self_collision is None:
        return None
    return contact_measure(pos[:, :3], scene.grid, scene.spacing, scene.self_collision, OFFSETS)


def max_penetration(pos: np.ndarray, scene: Scene) -> float:
    """Deepest penetration of a free particle into any collider (m); 0 when none. In blocks
    of particles, as the energy (harness/energy.py, BLOCK_ROWS, says why)."""
    worst = 0.0
    for start in range(0, len(pos), PARTICLES_PER_BLOCK):
        block = pos[start : start + PARTICLES_PER_BLOCK]
        worst = max(worst, _max_penetration(block[block[:, 3] != 0, :3].astype(np.float64), scene))
    return worst


def _max_penetration(xyz: np.ndarray, scene: Scene) -> float:
    worst = 0.0
    if not len(xyz):
        return worst
    for s in scene.spheres:
        depth = s.radius - np.linalg.norm(xyz - np.array(s.center), axis=1)
        worst = max(worst, float(depth.max()))
    for c in scene.cylinders:
        u = np.array(c.axis)
        d = xyz - np.array(c.start)
        t = d @ u
        rho = np.linalg.norm(d - np.outer(t, u), axis=1)
        # inside: the shortest way out is the smallest of side, start cap and end cap
        depth = np.minimum(np.minimum(c.radius - rho, t), c.length - t)
        worst = max(worst, float(depth.max()))
    for b in scene.boxes:
        # at its placement in the file, as every collider here: |coordinate| along each axis
        local = np.abs((xyz - np.array(b.center)) @ euler_degrees(b.rotation))
        # inside: the shortest way out is through the face pair of least penetration
        depth = (np.array(b.half_extents) - local).min(axis=1)
        worst = max(worst, float(depth.max()))
    for p in scene.planes:
        depth = -((xyz - np.array(p.point)) @ np.array(p.unit_normal))
        worst = max(worst, float(depth.max()))
    return worst
