"""What every GL backend shares: one OpenGL context per provider, its program cache, the
kernel sources with their includes resolved, the scene constants as shader source or
uniforms, the compute dispatch geometry, whether the driver keeps subnormal floats, and the
GL timestamps that time every GL backend's steps (GLClock, GLDeviceMixin; docs/timing.md).

Providers: EGL (headless, glcontext's `egl` backend: Mesa llvmpipe here, a GPU driver
elsewhere) and OSMesa (Debian's libosmesa6; glcontext has no OSMesa backend, so the context
is made with ctypes and handed to moderngl through `init_context(loader=...)`).
`--gl egl` (the default) falls back to OSMesa when EGL fails; `--gl osmesa` uses only OSMesa.

A context lives as long as the process, like a device: backends share it and release
only their own textures and buffers. Every GL call runs inside `with device:`, which makes
the context current, so EGL and OSMesa contexts can coexist in one process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import weakref
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from clothbench.model.colliders.kinds import KINDS
from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.kernel_source import glsl_float, read_kernel, resolve_includes
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver
from clothbench.backends.base import Availability, BackendOptions
from clothbench.model.kernel_inputs import VerletConstants, collider_rows
from clothbench.backends.gl.driver import GLDriverInfo, gl_driver
from clothbench.backends.gl.bodies import (  # noqa: F401  (re-exported, as gl_context.X)
    MESH_CORNERS,
    MESH_NODES,
    MESH_NORMALS,
    MOTION_BLOCK,
    MOTION_ROWS,
    PIN_SLOTS,
    GLBodies,
    MeshBuffers,
    body_defines,
    collider_kinds,
    collider_source,
    mesh_layout,
    motion_offsets,
    motion_rows,
    pin_slots,
    pose_block,
)

INSTALL_HINT = "apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri, or libosmesa6 for --gl osmesa"  # README
MAX_GENERIC_COLLIDERS = 8  # per kind, the uniform arrays of generic (unspecialised) programs
DEFAULT_LOCAL_SIZE = 64  # the smallest not slower on llvmpipe (docs/llvmpipe.md, "The kernel shapes of glsl-compute")
MAX_GROUPS_X = 65535  # GL guarantees this many work groups per dimension, no more

# Renderers that run the shaders on the host CPU: their timer queries are the host's clock, not
# a device's (docs/timing.md), so no GL backend on them reports a device time.
SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "lavapipe", "swiftshader")
DEVICE_TIMER = "gl-timer-query"  # the row's device_timer where the GL timestamps are a device's

# Two float32 products NumPy computes as subnormals: a normal value times a normal value
# (flush-to-zero of a result) and a subnormal value times 2 (denormals-are-zero of an input).
SUBNORMAL_PROBE = (1e-38, 0.01, 1e-40, 2.0)
_PROBE_BODY = "result = vec4(probe.x * probe.y, probe.z * probe.w, 0.0, 0.0);"


class GLUnavailable(ClothbenchError):
    """No context could be made with the provider asked for; the message says why."""


@dataclass(frozen=True)
class DrawableState:
    """Where a GL backend keeps x(t) and its normals (docs/normals.md) on the device, for the
    renderer to draw without a readback: RGBA32F n x n textures (`glsl`) or vec4 buffers
    (`glsl-compute`), moderngl objects of `device`'s context."""

    device: "GLDevice"
    positions: object
    normals: object


