"""What the viewer simulates and what its keys change, apart from any window.

One scene on one backend at a time, counted in steps since the cloth last started. Switching
backend keeps the cloth where it is: the state is read from one backend as it stands and
uploaded, unchanged, to the next, so a strict run switched between backends ends with the
bits of an unswitched one (every registry backend is bit-exact in strict mode with NumPy
float32; llvmpipe's fragment shaders, `glsl`, only while no value is subnormal:
docs/semantics.md). A backend that cannot run says why and nothing else changes. A grid
key or a reset starts the cloth again; a collider toggle rebuilds the backend for the new
scene and keeps the cloth where it is.

The shadow run (E) is NumPy in float64 started from the running backend's state, stepped
beside it, with the position error of the running backend against it after every frame.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from clothbench.backends import availability, capabilities, create_backend
from clothbench.backends.base import Backend, BackendOptions
from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.harness.normals import grid_normals
from clothbench.harness.simulate import position_error
from clothbench.scene import Scene, load_scene
from clothbench.solver import Solver
from clothbench.viewer.keys import COLLIDER_KEYS, GRID_KEYS, backend_keys
from clothbench.viewer.profiler import FrameProfile, GLTimer

SHADOW_MAX_GRID = 128  # float64 NumPy keeps up with a frame up to here (docs/view.md, "The shadow run")
KINDS = {"sphere": "spheres", "cylinder": "cylinders", "plane": "planes"}
# Colliders a toggle adds to a scene that has none of that kind: the built-in scenes' own.
DEFAULT_SCENES = {"sphere": "sphere", "cylinder": "cylinder", "plane": "cylinder"}


def has_stages(backend: Backend) -> bool:
    """Whether the backend times the stages of its step itself (profile_stages); a playback
    has none."""
    return getattr(type(backend), "profile_stages", Backend.profile_stages) is not Backend.profile_stages


class Session:
    """The simulation behind a window: scene, solver, backend, step, and the shadow run."""

    def __init__(
        self,
        scene: Scene,
        solver: Solver,
        backend: str,
        options: BackendOptions,
        steps_per_frame: int = 10,
        gl_timer: GLTimer | None = None,
        source=None,
    ):
        """`source`: frames to play back (viewer/playback.py) in place of the backend `backend`."""
        if steps_per_frame < 1:
            raise ClothbenchError(f"--steps-per-frame must be >= 1, got {steps_per_frame}")
        self.base = scene  # the scene as loaded: what a collider toggle restores
        self.scene, self.solver, self.steps_per_frame = scene, solver, steps_per_frame
        self.options = dataclasses.replace(options, normals=True)  # dropped where a backend has none
        self.gl_timer = gl_timer
        self.step = 0  # steps since the cloth last started (a reset, a grid key)
        self.paused = False
        self._pending = 0  # steps N asked for while paused
        self.shadow: Backend | None = None
        self.shadow_since = 0
        self.error: tuple[float, float] | None = None  # (RMS, max) m against the shadow
        self.profiling = False  # the profiler is open: backends time their stages
        self.scene_version = 0  # changes whenever the scene (grid, colliders) does
        self.events: list[str] = []  # what happened this frame, for the log and the overlay
        self.message = ""  # the last thing that happened, until something else does
        self._cache = None  # (backend, step, state): one readback per frame at most
        self._profile = FrameProfile()
        self.playback = source is not None
        if source is not None:
            self.backend_name, self.backend = source.name, source
            return
        avail = availability(backend)
        if not avail.usable:
            raise BackendUnavailable(backend, avail.reason)
        self.backend_name = backend
        self.backend = self._build(backend, scene)
        self.backend.upload(*self.backend.initial_state())

    # --- keys ---------------------------------------------------------------------------

    def press(self, key: str, profile: FrameProfile) -> bool:
        """Apply a simulation key; False if the key is not one (the window's keys)."""
        self._profile = profile
        if self.playback and key in (*backend_keys(), *GRID_KEYS, *COLLIDER_KEYS, "E"):
            self.say(f"{key}: a playback's frames are the file's (R, space and N play them)")
        elif key in (keys := backend_keys()):
            self.switch_backend(keys[key], key)
        elif key in GRID_KEYS:
            self.set_grid(GRID_KEYS[key])
        elif key in COLLIDER_KEYS:
            self.toggle_collider(COLLIDER_KEYS[key])
        elif key == "R":
            self.reset()
        elif key == "space":
            self.paused = not self.paused
            self.say("paused" if self.paused else "running", f"at step {self.step}")
        elif key == "N":
            if self.paused:
                self._pending += self.steps_per_frame
            else:
                self.say("N steps one frame while paused (space pauses)")
        elif key == "E":
            self.toggle_shadow()
        else:
            return False
        return True

    def switch_backend(self, name: str, key: str = "") -> None:
        """Move the cloth as it stands to backend `name`; if it cannot run, say why and keep
        the one running."""
        label = f"{key} {name}".strip()
        if name == self.backend_name:
            return self.say(f"{label}: already running")
        avail = availability(name)
        if not avail.usable:
            return self.say(f"{label}: unavailable: {avail.reason}")
        pos, prev = self.state()
        try:
            backend = self._build(name, self.scene)
        except Exception as e:  # any failure to start leaves the running backend as it was
            return self.say(f"{label}: cannot run: {_one_line(e)}")
        with self._profile.stage("step"), self._profile.stage("upload"):
            backend.upload(pos, prev)
        old = self.backend_name
        self.backend.close()
        self.backend, self.backend_name, self._cache = backend, name, None
        self.say(f"switched {old} -> {name} at step {self.step}", f"({backend.mode} on {backend.device})")

    def set_grid(self, n: int) -> None:
        """Restart the cloth at n x n on the running backend."""
        if n == self.scene.grid:
            return self.say(f"already {n}x{n}")
        try:
            scene = self.scene.replace(grid=n)
        except ClothbenchError as e:
            return self.say(f"grid {n}: {e}")
        shadowed = self.shadow is not None
        if self._rebuild(scene, keep_state=False, what=f"grid {n}x{n}"):
            self.say(f"grid {n}x{n}: the cloth starts again")
            if shadowed and self.shadow is None:  # _rebuild restarts it only where it keeps up
                self.say(f"shadow off: float64 NumPy keeps up only to {SHADOW_MAX_GRID}x{SHADOW_MAX_GRID}")

    def toggle_collider(self, kind: str) -> None:
        """Remove the scene's colliders of `kind`, or bring them back (a default one where the
        scene has none); the cloth stays where it is."""
        field, now = KINDS[kind], getattr(self.scene, KINDS[kind])
        if now:
            scene, verb = self.scene.replace(**{field: ()}), "off"
        else:
            have = getattr(self.base, field) or _default_colliders(kind, self.base)
            scene, verb = self.scene.replace(**{field: have}), "on"
        if self._rebuild(scene, keep_state=True, what=f"{field} {verb}"):
            self.say(f"{field} {verb} at step {self.step}")

    def reset(self) -> None:
        self.backend.upload(*self.backend.initial_state())
        self.step, self._cache = 0, None
        self._restart_shadow()
        self.say("reset: the cloth starts again")

    def toggle_shadow(self) -> None:
        if self.shadow is not None:
            return self._stop_shadow("shadow off")
        n = self.scene.grid
        if n > SHADOW_MAX_GRID:
            limit = f"{SHADOW_MAX_GRID}x{SHADOW_MAX_GRID}"
            return self.say(f"shadow: float64 NumPy keeps up only to {limit}, this is {n}x{n} (keys 1-3)")
        self._start_shadow()
        self.say(f"shadow on: float64 NumPy from step {self.step}")

    # --- a frame --------------------------------------------------------------------------

    def begin_frame(self, profile: FrameProfile) -> None:
        """Time this frame's work into `profile`, whose step has the same stages every frame."""
        self._profile = profile
        for name in ("upload", "kernel", "readback", "normals"):
            profile.root.child("step").child(name)

    def advance_frame(self, profile: FrameProfile) -> int:
        """Step one frame (unless paused); the steps taken."""
        self._profile = profile
        steps = self._pending if self.paused else self.steps_per_frame
        self._pending = 0
        with profile.stage("step"):
            if steps:
                with profile.stage("kernel") as node:
                    self._run(steps, profile, node)
        self.step += steps
        if steps:
            self._cache = None
            if self.shadow is not None:
                self._step_shadow(steps, profile)
        return steps

    def _run(self, steps: int, profile: FrameProfile, node) -> None:
        b = self.backend
        if self.profiling and has_stages(b):
            for stage, ms in b.profile_stages(steps).items():
                profile.add(f"step/kernel/{stage}", ms * steps)
            return
        timer = self.gl_timer
        if timer is not None and getattr(b, "gl", None) is timer.device:  # a GL backend in the window's context
            with timer.measure(node):
                b.advance(steps)
                b.synchronize()
        else:
            b.advance(steps)
            b.synchronize()
            device_ms = b.device_elapsed_ms()
            if device_ms is not None:
                node.device_ms = device_ms

    def _step_shadow(self, steps: int, profile: FrameProfile) -> None:
        # a readback the drawing needs anyway is the step's; one only for the shadow is its own
        from_device = self.drawable() is not None
        pos, _ = (None, None) if from_device else self.state()
        with profile.stage("shadow"):
            if from_device:
                pos, _ = self.state(path="shadow/readback")
            with profile.stage("f64 step"):
                self.shadow.advance(steps)
                ref, _ = self.shadow.read()
            with profile.stage("compare"):
                self.error = position_error(pos, ref)

    def state(self, path: str = "step/readback") -> tuple[np.ndarray, np.ndarray]:
        """The running backend's (pos, prev) now, read back at most once per step."""
        if self._cache is None or self._cache[0] is not self.backend or self._cache[1] != self.step:
            t0 = time.perf_counter()
            state = self.backend.read()
            self._profile.add(path, 1e3 * (time.perf_counter() - t0))
            self._cache = (self.backend, self.step, state)
        return self._cache[2]

    def cloth_normals(self, prev: np.ndarray) -> np.ndarray:
        """The normals of x(t) for drawing from a readback: the backend's, else the host's."""
        with self._profile.stage("step"), self._profile.stage("normals"):
            normals = self.backend.read_normals()
            return normals if normals is not None else grid_normals(prev, self.scene.grid, np.float32)

    def drawn_time(self) -> float:
        """Seconds simulated at the state drawn, where the colliders are drawn: x(t), the
        state the last step read (render.py's frame), or the playback's frame."""
        if self.playback:
            return self.backend.time
        return max(self.step - 1, 0) * self.solver.dt

    def drawable(self):
        """The backend's device state to draw from (the window's context), or None: a readback."""
        b = self.backend
        if getattr(b, "drawable_state", None) is None or not getattr(b, "has_normals", False):
            return None
        return b.drawable_state()

    def close(self) -> None:
        self._stop_shadow(None)
        self.backend.close()

    # --- helpers --------------------------------------------------------------------------

    def _build(self, name: str, scene: Scene) -> Backend:
        with self._profile.stage("build"):  # compiling kernels: not the step's time
            options = capabilities(name, self.solver.name).adapt(self.options)
            return create_backend(name, scene, self.solver, options)

    def _rebuild(self, scene: Scene, keep_state: bool, what: str) -> bool:
        """The running backend again for `scene`, from the cloth as it is or its start."""
        state = self.state() if keep_state else None
        try:
            backend = self._build(self.backend_name, scene)
        except Exception as e:
            self.say(f"{what}: cannot run: {_one_line(e)}")
            return False
        self.backend.close()
        self.backend, self.scene, self._cache = backend, scene, None
        self.scene_version += 1
        with self._profile.stage("step"), self._profile.stage("upload"):
            backend.upload(*(state if keep_state else backend.initial_state()))
        if not keep_state:
            self.step = 0
        self._restart_shadow()
        return True

    def _start_shadow(self) -> None:
        pos, prev = self.state()
        self.shadow = create_backend("numpy", self.scene, self.solver, BackendOptions(precision="f64"))
        self.shadow.upload(pos.astype(np.float64), prev.astype(np.float64))
        self.shadow_since, self.error = self.step, None

    def _restart_shadow(self) -> None:
        if self.shadow is not None:
            self.shadow.close()
            self.shadow = None
            if self.scene.grid <= SHADOW_MAX_GRID:
                self._start_shadow()

    def _stop_shadow(self, why: str | None) -> None:
        if self.shadow is not None:
            self.shadow.close()
        self.shadow, self.error = None, None
        if why:
            self.say(why)

    def say(self, text: str, detail: str = "") -> None:
        line = f"{text} {detail}".strip()
        self.events.append(line)
        self.message = line

    def take_events(self) -> list[str]:
        events, self.events = self.events, []
        return events


def _one_line(e: Exception) -> str:
    text = str(e).strip().splitlines()
    first = text[0] if text else ""
    return first if isinstance(e, ClothbenchError) else f"{type(e).__name__}: {first}"


def _default_colliders(kind: str, scene: Scene) -> tuple:
    """The built-in scene's colliders of `kind`, scaled to this scene's sheet."""
    field = KINDS[kind]
    found = getattr(load_scene(DEFAULT_SCENES[kind]), field)
    s = scene.size
    if kind == "plane":
        return found
    scaled = []
    for c in found:
        changes = {k: tuple(v * s for v in getattr(c, k)) for k in ("center", "start", "end") if hasattr(c, k)}
        scaled.append(dataclasses.replace(c, radius=c.radius * s, **changes))
    return tuple(scaled)
