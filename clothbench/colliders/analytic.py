"""The analytic colliders (sphere, capped cylinder, plane), the keys of their scene-file
tables, and the pose of any named body."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from clothbench.colliders.mesh import Mesh
from clothbench.colliders.motion import Motion, pose

# The keys each analytic collider's scene-file table needs, and those any collider may add.
COLLIDER_TABLE_KEYS = {
    "sphere": ("center", "radius"),
    "cylinder": ("start", "end", "radius"),
    "plane": ("point", "normal"),
}
COLLIDER_OPTIONAL_KEYS = ("name", "motion")  # any collider may be named and may move


@dataclass(frozen=True)
class Sphere:
    center: tuple[float, float, float]
    radius: float
    name: str = ""
    motion: Motion | None = None

    kind = "sphere"


@dataclass(frozen=True)
class Cylinder:
    """A capped cylinder around the segment start-end."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    radius: float
    name: str = ""
    motion: Motion | None = None

    kind = "cylinder"

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
class Plane:
    """A one-sided half-space: the solid is where (x - point) . normal < 0."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    name: str = ""
    motion: Motion | None = None

    kind = "plane"

    @property
    def unit_normal(self) -> tuple[float, float, float]:
        norm = math.sqrt(sum(x * x for x in self.normal))
        return tuple(x / norm for x in self.normal)


COLLIDER_KINDS = {"sphere": Sphere, "cylinder": Cylinder, "plane": Plane}
# the point a collider's motion moves and rotates it about (docs/semantics.md, "Moving colliders")
ANCHOR = {"sphere": "center", "cylinder": "start", "plane": "point", "mesh": "position", "frame": "origin"}


def body_pose(body, t: float):
    """(R, T) in float64 of any named body (collider or kinematic frame) at time t."""
    if isinstance(body, Mesh):
        return body.pose_at(t)
    return pose(getattr(body, ANCHOR[body.kind]), np.eye(3), body.motion, t)