class GLDevice:
    """An OpenGL context (the process's one for its provider) and its compiled programs."""

    def __init__(self, ctx, provider: str, get_proc_address, keepalive=None):
        self.ctx = ctx
        self.provider = provider  # "egl" or "osmesa"
        self.renderer = ctx.info["GL_RENDERER"]
        self.version_code = ctx.version_code  # e.g. 450 for OpenGL 4.5
        self.max_texture_buffer_size = ctx.info.get("GL_MAX_TEXTURE_BUFFER_SIZE", 0)
        self._programs: dict = {}
        self._get_proc_address = get_proc_address  # GL entry point by name, for what moderngl lacks
        self._gl: dict = {}
        self._keepalive = keepalive  # the OSMesa handle and its buffer must outlive ctx
        self._depth = 0  # how many `with device:` blocks are open
        self._flushes: dict[str, bool] = {}  # shader stage -> flushes subnormals (probed once)
        self._timestamp_bits: int | None = None  # GL_QUERY_COUNTER_BITS of GL_TIMESTAMP (asked once)
        self._free_queries: list[tuple[int, int]] = []  # query pairs of clocks gone, for the next

    def __enter__(self):
        # Re-entrant: only the outermost `with` makes the context current and releases it, so
        # code already inside `with device:` may call code that enters it again.
        if self._depth == 0:
            self.ctx.__enter__()  # make this context current (EGL, or the OSMesa loader's)
        self._depth += 1
        return self

    def __exit__(self, *exc):
        self._depth -= 1
        if self._depth == 0:
            self.ctx.__exit__(*exc)

    def program(self, key, build):
        """The program for `key`, compiled by `build()` the first time it is asked for."""
        if key not in self._programs:
            self._programs[key] = build()
        return self._programs[key]

    @property
    def programs_compiled(self) -> int:
        return len(self._programs)

    def flushes_subnormals(self, stage: str) -> bool:
        """Whether shaders of `stage` ("fragment" or "compute") flush subnormal float32 values
        to zero on this context, where NumPy keeps them; probed once per stage (llvmpipe
        flushes in fragment shaders and keeps them in compute shaders)."""
        if stage not in self._flushes:
            a, b, c, d = (np.float32(v) for v in SUBNORMAL_PROBE)
            expected = np.array([a * b, c * d, 0, 0], dtype=np.float32)
            with self:
                got = self._probe_compute() if stage == "compute" else self._probe_fragment()
            self._flushes[stage] = not np.array_equal(got, expected)
        return self._flushes[stage]

    def _probe_fragment(self) -> np.ndarray:
        ctx = self.ctx
        vertex = shader_source("verlet_cloth.vert", self.version_code, {})
        fragment = (
            f"#version {self.version_code} core\nuniform vec4 probe;\nout vec4 result;\n"
            f"void main() {{ {_PROBE_BODY} }}\n"
        )
        program = ctx.program(vertex_shader=vertex, fragment_shader=fragment)
        program["probe"].value = SUBNORMAL_PROBE
        target = ctx.texture((1, 1), 4, dtype="f4")
        fbo = ctx.framebuffer(color_attachments=[target])
        vao = ctx.vertex_array(program, [])
        fbo.use()
        ctx.disable(ctx.BLEND)
        vao.render(mode=ctx.TRIANGLES, vertices=3)
        got = np.frombuffer(fbo.read(components=4, dtype="f4"), dtype=np.float32).copy()
        for obj in (vao, fbo, target, program):
            obj.release()
        return got

    def _probe_compute(self) -> np.ndarray:
        source = (
            "#version 430 core\nlayout(local_size_x = 1) in;\nuniform vec4 probe;\n"
            "layout(std430, binding = 0) writeonly buffer Result { vec4 result; };\n"
            f"void main() {{ {_PROBE_BODY} }}\n"
        )
        program = self.ctx.compute_shader(source)
        program["probe"].value = SUBNORMAL_PROBE
        out = self.ctx.buffer(reserve=16)
        out.bind_to_storage_buffer(0)
        program.run(1)
        self.ctx.memory_barrier()
        got = np.frombuffer(out.read(), dtype=np.float32).copy()
        out.release()
        program.release()
        return got

    # --- timer queries: whether this context's GL timestamps are a device's clock ----------

    def timer_queries(self) -> tuple[bool, str]:
        """(whether this context's GL timestamps are a device's clock, and if not, why in one
        line). A software rasteriser's are the host's clock when it processed the command
        (docs/timing.md); a context without a timestamp counter has none."""
        name = self.renderer.split()[0] if self.renderer.strip() else "this renderer"
        if any(s in self.renderer.lower() for s in SOFTWARE_RENDERERS):
            return False, f"{name} runs the shaders on the host CPU: its GL timer queries are no device clock"
        if self._timestamp_bits is None:
            try:
                bits = ctypes.c_int(0)
                with self:
                    self._fn("glGetQueryiv", ctypes.c_uint, ctypes.c_uint, ctypes.POINTER(ctypes.c_int))(
                        _GL_TIMESTAMP, _GL_QUERY_COUNTER_BITS, ctypes.byref(bits)
                    )
                self._timestamp_bits = bits.value
            except ClothbenchError:  # no glGetQueryiv: no timer queries either
                self._timestamp_bits = 0
        if self._timestamp_bits <= 0:
            return False, f"{name} has no GL timestamp counter (GL_QUERY_COUNTER_BITS 0)"
        return True, ""

    # --- timestamps: moderngl has only GL_TIME_ELAPSED, so these calls go to GL directly ---

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

    # --- buffer textures: moderngl has none, so these few calls go to GL directly ---------

    def _fn(self, name: str, *argtypes):
        if name not in self._gl:
            address = self._get_proc_address(name)
            if not address:
                raise ClothbenchError(f"{self.renderer} has no {name}")
            self._gl[name] = ctypes.CFUNCTYPE(None, *argtypes)(address)
        return self._gl[name]

    def buffer_texture(self, buffer) -> int:
        """A GL_RGBA32F buffer texture viewing `buffer` (a moderngl Buffer): no copy."""
        name = ctypes.c_uint(0)
        self._fn("glGenTextures", ctypes.c_int, ctypes.POINTER(ctypes.c_uint))(1, ctypes.byref(name))
        bind = self._fn("glBindTexture", ctypes.c_uint, ctypes.c_uint)
        bind(_GL_TEXTURE_BUFFER, name.value)
        self._fn("glTexBuffer", ctypes.c_uint, ctypes.c_uint, ctypes.c_uint)(
            _GL_TEXTURE_BUFFER, _GL_RGBA32F, buffer.glo
        )
        bind(_GL_TEXTURE_BUFFER, 0)
        return name.value

    def bind_image_read(self, unit: int, texture: int) -> None:
        """Bind a buffer texture to image unit `unit` for imageLoad (imageBuffer, rgba32f)."""
        self._fn(
            "glBindImageTexture",
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.c_int,
            ctypes.c_ubyte,
            ctypes.c_int,
            ctypes.c_uint,
            ctypes.c_uint,
        )(unit, texture, 0, 0, 0, _GL_READ_ONLY, _GL_RGBA32F)

    def delete_textures(self, names: list[int]) -> None:
        if names:
            array = (ctypes.c_uint * len(names))(*names)
            self._fn("glDeleteTextures", ctypes.c_int, ctypes.POINTER(ctypes.c_uint))(len(names), array)


