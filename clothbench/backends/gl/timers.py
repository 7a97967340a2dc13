"""GL timestamps, kept apart from the context code: the query objects GLDevice records them
in (moderngl has only GL_TIME_ELAPSED, so these calls go to GL directly), GLClock around one
advance(), and GLDeviceMixin, which times every GL backend's steps with it (docs/timing.md)."""

from __future__ import annotations

import ctypes
import weakref
from contextlib import contextmanager
from typing import TYPE_CHECKING

from clothbench.backends.gl.driver import GLDriverInfo

if TYPE_CHECKING:
    from clothbench.backends.gl.context import GLDevice

DEVICE_TIMER = "gl-timer-query"  # the row's device_timer where the GL timestamps are a device's
_GL_TIMESTAMP, _GL_QUERY_RESULT, _GL_QUERY_COUNTER_BITS = 0x8E28, 0x8866, 0x8864


class GLTimestamps:
    """GLDevice's timestamp queries (its `_fn`, `_free_queries` and `with self:` are GLDevice's;
    whether they are trusted is GLDevice.timer_queries)."""

    def query_pair(self) -> tuple[int, int]:
        """Two query objects for timestamps: a pair a finished clock gave back, else new ones."""
        if self._free_queries:
            return self._free_queries.pop()
        names = (ctypes.c_uint * 2)()
        with self:
            self._fn("glGenQueries", ctypes.c_int, ctypes.POINTER(ctypes.c_uint))(2, names)
        return names[0], names[1]

    def record_timestamp(self, query: int) -> None:
        """glQueryCounter: the GL time when every command before it has been carried out."""
        self._fn("glQueryCounter", ctypes.c_uint, ctypes.c_uint)(query, _GL_TIMESTAMP)

    def timestamp_ns(self, query: int) -> int:
        """The recorded GL time of `query` in ns, waiting for it (GL_QUERY_RESULT blocks)."""
        value = ctypes.c_uint64(0)
        with self:
            self._fn("glGetQueryObjectui64v", ctypes.c_uint, ctypes.c_uint, ctypes.POINTER(ctypes.c_uint64))(
                query, _GL_QUERY_RESULT, ctypes.byref(value)
            )
        return value.value


class GLClock:
    """Two GL timestamps around the steps of one advance(), read as the device's ms between
    them (docs/timing.md: the shaders, their barriers, and any time the device waited for the
    host to submit the next draw or dispatch).

    Timestamps (glQueryCounter), not a GL_TIME_ELAPSED query: only one GL_TIME_ELAPSED query
    may be active in a context, and the viewer's profiler holds one around advance()
    (reports/viewer/profiler.py). The pair of query objects goes back to the context's pool
    when the clock is collected: backends share the context, and not every one closes its
    clock (the PBD solver's close() is its own)."""

    def __init__(self, device: GLDevice):
        self.device = device
        self.start, self.end = device.query_pair()
        self.recorded = False
        weakref.finalize(self, device._free_queries.append, (self.start, self.end))

    @contextmanager
    def measure(self):
        self.recorded = False  # until both timestamps of this advance() are in
        with self.device:
            self.device.record_timestamp(self.start)
            yield
            self.device.record_timestamp(self.end)
        self.recorded = True

    def elapsed_ms(self) -> float | None:
        """ms between the two timestamps of the last measure(), or None before one."""
        if not self.recorded:
            return None
        return (self.device.timestamp_ns(self.end) - self.device.timestamp_ns(self.start)) / 1e6


class GLDeviceMixin(GLDriverInfo):
    """What every GL backend (glsl, glsl-compute and its PBD solver) does the same way with its
    context `self.gl`: the device is the GL renderer, synchronising is glFinish, and the
    device's own time of the last advance() is two GL timestamps around its steps where the
    driver's clock is a device's (GLDevice.timer_queries; not llvmpipe's, docs/timing.md).
    glsl and glsl-compute wrap their steps in timed_steps(); the PBD solver's steps are
    PbdDeviceBackend.advance, which this class's advance() times."""

    gl: GLDevice
    shader_stage = "compute"  # the kind of shader the step runs in; glsl's is "fragment"
    _gl_clock: GLClock | None = None  # made at the first timed advance()

    @property
    def device(self) -> str:
        return self.gl.renderer

    @property
    def flushes_subnormals(self) -> bool:
        """Whether this driver flushes subnormal floats to zero in the step's shaders, where
        NumPy keeps them: a strict run can then part from NumPy (harness/strict_watch.py)."""
        return self.gl.flushes_subnormals(self.shader_stage)

    def synchronize(self) -> None:
        with self.gl:  # re-entrant: also called inside a backend's own `with self.gl`
            self.gl.ctx.finish()

    @property
    def device_timer(self) -> str:
        """The device clock device_elapsed_ms() reads: GL timestamps, or '' where the driver's
        are not a device's clock (device_timer_note says why)."""
        return DEVICE_TIMER if self.gl.timer_queries()[0] else ""

    @property
    def device_timer_note(self) -> str:
        return self.gl.timer_queries()[1]

    @contextmanager
    def timed_steps(self):
        """Brackets the GL commands of one advance() with timestamps, where they are trusted."""
        if not self.device_timer:
            yield
            return
        if self._gl_clock is None:
            self._gl_clock = GLClock(self.gl)
        with self._gl_clock.measure():
            yield

    def advance(self, steps: int) -> None:
        """The next class's steps (the PBD solver's PbdDeviceBackend.advance), timed."""
        with self.timed_steps():
            super().advance(steps)

    def device_elapsed_ms(self) -> float | None:
        """The device's ms between the GL timestamps around the last advance(), where trusted."""
        if self._gl_clock is None or not self.device_timer:
            return None
        return self._gl_clock.elapsed_ms()
