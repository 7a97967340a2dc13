"""`clothbench view`: the window, its frame loop, and what a run leaves behind.

The window is moderngl-window's (pyglet on a display; its headless EGL window with
--headless). Its OpenGL context is the one the GL backends compute in (`shared_context`):
`glsl` and `glsl-compute` step in the window's context and the cloth is drawn from their
own textures and buffers, nothing read back; every other backend's state is read back each
frame and uploaded. A frame: the keys pressed since the last one (and those --keys
schedules for it), one frame's steps, the shadow run, the cloth, the overlay, the capture
for --screenshot/--record, the swap; then one line of --log.
"""

from __future__ import annotations

import ctypes
import json
import os
import statistics
import sys
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from clothbench.colliders.kinds import KINDS
from clothbench.backends.gl import context as gl_context
from clothbench.errors import ClothbenchError
from clothbench.reports.render import write_gif
from clothbench.viewer.camera import WHEEL_ZOOM, KEY_ZOOM, Trackball
from clothbench.viewer.draw import Overlay, WindowRenderer, clear_span
from clothbench.viewer.keys import ROTATE_KEYS, ZOOM_KEYS, name_of, window_key_names
from clothbench.viewer.overlay_text import panels
from clothbench.viewer.profiler import FrameProfile, GLTimer, gl_timer_queries
from clothbench.viewer.session import Session
from clothbench.viewer.signals import on_lost_display, raise_if_stopped, stop_between_frames

NO_DISPLAY = (
    "no display to open a window on ({why}): run it under a virtual display with --frames N and "
    "--screenshot FILE.png or --record FILE.gif, e.g. `xvfb-run -a clothbench view --frames 200 "
    "--screenshot view.png`, or add --headless"
)


@dataclass(frozen=True)
class ViewSettings:
    frames: int | None = None  # stop after this many frames; None: when the window closes
    size: tuple[int, int] = (1280, 720)
    steps_per_frame: int = 10
    keys: dict = field(default_factory=dict)  # frame -> key names pressed before it (keys.parse_script)
    screenshot: str | None = None  # the last frame, as a PNG
    record: str | None = None  # every frame, as a GIF
    save: str | None = None  # the final state, as `run --save` writes it
    log: str | None = None  # one JSON line per frame
    headless: bool = False  # moderngl-window's headless window: no display, nothing shown
    fps: float = 25.0  # GIF playback


@dataclass
class ViewReport:
    frames: int = 0
    step: int = 0
    backend: str = ""
    files: list[str] = field(default_factory=list)


def open_window(settings: ViewSettings):
    """A moderngl-window window, or one line saying there is no display."""
    try:
        import moderngl_window
    except ModuleNotFoundError as e:
        raise ClothbenchError(f"{e.name} not installed (pip install moderngl-window)") from None
    if not settings.headless and sys.platform.startswith("linux") and not os.environ.get("DISPLAY"):
        raise ClothbenchError(NO_DISPLAY.format(why="DISPLAY is not set"))
    kind, extra = ("headless", {"backend": "egl"}) if settings.headless else ("pyglet", {})
    try:  # importing pyglet's window already connects to the display
        cls = moderngl_window.get_local_window_cls(kind)
        window = cls(
            title="clothbench view",
            size=settings.size,
            gl_version=(3, 3),
            vsync=False,
            resizable=not settings.headless,
            samples=0,
            **extra,
        )
    except Exception as e:  # a display that cannot be reached, no GL: one line
        why = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}".rstrip(": ")
        if settings.headless:
            raise ClothbenchError(f"no headless EGL window: {why} ({gl_context.INSTALL_HINT})") from None
        raise ClothbenchError(NO_DISPLAY.format(why=why)) from None
    window.exit_key = None  # escape and Q quit through the viewer, which then writes its files
    if window.name == "pyglet" and sys.platform.startswith("linux"):
        on_lost_display()  # an X display: its server may go first (a Ctrl-C under xvfb-run)
    return window


def _proc_address(window):
    """GL entry points by name in the window's context, for what moderngl lacks (GLDevice)."""
    if window.name == "headless":
        lib, lookup = ctypes.CDLL("libEGL.so.1"), "eglGetProcAddress"
    elif sys.platform.startswith("linux"):
        lib, lookup = ctypes.CDLL("libGL.so.1"), "glXGetProcAddressARB"
    else:
        return lambda name: 0  # glsl-compute then says which call it lacks
    fn = getattr(lib, lookup)
    fn.restype, fn.argtypes = ctypes.c_void_p, [ctypes.c_char_p]
    return lambda name: fn(name.encode())


def _writing(path: str, write):
    """write(), with an OSError as one line naming `path`."""
    try:
        return write()
    except OSError as e:
        raise ClothbenchError(f"cannot write {path}: {e.strerror or e}") from None


