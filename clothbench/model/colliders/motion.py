"""Rigid motion of a collider or a kinematic frame: docs/semantics.md, "Moving colliders".

A body's pose at time t maps its body frame to the world, x = R(t) x_body + T(t), evaluated on
the host in float64 (and rounded once by kernel_inputs). A motion is an offset from the
placement in the scene file about the body's anchor (a sphere's centre, a cylinder's start, a
plane's point, a mesh's position, a frame's origin): a displacement d(t) and a rotation
R_m(t), so R(t) = R_m(t) R0 and T(t) = anchor + d(t).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothbench.errors import SceneError
from clothbench.model.solver import finite_number

_MOTION_KEYS = {"velocity", "angular_velocity", "keyframes"}
_FRAME_KEYS = {"name", "origin", "motion"}


def euler_degrees(angles) -> np.ndarray:
    """The rotation of `angles` degrees about x, then y, then z (world axes): Rz Ry Rx, float64."""
    rx, ry, rz = (math.radians(a) for a in angles)
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=np.float64)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=np.float64)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=np.float64)
    if not any(angles):
        return np.eye(3)  # exactly the identity: a file without rotation changes no bit
    return Rz @ Ry @ Rx


def axis_angle_degrees(omega, t: float) -> np.ndarray:
    """Rotation by |omega| t degrees about omega's direction (Rodrigues), float64."""
    norm = math.sqrt(sum(w * w for w in omega))
    if norm == 0 or t == 0:
        return np.eye(3)
    k = np.array(omega, dtype=np.float64) / norm
    angle = math.radians(norm * t)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * (K @ K)


@dataclass(frozen=True)
class Motion:
    """A linear velocity (m/s) and an angular velocity (degrees/s about world axes through the
    anchor), or keyframes ((t, displacement, rotation in degrees), ...) interpolated linearly
    and held constant before the first and after the last."""

    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    keyframes: tuple = ()

    def offset(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R_m, d) at time t, float64."""
        if not self.keyframes:
            d = np.array([v * t for v in self.velocity], dtype=np.float64)
            return axis_angle_degrees(self.angular_velocity, t), d
        times = [k[0] for k in self.keyframes]
        if t <= times[0] or len(times) == 1:
            _, d, r = self.keyframes[0]
        elif t >= times[-1]:
            _, d, r = self.keyframes[-1]
        else:
            j = next(i for i in range(1, len(times)) if t < times[i])
            (t0, d0, r0), (t1, d1, r1) = self.keyframes[j - 1], self.keyframes[j]
            f = (t - t0) / (t1 - t0)
            d = tuple(a + (b - a) * f for a, b in zip(d0, d1))
            r = tuple(a + (b - a) * f for a, b in zip(r0, r1))
        return euler_degrees(r), np.array(d, dtype=np.float64)


@dataclass(frozen=True)
class Frame:
    """A kinematic frame: no geometry, only a pose that pins can follow ([[frame]])."""

    name: str
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    motion: Motion | None = None

    kind = "frame"
    anchor = "origin"  # the point its motion moves and rotates it about


def pose(anchor, rotation: np.ndarray, motion: Motion | None, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) of a body placed at `anchor` with rotation `rotation` (3x3) in the file, at time t."""
    anchor = np.array(anchor, dtype=np.float64)
    if motion is None:
        return rotation, anchor
    rm, d = motion.offset(t)
    return rm @ rotation, anchor + d


def finite3(value, what: str) -> tuple[float, float, float]:
    """Three finite numbers as floats, or one line saying what `what` must be."""
    if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(finite_number(v) for v in value):
        raise SceneError(f"{what} must be three finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def motion_from_toml(value, what: str) -> Motion:
    """`motion = { velocity = [...], angular_velocity = [...] }` or `motion = { keyframes =
    [[t, [dx, dy, dz], [rx, ry, rz]], ...] }`, every value checked."""
    if not isinstance(value, dict):
        raise SceneError(f"{what} motion must be a table, e.g. {{ velocity = [0.1, 0, 0] }}")
    refuse_unknown_keys(value, _MOTION_KEYS, f"{what} motion")
    if "keyframes" in value:
        if set(value) & {"velocity", "angular_velocity"}:
            raise SceneError(f"{what} motion: give keyframes or velocities, not both")
        raw = value["keyframes"]
        if not isinstance(raw, list) or not raw:
            raise SceneError(f"{what} motion: keyframes must be a non-empty list of [t, [dx, dy, dz], [rx, ry, rz]]")
        frames = []
        for k in raw:
            if (
                not isinstance(k, list)
                or len(k) != 3
                or not isinstance(k[0], (int, float))
                or isinstance(k[0], bool)
                or not math.isfinite(k[0])
            ):
                raise SceneError(f"{what} motion: each keyframe is [t, [dx, dy, dz], [rx, ry, rz]], got {k!r}")
            frames.append(
                (
                    float(k[0]),
                    finite3(k[1], f"{what} keyframe displacement"),
                    finite3(k[2], f"{what} keyframe rotation"),
                )
            )
        times = [f[0] for f in frames]
        if any(b <= a for a, b in zip(times, times[1:])):
            raise SceneError(f"{what} motion: keyframe times must increase, got {times}")
        return Motion(keyframes=tuple(frames))
    return Motion(
        velocity=finite3(value.get("velocity", [0, 0, 0]), f"{what} motion velocity"),
        angular_velocity=finite3(value.get("angular_velocity", [0, 0, 0]), f"{what} motion angular_velocity"),
    )


def refuse_unknown_keys(table: dict, allowed, where: str, inside: str = "", what: str = "key") -> None:
    """One line naming the first key of `table` (in sorted order) that is not in `allowed`,
    and those allowed: the check every table of a scene file gets. `inside` names the table
    (e.g. "[[mesh]]") where `where` does not."""
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        table_name = f" in {inside}" if inside else ""
        raise SceneError(f"{where}: unknown {what} {unknown[0]!r}{table_name} (allowed: {', '.join(sorted(allowed))})")


def array_of_tables(raw, name: str, plural: str, where: str) -> list[dict]:
    """A scene file's [[name]] entries, refused in one line unless an array of tables: the
    shape every collider, mesh and frame list of a scene file shares."""
    if not isinstance(raw, list):
        raise SceneError(f"{where}: {plural} are written [[{name}]] (an array of tables)")
    for table in raw:
        if not isinstance(table, dict):
            raise SceneError(f"{where}: each [[{name}]] must be a table")
    return raw


def frames_from_toml(raw, where: str) -> tuple[Frame, ...]:
    out = []
    for table in array_of_tables(raw, "frame", "kinematic frames", where):
        refuse_unknown_keys(table, _FRAME_KEYS, where, "[[frame]]")
        if not isinstance(table.get("name"), str) or not table["name"]:
            raise SceneError(f"{where}: [[frame]] needs a name (pins attach to it by name)")
        out.append(
            Frame(
                name=table["name"],
                origin=finite3(table.get("origin", [0, 0, 0]), "frame origin"),
                motion=motion_from_toml(table["motion"], f"frame {table['name']!r}") if "motion" in table else None,
            )
        )
    return tuple(out)
