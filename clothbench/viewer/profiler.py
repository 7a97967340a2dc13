"""The viewer's hierarchical profiler: one tree of timed stages per frame.

    frame
      step      upload, build, kernel (its stages, where the backend times them), readback, normals
      shadow    the float64 NumPy run and the error against it, when it is on
      draw      cloth and colliders, overlay, capture (--screenshot/--record)
      present   swapping the window's buffers and taking its events

Each stage is perf_counter around work that ends synchronised (the backend's synchronize(),
glFinish), the timers `run --profile` uses; each shows its share of its parent and of the
frame. A stage may also carry the device's own clock (`device_ms`): OpenCL and CUDA events
(backend.device_elapsed_ms), and GL timer queries where the driver's are a GPU's
(`gl_timer_queries`); a software rasteriser's are not.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field

from clothbench.backends.gl.context import SOFTWARE_RENDERERS


@dataclass
class Stage:
    name: str
    ms: float = 0.0
    device_ms: float | None = None  # the device's own clock for the same work, where it has one
    children: list["Stage"] = field(default_factory=list)

    def child(self, name: str) -> "Stage":
        for c in self.children:
            if c.name == name:
                return c
        self.children.append(Stage(name))
        return self.children[-1]

    def find(self, path: str) -> "Stage | None":
        """The stage at 'step/kernel' below this one, or None."""
        node = self
        for name in path.split("/"):
            node = next((c for c in node.children if c.name == name), None)
            if node is None:
                return None
        return node

    def as_dict(self, frame_ms: float, parent_ms: float | None = None) -> dict:
        """The tree as the event log writes it: ms, share of the parent and of the frame."""
        out = {
            "name": self.name,
            "ms": round(self.ms, 4),
            "of_parent": _share(self.ms, parent_ms if parent_ms is not None else self.ms),
            "of_frame": _share(self.ms, frame_ms),
        }
        if self.device_ms is not None:
            out["device_ms"] = round(self.device_ms, 4)
        if self.children:
            out["children"] = [c.as_dict(frame_ms, self.ms) for c in self.children]
        return out

    def lines(self, frame_ms: float, depth: int = 0, parent_ms: float | None = None) -> list[str]:
        """The tree as the overlay shows it: name, ms, % of parent, % of frame (and device)."""
        of_parent = _share(self.ms, parent_ms if parent_ms is not None else self.ms)
        of_frame = _share(self.ms, frame_ms)
        line = f"{'  ' * depth + self.name:<18}{self.ms:8.2f} ms {100 * of_parent:5.1f}% {100 * of_frame:5.1f}%"
        if self.device_ms is not None:
            line += f"  dev {self.device_ms:.2f}"
        out = [line]
        for c in self.children:
            out += c.lines(frame_ms, depth + 1, self.ms)
        return out


def _share(part: float, whole: float) -> float:
    return round(part / whole, 4) if whole > 0 else 0.0


class FrameProfile:
    """The stages of one frame, nested as they are entered."""

    def __init__(self):
        self.root = Stage("frame")
        self._stack = [self.root]
        self._start = time.perf_counter()

    @contextmanager
    def stage(self, name: str):
        node = self._stack[-1].child(name)
        self._stack.append(node)
        t0 = time.perf_counter()
        try:
            yield node
        finally:
            node.ms += 1e3 * (time.perf_counter() - t0)
            self._stack.pop()

    def add(self, path: str, ms: float) -> Stage:
        """Work timed elsewhere (a backend's profile_stages, a readback), at 'step/kernel/NAME':
        its time goes to that stage and to each stage above it that is not open (an open one
        counts it when it closes)."""
        node, nodes = self.root, []
        for name in path.split("/"):
            node = node.child(name)
            nodes.append(node)
        for n in nodes:
            if not any(n is open_ for open_ in self._stack):
                n.ms += ms
        return node

    def finish(self) -> Stage:
        """Close the frame: its time from the start to now."""
        self.root.ms = 1e3 * (time.perf_counter() - self._start)
        return self.root

    @property
    def step_ms(self) -> float:
        step = self.root.find("step")
        return step.ms if step is not None else 0.0


def gl_timer_queries(device) -> tuple[bool, str]:
    """(whether GL timer queries on `device` measure a GPU, one line saying what they are)."""
    renderer = device.renderer
    if any(s in renderer.lower() for s in SOFTWARE_RENDERERS):
        name = renderer.split()[0]
        return False, (
            f"{name} rasterises on the CPU: its GL timer queries are not a GPU's clock; "
            "GL stages are perf_counter around glFinish"
        )
    return True, f"GL timer queries: {renderer}'s own clock (dev)"


class GLTimer:
    """A GL_TIME_ELAPSED query around some GL work, where the driver's are real; else nothing."""

    def __init__(self, device, real: bool):
        self.device, self.real, self._query = device, real, None

    @contextmanager
    def measure(self, stage: Stage):
        if not self.real:
            yield
            return
        with self.device:
            if self._query is None:
                self._query = self.device.ctx.query(time=True)
            with self._query:
                yield
            stage.device_ms = (stage.device_ms or 0.0) + self._query.elapsed / 1e6

    def release(self) -> None:
        # moderngl 5.13's Query has no release(): the query goes with its last reference
        release = getattr(self._query, "release", None)
        if release is not None:
            with self.device:
                release()
        self._query = None