@contextmanager
def shared_context(window):
    """The window's context as the GL backends' device for as long as the window is open,
    so that they compute where the window draws (gl_context.lend_device)."""
    device = gl_context.GLDevice(window.ctx, "window", _proc_address(window))
    with gl_context.lend_device(device):
        yield device


class Viewer:
    """One window showing one Session, frame by frame."""

    def __init__(self, window, device, session: Session, settings: ViewSettings):
        self.window, self.device, self.session, self.settings = window, device, session, settings
        self.size = tuple(window.buffer_size)
        self.trackball = Trackball(session.scene, self.size)
        self.timer_note = gl_timer_queries(device)[1]
        self.renderer, self._built_for = None, None
        self.overlay = Overlay(device, self.size)
        self.show_profiler = self.show_help = self.wireframe = self.quit = False
        self.frame = 0
        self.step_ms: deque = deque(maxlen=120)  # since the backend or the grid last changed
        self.frame_ms: deque = deque(maxlen=30)
        self.last_tree = None  # the previous frame's profile, what the profiler panel shows
        self.source = ""
        self.images: list[np.ndarray] = []
        self.screenshot: np.ndarray | None = None
        self._keys: list[str] = []  # pressed on the keyboard, for the next frame
        self._resized = False
        self._running, self._warming = (None, None), True  # (backend, grid) the averages are of
        self._log = None
        codes = window_key_names(window.keys)
        window.key_event_func = lambda key, action, mods: (
            self._keys.append(name)
            if action == window.keys.ACTION_PRESS and (name := name_of(codes, key, bool(mods.shift)))
            else None
        )
        window.mouse_drag_event_func = lambda x, y, dx, dy: self.trackball.drag(x, y, dx, dy)
        window.mouse_scroll_event_func = lambda dx, dy: self.trackball.zoom(WHEEL_ZOOM**dy)
        window.resize_func = lambda w, h: setattr(self, "_resized", True)
        window.close_func = lambda: setattr(self, "quit", True)

    # --- keys that change the view, not the simulation ---

    def key(self, name: str, profile: FrameProfile) -> None:
        if self.session.press(name, profile):
            return
        if name == "W":
            self.wireframe = not self.wireframe
        elif name == "P":
            self.show_profiler = self.session.profiling = not self.show_profiler
        elif name == "H":
            self.show_help = not self.show_help
        elif name in ROTATE_KEYS:
            self.trackball.turn(*ROTATE_KEYS[name])
        elif name in ZOOM_KEYS:
            self.trackball.zoom(KEY_ZOOM ** ZOOM_KEYS[name])
        elif name == "O":
            self.trackball.home()
        elif name in ("Q", "escape"):
            self.quit = True
        else:
            self.session.say(f"{name}: no action (H: the keys)")

    # --- a frame ---

    def run(self) -> ViewReport:
        if self.settings.log:
            self._log = _writing(self.settings.log, lambda: open(self.settings.log, "w"))
        try:
            while not self.quit and (self.settings.frames is None or self.frame < self.settings.frames):
                raise_if_stopped()
                if self.window.is_closing:
                    break
                self.run_frame()
        finally:
            if self._log is not None:
                self._log.close()
        return self.finish()

    def run_frame(self) -> None:
        self.frame += 1
        profile = FrameProfile()
        self.session.begin_frame(profile)
        keys = self._keys + self.settings.keys.get(self.frame, [])
        self._keys = []
        for name in keys:
            self.key(name, profile)
        session = self.session
        steps = session.advance_frame(profile)
        if self._resized:
            self._resize()
        if self._built_for != (session.scene_version, self.size):
            self._build_renderer()
        drawable = session.drawable()
        if drawable is None:
            _, prev = session.state()
            normals = session.cloth_normals(prev)
        self.source = "device" if drawable is not None else "readback"
        last = self.settings.frames is not None and self.frame == self.settings.frames
        with profile.stage("draw"):
            with profile.stage("overlay"):  # laid out first: the camera frames the cloth clear of it
                placed = self.overlay.place(panels(self, profile))
            self.trackball.keep_clear_of(*clear_span(placed, self.size[0]))
            self.renderer.camera = self.trackball.camera()
            self.renderer.time = session.drawn_time()
            self.renderer.wireframe = self.wireframe
            with profile.stage("cloth"):
                if drawable is not None:
                    self.renderer.draw_state(drawable)
                else:
                    self.renderer.draw_arrays(prev, normals)
            with profile.stage("overlay"):
                self.overlay.draw(self.window.fbo, placed)
            if self.settings.record or (
                self.settings.screenshot and (last or self.quit or self.settings.frames is None)
            ):
                with profile.stage("capture"):
                    image = self._capture()
                    if self.settings.record:
                        self.images.append(image)
                    self.screenshot = image
        with profile.stage("present"):
            with self.device:  # the headless window's swap is a glFinish: in its own context
                self.window.swap_buffers()  # also takes the window's events: keys for the next frame
        root = profile.finish()
        self._account(root, profile.step_ms, steps)
        self.last_tree = root
        if self._log is not None:
            self._log.write(json.dumps(self.log_line(root, keys, steps)) + "\n")
            self._log.flush()

    def _account(self, root, step_ms: float, steps: int) -> None:
        running = (self.session.backend, self.session.scene.grid)
        if running != self._running:  # the average is of one backend at one grid
            self.step_ms.clear()
            self._running, self._warming = running, True
        if steps and self._warming:
            self._warming = False  # its first frame compiles what the driver compiles lazily
        elif steps:
            self.step_ms.append(step_ms)
        self.frame_ms.append(root.ms)

    @property
    def avg_step_ms(self) -> float | None:
        return statistics.fmean(self.step_ms) if self.step_ms else None

    @property
    def fps(self) -> float | None:
        return 1e3 / statistics.fmean(self.frame_ms) if self.frame_ms else None

    def log_line(self, root, keys: list[str], steps: int) -> dict:
        s = self.session
        line = {
            "frame": self.frame,
            "backend": s.backend_name,
            "mode": s.backend.mode,
            "grid": s.scene.grid,
            "step": s.step,
            "steps": steps,
            "paused": s.paused,
            "ms": round(root.find("step").ms, 4) if root.find("step") else 0.0,
            "avg_ms": round(self.avg_step_ms, 4) if self.avg_step_ms is not None else None,
            "frame_ms": round(root.ms, 4),
            "fps": round(self.fps, 2) if self.fps else None,
            "drawn_from": self.source,
            "colliders": {k.plural: len(getattr(s.scene, k.plural)) for k in KINDS},
            "keys": keys,
            "events": s.take_events(),
            "profiler": root.as_dict(root.ms),
        }
        if s.shadow is not None:
            rms, worst = s.error if s.error is not None else (None, None)
            line["shadow_error"] = {"rms_m": rms, "max_m": worst, "since_step": s.shadow_since}
        return line

    def _capture(self) -> np.ndarray:
        w, h = self.size
        with self.device:
            data = self.window.fbo.read(viewport=(0, 0, w, h), components=3, alignment=1)
        return np.frombuffer(data, dtype=np.uint8).reshape(h, w, 3)[::-1].copy()

    def _resize(self) -> None:
        self._resized = False
        size = tuple(self.window.buffer_size)
        if size != self.size and min(size) > 0:
            self.size = size
            self.trackball.resize(size)
            self.overlay.release()
            self.overlay = Overlay(self.device, size)

    def _build_renderer(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
        self.renderer = WindowRenderer(self.device, self.session.scene, self.size, self.window.fbo)
        self.trackball.scene = self.session.scene
        self._built_for = (self.session.scene_version, self.size)

    def finish(self) -> ViewReport:
        s, out = self.session, self.settings
        report = ViewReport(self.frame, s.step, s.backend_name)
        if out.save:
            pos, prev = s.state()
            _writing(out.save, lambda: np.savez(out.save, pos=pos, prev=prev))
            report.files.append(out.save)
        if out.screenshot and self.screenshot is not None:
            from PIL import Image

            _writing(out.screenshot, lambda: Image.fromarray(self.screenshot).save(out.screenshot))
            report.files.append(out.screenshot)
        if out.record and self.images:
            _writing(out.record, lambda: write_gif(self.images, Path(out.record), out.fps))
            report.files.append(out.record)
        if out.log:
            report.files.append(out.log)
        return report

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
        self.overlay.release()


def view(scene, solver, backend: str, options, settings: ViewSettings, source=None) -> ViewReport:
    """Open the window and run `scene` stepped by `solver` on `backend` in it until it closes
    or `settings.frames` frames are drawn; with `source` (viewer/playback.py), play its frames
    instead. Ctrl-C or SIGTERM stops it between frames."""
    with stop_between_frames():
        return _view(scene, solver, backend, options, settings, source)


def _view(scene, solver, backend: str, options, settings: ViewSettings, source=None) -> ViewReport:
    window = open_window(settings)
    try:
        with shared_context(window) as device:
            timer = GLTimer(device, gl_timer_queries(device)[0])
            session = Session(scene, solver, backend, options, settings.steps_per_frame, timer, source)
            try:
                viewer = Viewer(window, device, session, settings)
                try:
                    return viewer.run()
                finally:
                    viewer.close()
            finally:
                session.close()
                timer.release()
    finally:
        window.close()
        window.destroy()
