"""The analytic colliders (sphere, capped cylinder, oriented box, plane): their geometry and
its checks, and the pose of any named body. Their kinds, with the keys of their scene-file
tables and everything a kernel names them by, are one table: colliders/kinds.py."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from clothbench.model.colliders.mesh import Mesh
from clothbench.model.colliders.motion import Motion, euler_degrees, finite3, pose
from clothbench.model.solver import finite_number
from clothbench.errors import SceneError

COLLIDER_OPTIONAL_KEYS = ("name", "motion")  # any collider may be named and may move


def _positive(value, what: str) -> None:
    if not finite_number(value) or value <= 0:
        raise SceneError(f"{what} must be > 0, got {value!r}")


@dataclass(frozen=True)
class Collider:
    """What every analytic collider has beside its geometry: the COLLIDER_OPTIONAL_KEYS,
    keyword-only (after the geometry in its constructor), and the checks of that geometry."""

    name: str = field(default="", kw_only=True)  # what pins attach to
    motion: Motion | None = field(default=None, kw_only=True)

    kind = "?"
    anchor = "?"  # the point its motion moves and rotates it about

    def check(self) -> None:
        """Every geometry field three finite numbers, or (one declared a float: a radius) a
        number > 0, in the order declared; then the kind's own rule."""
        for f in dataclasses.fields(self):
            if f.name not in COLLIDER_OPTIONAL_KEYS:
                check = _positive if f.type in ("float", float) else finite3
                check(getattr(self, f.name), f"{self.kind} {f.name}")
        self.check_shape()

    def check_shape(self) -> None:
        """The kind's own rule, beside the checks of every field: none."""


@dataclass(frozen=True)
class Sphere(Collider):
    center: tuple[float, float, float]
    radius: float

    kind = "sphere"
    anchor = "center"


@dataclass(frozen=True)
class Cylinder(Collider):
    """A capped cylinder around the segment start-end."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float

    kind = "cylinder"
    anchor = "start"

    def check_shape(self) -> None:
        if self.length == 0:
            raise SceneError(f"cylinder start and end must differ (zero-length cylinder at {self.start})")

    @property
    def length(self) -> float:
        return math.dist(self.start, self.end)

    @property
    def axis(self) -> tuple[float, float, float]:
        """Unit vector from start to end (float64)."""
        length = self.length
        return tuple((e - s) / length for s, e in zip(self.start, self.end))

    @property
    def radial(self) -> tuple[float, float, float]:
        """A fixed unit vector perpendicular to the axis, for a particle exactly on it."""
        u = self.axis
        # cross the axis with the world axis it is least aligned with
        helper = min(
            ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), key=lambda e: abs(sum(a * b for a, b in zip(u, e)))
        )
        c = (
            u[1] * helper[2] - u[2] * helper[1],
            u[2] * helper[0] - u[0] * helper[2],
            u[0] * helper[1] - u[1] * helper[0],
        )
        norm = math.sqrt(sum(x * x for x in c))
        return tuple(x / norm for x in c)


@dataclass(frozen=True)
class Box(Collider):
    """An oriented box: half extents along its own three axes, which are the columns of its
    rotation (Euler degrees, as a mesh's: motion.euler_degrees). docs/semantics.md, "Box"."""

    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    kind = "box"
    anchor = "center"

    def check_shape(self) -> None:
        if not all(h > 0 for h in self.half_extents):
            raise SceneError(f"box half_extents must be > 0, got {self.half_extents!r}")

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) in float64 at time t: column i of R is the world direction of its axis i; a
        fixed box keeps the file's centre exactly, an unrotated one the identity exactly."""
        return pose(self.center, euler_degrees(self.rotation), self.motion, t)


@dataclass(frozen=True)
class Plane(Collider):
    """A one-sided half-space: the solid is where (x - point) . normal < 0."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]

    kind = "plane"
    anchor = "point"

    def check_shape(self) -> None:
        if not any(self.normal):
            raise SceneError("plane normal must not be zero")

    @property
    def unit_normal(self) -> tuple[float, float, float]:
        norm = math.sqrt(sum(x * x for x in self.normal))
        return tuple(x / norm for x in self.normal)


def body_pose(body, t: float):
    """(R, T) in float64 of any named body (collider or kinematic frame) at time t: its motion
    about its anchor (docs/semantics.md, "Moving colliders"), from its own rotation where it
    has one (a mesh, a box)."""
    if isinstance(body, (Mesh, Box)):
        return body.pose_at(t)
    return pose(getattr(body, body.anchor), np.eye(3), body.motion, t)