_GL_TEXTURE_BUFFER, _GL_RGBA32F, _GL_READ_ONLY = 0x8C2A, 0x8814, 0x88B8
_GL_TIMESTAMP, _GL_QUERY_RESULT, _GL_QUERY_COUNTER_BITS = 0x8E28, 0x8866, 0x8864


class GLClock:
    """Two GL timestamps around the steps of one advance(), read as the device's ms between
    them (docs/timing.md: the shaders, their barriers, and any time the device waited for the
    host to submit the next draw or dispatch).

    Timestamps (glQueryCounter), not a GL_TIME_ELAPSED query: only one GL_TIME_ELAPSED query
    may be active in a context, and the viewer's profiler holds one around advance()
    (clothbench/viewer/profiler.py). The pair of query objects goes back to the context's pool
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


_devices: dict[str, GLDevice] = {}
_failures: dict[str, str] = {}  # provider -> why it failed (not retried in this process)


def get_device(gl: str = "egl") -> GLDevice:
    """The context for `--gl egl` (EGL, else OSMesa) or `--gl osmesa`; GLUnavailable if none."""
    order = ("egl", "osmesa") if gl == "egl" else ("osmesa",)
    for provider in order:
        device = _provider(provider)
        if device is not None:
            return device
    if gl == "osmesa":
        raise GLUnavailable(f"no OSMesa context: {_failures['osmesa']} ({INSTALL_HINT})")
    raise GLUnavailable(f"no EGL display ({_failures['egl']}) and no OSMesa ({_failures['osmesa']}) ({INSTALL_HINT})")


@contextmanager
def lend_device(device: GLDevice):
    """Within the block, `device` is what get_device() gives for `--gl egl` (the default): a
    context an application made (the viewer's window) lent to the GL backends, so that they
    compute where it draws. The context there was before, if any, comes back after."""
    saved = _devices.get("egl")
    _devices["egl"] = device
    try:
        yield device
    finally:
        if saved is None:
            _devices.pop("egl", None)
        else:
            _devices["egl"] = saved


def probe(min_version: int = 330) -> Availability:
    """Can a GL backend needing OpenGL `min_version` (e.g. 430 for compute) run here?"""
    try:
        import moderngl  # noqa: F401  (a dependency of clothbench's, as glcontext is)
    except ModuleNotFoundError as e:
        return Availability(False, f"{e.name} not installed (pip install moderngl glcontext)")
    try:
        device = get_device("egl")
    except GLUnavailable as e:
        return Availability(False, str(e))
    if device.version_code < min_version:
        offers = f"{device.version_code / 100:.1f}"
        return Availability(False, f"needs OpenGL {min_version / 100:.1f}; {device.renderer} offers {offers}")
    return Availability(True, device=device.renderer, driver=gl_driver(device))


def open_device(backend: str, options: BackendOptions, min_version: int) -> GLDevice:
    """The GL context for `options.gl`, checked for the GL version `backend` needs."""
    try:
        device = get_device(options.gl)
    except GLUnavailable as e:
        raise BackendUnavailable(backend, str(e)) from None
    if device.version_code < min_version:
        need = f"{min_version // 100}.{min_version % 100 // 10}"
        have = f"{device.version_code // 100}.{device.version_code % 100 // 10}"
        raise BackendUnavailable(backend, f"needs OpenGL {need}, {device.renderer} offers {have}")
    return device


def open_compute_device(backend: str, options: BackendOptions) -> tuple[GLDevice, int]:
    """The GL 4.3 context for `options.gl` and the work-group size to use on it:
    options.local_size, else DEFAULT_LOCAL_SIZE, refused past what the driver allows."""
    device = open_device(backend, options, 430)
    local_size = options.local_size or DEFAULT_LOCAL_SIZE
    limit = device.ctx.info["GL_MAX_COMPUTE_WORK_GROUP_INVOCATIONS"]
    if local_size > limit:
        raise ClothbenchError(f"--local-size {local_size} is more than {device.renderer} allows ({limit})")
    return device, local_size


def work_groups(items: int, local_size: int) -> tuple[int, int]:
    """Work groups of `local_size` invocations for `items` items, as (x, y) within the
    per-dimension limit."""
    count = -(-items // local_size)
    x = min(count, MAX_GROUPS_X)
    return x, -(-count // x)


def dispatch(device: GLDevice, launch) -> None:
    """Run one compute launch, (program, work groups, storage-buffer bindings, image bindings,
    uniform values), then a memory barrier: the next dispatch reads what this one wrote."""
    program, groups, ssbos, images, uniforms = launch
    for binding, buf in ssbos:
        buf.bind_to_storage_buffer(binding)
    for unit, view in images:
        device.bind_image_read(unit, view)
    for uniform, value in uniforms:
        uniform.value = value
    program.run(*groups)
    device.ctx.memory_barrier()


def mode_suffix(device: GLDevice, ssbo_reads: bool = False) -> str:
    """What a GL backend's mode says beyond its options: the provider where it is not EGL
    (--gl osmesa, or EGL failed), and the SSBO reads a compute backend fell back to."""
    provider = "" if device.provider == "egl" else f"/{device.provider}"
    return provider + ("/ssbo-reads" if ssbo_reads else "")


def _provider(provider: str) -> GLDevice | None:
    if provider in _devices:
        return _devices[provider]
    if provider in _failures:
        return None
    try:
        device = _create_egl() if provider == "egl" else _create_osmesa()
    except Exception as e:  # any failure to get a context means "not here", with the reason
        _failures[provider] = f"{type(e).__name__}: {e}".strip().rstrip(":")
        return None
    _devices[provider] = device
    return device


def _create_egl() -> GLDevice:
    import moderngl

    ctx = moderngl.create_standalone_context(backend="egl", require=330)
    egl = ctypes.CDLL("libEGL.so.1")  # loaded already by glcontext; its entry-point lookup
    egl.eglGetProcAddress.restype = ctypes.c_void_p
    egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
    return GLDevice(ctx, "egl", lambda name: egl.eglGetProcAddress(name.encode()))


# OSMesa constants (GL/osmesa.h)
_OSMESA_FORMAT, _OSMESA_RGBA = 0x22, 0x1908
_OSMESA_DEPTH_BITS, _OSMESA_PROFILE, _OSMESA_CORE_PROFILE = 0x30, 0x33, 0x34
_OSMESA_MAJOR, _OSMESA_MINOR = 0x36, 0x37
_GL_UNSIGNED_BYTE = 0x1401


def _load_osmesa():
    names = ["libOSMesa.so.8", "libOSMesa.so.6", ctypes.util.find_library("OSMesa")]
    errors = []
    for name in filter(None, names):
        try:
            return ctypes.CDLL(name)
        except OSError as e:
            errors.append(str(e))
    raise OSError("libOSMesa not found" + (f" ({errors[-1]})" if errors else ""))


class _OSMesaLoader:
    """What moderngl's init_context needs from a context: GL entry points and make-current."""

    def __init__(self, lib, handle, buffer):
        self.lib, self.handle, self.buffer = lib, handle, buffer

    def load_opengl_function(self, name: str) -> int:
        return self.lib.OSMesaGetProcAddress(name.encode()) or 0

    def make_current(self) -> None:
        # OSMesa needs a colour buffer to be current; we never draw to it (1x1)
        if not self.lib.OSMesaMakeCurrent(self.handle, self.buffer, _GL_UNSIGNED_BYTE, 1, 1):
            raise RuntimeError("OSMesaMakeCurrent failed")

    def __enter__(self):
        self.make_current()

    def __exit__(self, *exc):
        pass

    def release(self):
        pass


def _create_osmesa() -> GLDevice:
    import moderngl

    lib = _load_osmesa()
    lib.OSMesaCreateContextAttribs.restype = ctypes.c_void_p
    lib.OSMesaCreateContextAttribs.argtypes = [ctypes.POINTER(ctypes.c_int), ctypes.c_void_p]
    lib.OSMesaMakeCurrent.restype = ctypes.c_ubyte
    lib.OSMesaMakeCurrent.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_int, ctypes.c_int]
    lib.OSMesaGetProcAddress.restype = ctypes.c_void_p
    lib.OSMesaGetProcAddress.argtypes = [ctypes.c_char_p]
    # a core-profile 4.5 context: compute shaders need 4.3, and the default OSMesa context is 2.1
    attribs = [
        _OSMESA_FORMAT,
        _OSMESA_RGBA,
        _OSMESA_DEPTH_BITS,
        0,
        _OSMESA_PROFILE,
        _OSMESA_CORE_PROFILE,
        _OSMESA_MAJOR,
        4,
        _OSMESA_MINOR,
        5,
        0,
    ]
    handle = lib.OSMesaCreateContextAttribs((ctypes.c_int * len(attribs))(*attribs), None)
    if not handle:
        raise RuntimeError("OSMesaCreateContextAttribs refused a core 4.5 context")
    loader = _OSMesaLoader(lib, handle, (ctypes.c_ubyte * 4)())
    loader.make_current()
    moderngl.init_context(loader=loader)
    ctx = moderngl.get_context()
    if ctx.version_code < 330:
        raise RuntimeError(f"OSMesa gave OpenGL {ctx.version_code}, need 3.3+")
    return GLDevice(ctx, "osmesa", loader.load_opengl_function, keepalive=loader)


