"""The meshes the renderer draws: the cloth's triangles over its particle grid, unit
spheres, capped cylinders and cubes scaled into place for the colliders, and the triangles of
a mesh collider as the step sees them, in its body frame."""

from __future__ import annotations

import math

import numpy as np


def cloth_indices(n: int) -> np.ndarray:
    """Triangles of the n x n grid as particle indices, two per quad split along its
    (r, c)-(r+1, c+1) diagonal, wound counter-clockwise seen from the side the normals of
    docs/normals.md point to (so the front face is that side)."""
    r, c = np.divmod(np.arange((n - 1) * (n - 1)), n - 1)
    i = r * n + c
    lower = np.stack([i, i + n, i + n + 1], axis=1)  # (r,c), (r+1,c), (r+1,c+1)
    upper = np.stack([i, i + n + 1, i + 1], axis=1)  # (r,c), (r+1,c+1), (r,c+1)
    return np.concatenate([lower, upper]).astype(np.uint32)


def sphere_mesh(segments: int = 48, rings: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit sphere: (vertices as (x, y, z, nx, ny, nz), triangle indices)."""
    theta = np.linspace(0, math.pi, rings + 1)[:, None]
    phi = np.linspace(0, 2 * math.pi, segments + 1)[None, :]
    p = np.stack(
        [np.sin(theta) * np.cos(phi), np.cos(theta) * np.ones_like(phi), np.sin(theta) * np.sin(phi)], axis=-1
    ).reshape(-1, 3)
    return np.hstack([p, p]).astype(np.float32), grid_triangles(rings, segments)


def cylinder_mesh(segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A capped cylinder of radius 1 around the z axis from z = 0 to z = 1."""
    a = np.linspace(0, 2 * math.pi, segments + 1)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    side = [np.hstack([ring + (0, 0, z), ring]) for z in (0.0, 1.0)]
    vertices = [np.vstack(side)]
    indices = [grid_triangles(1, segments)]
    for z, nz in ((0.0, -1.0), (1.0, 1.0)):  # the caps: a centre and a ring each
        base = sum(len(v) for v in vertices)
        cap = np.vstack([[0.0, 0.0, z], ring + (0, 0, z)])
        vertices.append(np.hstack([cap, np.tile([0.0, 0.0, nz], (len(cap), 1))]))
        k = np.arange(1, segments + 1)
        indices.append(base + np.stack([np.zeros_like(k), k, k + 1], axis=1))
    return np.vstack(vertices).astype(np.float32), np.vstack(indices).astype(np.uint32)


def cube_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The cube -1..1 on each axis, flat-shaded: (vertices as (x, y, z, nx, ny, nz), indices)."""
    vertices, indices = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            nrm = np.zeros(3)
            nrm[axis] = sign
            u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            if sign < 0:
                u, v = v, u  # counter-clockwise seen from outside
            base = len(vertices)
            vertices += [np.hstack([nrm + a * u + b * v, nrm]) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            indices += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return np.array(vertices, np.float32), np.array(indices, np.uint32)


def triangle_mesh(corners: np.ndarray, shrink: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A mesh collider's (T, 3, 3) body-frame triangles, flat-shaded (each corner with its
    face's normal), scaled by `shrink` about the centre of their box: (vertices as (x, y, z,
    nx, ny, nz), triangle indices)."""
    p = corners.astype(np.float64).reshape(-1, 3, 3)
    centre = (p.reshape(-1, 3).min(axis=0) + p.reshape(-1, 3).max(axis=0)) / 2
    p = centre + shrink * (p - centre)
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face /= np.maximum(np.linalg.norm(face, axis=1, keepdims=True), 1e-30)
    normals = np.repeat(face, 3, axis=0)
    vertices = np.hstack([p.reshape(-1, 3), normals]).astype(np.float32)
    return vertices, np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3)


def grid_triangles(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a (rows + 1) x (cols + 1) vertex grid."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    i = r * (cols + 1) + c
    j = i + cols + 1
    return np.concatenate([np.stack([i, j, i + 1], 1), np.stack([i + 1, j, j + 1], 1)]).astype(np.uint32)


def perpendicular(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit vector u to an orthonormal basis."""
    helper = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)
