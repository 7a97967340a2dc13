"""Is a state still a simulation? Blow-up detection shared by every command.

A run is declared blown up when a position is NaN or Inf, or when a particle moves faster
than RUNAWAY_SPEED plus twice the free-fall speed reached so far: a stable cloth of any
stiffness moves no faster than its fall plus bounded elastic oscillation, while an
explicit integrator past its stability limit grows exponentially and crosses any such
bound within a few dozen steps.
"""

from __future__ import annotations

import math

import numpy as np

from ..scene import Scene

RUNAWAY_SPEED = 100.0  # m/s


def speed_limit(scene: Scene, step: int) -> float:
    g = math.sqrt(sum(c * c for c in scene.gravity))
    return RUNAWAY_SPEED + 2.0 * g * step * scene.dt


def state_problem(pos: np.ndarray, prev: np.ndarray, scene: Scene, step: int) -> str | None:
    """None if the state after `step` steps is healthy, else what is wrong with it."""
    xyz = pos[:, :3]
    if not np.isfinite(xyz).all() or not np.isfinite(prev[:, :3]).all():
        bad = int(np.argmax(~np.isfinite(xyz).all(axis=1)))
        return f"particle {bad} is not finite (NaN or Inf)"
    step_len = np.sqrt(((xyz.astype(np.float64) - prev[:, :3]) ** 2).sum(axis=1))
    speed = float(step_len.max()) / scene.dt
    limit = speed_limit(scene, step)
    if speed > limit:
        return f"a particle moves at {speed:.3g} m/s, past the runaway limit {limit:.3g} m/s"
    return None


def max_penetration(pos: np.ndarray, scene: Scene) -> float:
    """Deepest penetration of a free particle into any collider (m); 0 when none."""
    xyz = pos[pos[:, 3] != 0, :3].astype(np.float64)
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
    for p in scene.planes:
        depth = -((xyz - np.array(p.point)) @ np.array(p.unit_normal))
        worst = max(worst, float(depth.max()))
    return worst