# --- the scene constants ------------------------------------------------------------------


def shader_source(
    filename: str,
    version: int,
    defines: dict[str, object],
    colliders: tuple[str, ...] = (),
    meshes: bool = False,
    moving: bool = False,
    self_collision: bool = False,
) -> str:
    """The kernel file with `#version` and the build switches in front of it, and its includes
    resolved: `#include "file"` is kernels/file, `#include <colliders>` the collider files of
    `colliders`, and the mesh file where `meshes` (collider_source), `#include <self_collision>`
    kernels/self_collision.glsl where `self_collision`, else nothing. GLSL has no #include;
    `#line 1 S` at each file start (and after each include) keeps a compiler message's line
    number the line of that file, with S its number in the list on the source's second line
    (Mesa prints every source as 0)."""
    body, files = resolve_includes(
        filename,
        read_kernel(filename),
        lambda line, number, name: f"#line {line} {number}",
        {
            "colliders": lambda: collider_source(colliders, meshes, moving),
            "self_collision": lambda: '#include "self_collision.glsl"\n' if self_collision else "",
        },
    )
    lines = [f"#version {version} core", f"// sources: {', '.join(f'{i} {f}' for i, f in enumerate(files))}"]
    lines += [f"#define {k} {v}".rstrip() for k, v in defines.items()]
    return "\n".join(lines) + "\n" + body


