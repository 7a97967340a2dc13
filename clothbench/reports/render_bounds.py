"""Collider poses over time and the box around a scene that the camera frames, apart from
reports/render.py because they are plain NumPy (no moderngl) and the viewer uses them too."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from clothbench.scene import Scene, body_pose

HANG = 1.5  # a sheet hanging from a pin reaches this many times its side below it

BOUND_SAMPLES = 9  # times at which a moving body's pose is taken for the camera's box


def _pose_matrix(body, t: float) -> np.ndarray:
    """The 4x4 body-to-world matrix of a collider (or frame) at time t (colliders/motion.py)."""
    rotation, translation = body_pose(body, t)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, translation
    return m


def placement_matrix(body) -> np.ndarray:
    """The body-to-world matrix of the scene file's placement, without its motion."""
    return _pose_matrix(replace(body, motion=None), 0.0)


def motion_matrix(body, t: float) -> np.ndarray:
    """What the body's motion has done to its placement by time t (world to world)."""
    return _pose_matrix(body, t) @ np.linalg.inv(placement_matrix(body))


def _mesh_box(mesh, t: float) -> tuple[np.ndarray, np.ndarray]:
    rotation, translation = mesh.pose_at(t)
    world = mesh.geometry.corners.reshape(-1, 3).astype(np.float64) @ rotation.T + translation
    return world.min(axis=0), world.max(axis=0)


def _box_box(box, t: float) -> tuple[np.ndarray, np.ndarray]:
    """The world-axis box around a box collider's eight corners at time t."""
    rotation, centre = box.pose_at(t)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
    world = (signs * np.array(box.half_extents)) @ rotation.T + centre
    return world.min(axis=0), world.max(axis=0)


def scene_bounds(scene: Scene, duration: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A box around where the cloth goes and the colliders: the sheet, as far down as it is
    long when pinned (hanging, stretched by its weight: HANG), or down to the lowest collider
    when it lands on them, and every sphere, cylinder, box and mesh; not below a floor. Over
    `duration` seconds a moving collider is boxed at several times, and a sheet whose pins
    follow a body is boxed where the body carries it."""
    times = np.linspace(0.0, duration, BOUND_SAMPLES) if duration > 0 else np.zeros(1)
    lo = np.array([0.0, scene.height - HANG * scene.size, 0.0])
    hi = np.array([scene.size, scene.height, scene.size])
    if scene.pin_attach is not None:  # the sheet goes where its pins are carried
        start = _pose_matrix(scene.body(scene.pin_attach), 0.0)[:3, 3]
        shifts = [_pose_matrix(scene.body(scene.pin_attach), t)[:3, 3] - start for t in times]
        lo, hi = lo + np.min(shifts, axis=0), hi + np.max(shifts, axis=0)
    mesh_boxes = [_mesh_box(m, t) for m in scene.meshes for t in (times if m.motion else [0.0])]
    mesh_boxes += [_box_box(b, t) for b in scene.boxes for t in (times if b.motion else [0.0])]
    lowest = [s.center[1] - s.radius for s in scene.spheres]
    lowest += [min(c.start[1], c.end[1]) - c.radius for c in scene.cylinders]
    lowest += [b[0][1] for b in mesh_boxes]
    if not len(scene.pinned()) and lowest:  # it lands on the colliders and drapes over them
        lo[1] = min(max(lo[1], min(lowest)), hi[1])
    for s in scene.spheres:
        lo = np.minimum(lo, np.array(s.center) - s.radius)
        hi = np.maximum(hi, np.array(s.center) + s.radius)
    for c in scene.cylinders:
        for end in (c.start, c.end):
            lo = np.minimum(lo, np.array(end) - c.radius)
            hi = np.maximum(hi, np.array(end) + c.radius)
    for body in [b for b in scene.spheres + scene.cylinders if b.motion is not None]:
        for t in times:  # where its motion takes it: the same shape moved by its pose
            moved = motion_matrix(body, t)
            points = [body.center] if body.kind == "sphere" else [body.start, body.end]
            for point in points:
                centre = (moved @ np.append(point, 1.0))[:3]
                lo = np.minimum(lo, centre - body.radius)
                hi = np.maximum(hi, centre + body.radius)
    for box_lo, box_hi in mesh_boxes:
        lo, hi = np.minimum(lo, box_lo), np.maximum(hi, box_hi)
    for p in scene.planes:  # a floor (normal up) cuts the box off at its height
        nrm = np.array(p.unit_normal)
        if nrm[1] > 0.99:
            lo[1] = max(lo[1], min(p.point[1], hi[1]))
    return lo, hi
