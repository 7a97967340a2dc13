"""A sheet folded over onto itself, the state the self-collision tests start from
(tests/test_self_collision.py, tests/contract/test_self_collision_contract.py), and that sheet among
colliders (the OpenCL and CUDA passes' tests)."""

from __future__ import annotations

import numpy as np

from clothbench.model.colliders.analytic import Box, Plane, Sphere
from clothbench.model.colliders.mesh import Mesh
from clothbench.model.colliders.motion import Motion
from clothbench.model.scene import SelfCollision, load_setup

N = 16


def folded(n: int = N, gap: float = 0.5, thickness: float = 0.8, pins=("top-left",)):
    """A sheet folded over onto itself: rows n/2.. lie back over rows ..n/2 - 1, `gap`·h above
    them, so particle (r, c) of the lower half and (n - 1 - r, c) of the upper one are `gap`·h
    apart and not neighbours (r < n/2 - 1). Thickness and gap in units of the spacing h."""
    setup = load_setup("drape")
    scene = setup.scene.replace(grid=n, pin_corners=pins)
    h = scene.spacing
    scene = scene.replace(self_collision=SelfCollision(thickness=thickness * h))
    pos, _ = scene.initial_state(np.float64)
    row = np.arange(n * n) // n
    upper = row >= n // 2
    pos[upper, 2] = (n - 1 - row[upper]) * h
    pos[upper, 1] += gap * h
    rng = np.random.default_rng(34)  # off the lattice: no pair exactly symmetric, every sum's order shows
    pos[:, :3] += 0.05 * h * rng.standard_normal((n * n, 3))
    pos[scene.pinned(), :3] = scene.initial_state(np.float64)[0][scene.pinned(), :3]
    return scene, pos.astype(np.float32)


def crumpled(scene, pos: np.ndarray, width: float = 1.5) -> np.ndarray:
    """`pos` with its free particles crumpled into a ball `width` thicknesses wide: every particle
    has dozens of pairs, more than a kernel sorts on its stack (the C and OpenCL kernels merge
    their cells' runs then)."""
    pos = pos.copy()
    rng = np.random.default_rng(7)
    free = np.ones(scene.particles, dtype=bool)
    free[scene.pinned()] = False
    pos[free, :3] = 0.5 + width * scene.self_collision.thickness * rng.random((int(free.sum()), 3))
    return pos


def on_bodies(folded_sheet):
    """A folded sheet (scene, pos) lying on a rising floor its pin follows, beside a sphere, a
    box and a mesh: the colliders act after the pass (a particle pushed into the floor comes back
    out), at the pose of the step's end (per-step tables), with an attached pin."""
    scene, pos = folded_sheet
    h, y = scene.spacing, float(pos[0, 1])
    floor = Plane(
        point=(0.0, y - 0.2 * h, 0.0), normal=(0.0, 1.0, 0.0), name="floor", motion=Motion(velocity=(0.0, 0.5, 0.0))
    )
    ball = Sphere(center=(0.5, y + 0.5 * h, 0.4), radius=0.1)
    mesh = Mesh(shape="icosphere", subdivisions=1, position=(0.3, y, 0.3), scale=0.08, name="ico")
    box = Box(center=(0.7, y, 0.2), half_extents=(0.06, 0.05, 0.06), rotation=(0.0, 30.0, 0.0))
    scene = scene.replace(planes=(floor,), spheres=(ball,), boxes=(box,), meshes=(mesh,), pin_attach="floor")
    return scene, pos