def kernel_defines(scene: Scene, solver: Solver, options: BackendOptions) -> dict[str, object]:
    """The switches of the Verlet step (kernels/verlet_cloth_step.glsl) and its constants."""
    defines: dict[str, object] = {}
    if options.strict:
        defines["STRICT"] = ""
    if options.normals:
        defines["NORMALS"] = ""
    defines.update(constant_defines(scene, solver, options.generic))
    return defines


def constant_defines(scene: Scene, solver: Solver, generic: bool) -> dict[str, object]:
    """Defines that make the kernel specialised (exact literals) or generic (uniforms).

    Specialised (the default): the grid size, the counts and every constant are baked in,
    each value an exact float32 literal (glsl_float, the bit pattern) of kernel_inputs'
    rounding, and the compiler folds them; only the collider kinds the scene has get a count
    and values (their code is included only for them: collider_kinds). Generic: the kernel
    declares uniforms, which set_constant_uniforms fills with the same float32 values; one
    program serves every scene.
    """
    if generic:
        worst = max(len(getattr(scene, kind.plural)) for kind in KINDS)
        if worst > MAX_GENERIC_COLLIDERS:
            raise ClothbenchError(
                f"--generic takes up to {MAX_GENERIC_COLLIDERS} colliders of each kind, the scene "
                f"has {worst}; run without --generic"
            )
        return {"GENERIC": "", "MAX_COLLIDERS": MAX_GENERIC_COLLIDERS}

    c = VerletConstants.of(scene, solver)
    defines = scene_defines(scene)
    defines.update(
        DT_VALUE=glsl_float(c.dt),
        DT2_VALUE=glsl_float(c.dt2),
        K_VALUE=glsl_float(c.k),
        B_VALUE=glsl_float(c.b),
        G_VALUE="vec3({})".format(", ".join(map(glsl_float, c.g))),
        REST_VALUE="float[3]({})".format(", ".join(map(glsl_float, c.rest))),
    )
    return defines


