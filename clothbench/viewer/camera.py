"""The viewer's camera: `clothbench render`'s view of the scene to start with, then a
trackball (a drag turns the scene as if it were a ball under the pointer) and a zoom.

The camera looks at the centre of the scene's bounds from `distance` away; `orientation`
is the world-to-camera rotation, its rows the camera's right, up and back axes.

The run panel covers the window's top-left corner (the profiler, when open, its top-right),
and `render`'s framing fills the whole window: a cloth corner would sit under the text. So
the picture is framed in the columns between the panels (`keep_clear_of`): moved to their
middle and made smaller only as far as the scene's width at home needs. It is a transform of
the image, the same at every turn and zoom, so the view does not jump as the scene turns.
"""

from __future__ import annotations

import math

import numpy as np

from clothbench.reports.render import FOV_Y, Camera, frame_scene, scene_bounds
from clothbench.model.scene import Scene

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
        self.clear = (0, size[0])  # the pixel columns [left, right) the picture is framed in
        self._panels = (False, False)  # whether a panel was at the left, at the right
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
        self._home_half_width()

    def _home_half_width(self) -> None:
        """Half the width of the scene's bounds at home, in normalised device coordinates: how
        much of the window's width the picture needs (at most about 0.94, render's margin)."""
        lo, hi = scene_bounds(self.scene)
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        p = np.hstack([corners, np.ones((8, 1))]) @ self._view_projection().T
        self.half_width = float(np.max(np.abs(p[:, 0] / p[:, 3])))

    def keep_clear_of(self, left: int, right: int) -> None:
        """Frame the picture in the pixel columns [left, right) (between the top panels,
        draw.clear_span). The span only narrows while the same panels are shown, until a
        resize: a panel that is a number narrower for a frame must not make the picture
        jitter; a panel opened or closed places it again."""
        panels = (left > 0, right < self.size[0])
        if panels != self._panels:
            self.clear, self._panels = (int(left), int(right)), panels
        else:
            self.clear = (max(self.clear[0], int(left)), min(self.clear[1], int(right)))

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
        self.clear, self._panels = (0, size[0]), (False, False)
        self._home_half_width()

    def camera(self) -> Camera:
        """The Camera (render.Camera) of the current view, framed in the columns `clear`."""
        w = self.size[0]
        left, right = self.clear
        if 2 * (right - left) < w:
            # a span under half the window (a narrow window, or both panels wide) keeps the
            # whole-window framing: the cloth shares it with the text rather than live in a strip
            left, right = 0, w
        scale = min(1.0, (right - left) / (w * self.half_width)) if self.half_width > 0 else 1.0
        frame = np.eye(4)  # clip x' = scale x + shift w: the image scaled, then moved
        frame[0, 0] = frame[1, 1] = scale
        frame[0, 3] = (left + right) / w - 1  # NDC 0 to the middle of the span
        back = self.orientation[2]
        eye = self.centre + back * self.distance
        return Camera(eye, frame @ self._view_projection(), self.size)

    def _view_projection(self) -> np.ndarray:
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
        return projection @ view
