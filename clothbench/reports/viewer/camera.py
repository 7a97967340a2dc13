"""The viewer's camera: `clothbench render`'s view of the scene to start with, then a
trackball (a drag turns the scene as if it were a ball under the pointer) and a zoom.

The camera looks at the centre of the scene's bounds from `distance` away; `orientation`
is the world-to-camera rotation, its rows the camera's right, up and back axes.
"""

from __future__ import annotations

import math

import numpy as np

from clothbench.reports.render import FOV_Y, Camera, frame_scene, scene_bounds
from clothbench.scene import Scene

KEY_TURN = math.radians(15)  # an arrow key turns the scene this much
KEY_ZOOM = 0.85  # Z brings the camera this much closer, X takes it as much away
WHEEL_ZOOM = 0.9  # per notch of the wheel


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation by `angle` about the unit vector `axis` (Rodrigues)."""
    x, y, z = axis
    k = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


class Trackball:
    def __init__(self, scene: Scene, size: tuple[int, int]):
        self.scene, self.size = scene, size
        self.home()

    def home(self) -> None:
        """`clothbench render`'s view: above and in front of the scene."""
        lo, hi = scene_bounds(self.scene)
        self.centre = (lo + hi) / 2
        self.radius = float(np.linalg.norm(hi - lo))
        eye = frame_scene(self.scene, self.size).eye
        back = (eye - self.centre) / np.linalg.norm(eye - self.centre)
        right = np.cross((0.0, 1.0, 0.0), back)
        right /= np.linalg.norm(right)
        self.orientation = np.stack([right, np.cross(back, right), back])
        self.distance = float(np.linalg.norm(eye - self.centre))
        self.home_distance = self.distance

    def _on_ball(self, x: float, y: float) -> np.ndarray:
        """Window pixel (x right, y down) on the virtual ball, in camera coordinates."""
        w, h = self.size
        r = min(w, h) / 2
        p = np.array([(x - w / 2) / r, (h / 2 - y) / r, 0.0])
        d2 = p[0] ** 2 + p[1] ** 2
        p[2] = math.sqrt(1 - d2) if d2 <= 0.5 else 0.5 / math.sqrt(d2)  # sphere, then a hyperbola
        return p / np.linalg.norm(p)

    def drag(self, x: float, y: float, dx: float, dy: float) -> None:
        """The pointer moved by (dx, dy) to (x, y) with a button down: the scene turns with it."""
        a, b = self._on_ball(x - dx, y - dy), self._on_ball(x, y)
        axis = np.cross(a, b)
        s = float(np.linalg.norm(axis))
        if s < 1e-9:
            return
        angle = math.atan2(s, float(np.dot(a, b)))
        self.orientation = _rotation(axis / s, angle) @ self.orientation

    def turn(self, pitch: int, yaw: int) -> None:
        """Turn the scene about the world's vertical (yaw: a turntable, the floor stays level)
        and the camera's right axis (pitch), KEY_TURN a step."""
        if yaw:  # the camera orbits the vertical through the centre: its axes turn with it
            self.orientation = self.orientation @ _rotation(np.array([0.0, 1.0, 0.0]), yaw * KEY_TURN).T
        if pitch:
            self.orientation = _rotation(np.array([1.0, 0.0, 0.0]), pitch * KEY_TURN) @ self.orientation

    def zoom(self, factor: float) -> None:
        self.distance = float(np.clip(self.distance * factor, 0.05 * self.home_distance, 20 * self.home_distance))

    def resize(self, size: tuple[int, int]) -> None:
        self.size = size

    def camera(self) -> Camera:
        """The Camera (render.Camera) of the current view."""
        back = self.orientation[2]
        eye = self.centre + back * self.distance
        w, h = self.size
        tan_v = math.tan(math.radians(FOV_Y) / 2)
        tan_h = tan_v * w / h
        near = max(1e-3, self.distance - 2 * self.radius)
        far = self.distance + 6 * self.radius
        view = np.eye(4)
        view[:3, :3] = self.orientation
        view[:3, 3] = -self.orientation @ eye
        projection = np.zeros((4, 4))
        projection[0, 0], projection[1, 1] = 1 / tan_h, 1 / tan_v
        projection[2, 2], projection[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
        projection[3, 2] = -1
        return Camera(eye, projection @ view, (w, h))