def scene_defines(scene: Scene) -> dict[str, object]:
    """The grid size and the colliders as exact float32 literals, whatever the solver: only
    the kinds the scene has get SPHERE_COUNT and SPHERES_VALUE, ... (collider_kinds)."""

    def vec4s(rows: np.ndarray) -> str:
        items = ", ".join("vec4({})".format(", ".join(map(glsl_float, row))) for row in rows)
        return f"vec4[{len(rows)}]({items})"

    defines: dict[str, object] = {"N_VALUE": scene.grid}
    table = collider_rows(scene)
    for kind in KINDS:
        rows = table[kind.plural]
        if len(rows):
            defines[kind.count_name("glsl")] = len(rows) // kind.rows
            defines[f"{kind.plural.upper()}_VALUE"] = vec4s(rows)
    return defines


def set_constant_uniforms(program, scene: Scene, solver: Solver) -> None:
    """Fill a generic program's uniforms with the constants of `scene` stepped by `solver`,
    rounded once to float32 (kernel_inputs)."""
    c = VerletConstants.of(scene, solver)
    values = {
        "n": scene.grid,
        "dt": c.dt,
        "dt2": c.dt2,
        "k": c.k,
        "b": c.b,
        "g": c.g,
        "rest": list(c.rest),
        **{kind.count_name("glsl-uniform"): len(getattr(scene, kind.plural)) for kind in KINDS},
    }
    for name, value in values.items():
        if name in program:  # the compiler drops uniforms a program does not use
            program[name].value = value
    for name, rows in collider_rows(scene).items():
        if len(rows) and name in program:
            uniform = program[name]  # the whole declared array is written, zero-padded
            padded = np.zeros((uniform.array_length, 4), dtype=np.float32)
            padded[: len(rows)] = rows
            uniform.write(padded.tobytes())
