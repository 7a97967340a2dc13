"""The OpenCL backend: kernels/verlet_cloth.cl through pyopencl (PoCL's CPU device here).

Host code only; the step is in the kernel file and docs/semantics.md. Two pairs of buffers
(positions, previous positions) are ping-ponged by swapping references, as in the chapter's
Figure 22.4: the state stays on the device and is read back only by read().

Transfer modes (options.transfer):
  resident  (default) the state never leaves the device between read() calls.
  per-step  the chapter's OpenCL variant (section 22.8): the host owns the state and uploads
            it at the start of every step; to upload the current state it must also read each
            step's result back, so a step costs one round trip. Done inside advance(), so the
            harness times it.

Strict mode runs kernel `verlet_cloth` (float4, no contraction: bit-exact with the NumPy
float32 reference); fast mode runs `verlet_cloth_interior` + `verlet_cloth_border` on SoA
planes. The kernel file's header says which values are -D build options and which are
arguments, and why.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import ClothbenchError
from ..kernel_source import read_kernel
from ..scene import Scene
from .base import Availability, Backend, BackendOptions

KERNEL_FILE = "verlet_cloth.cl"
TRANSFERS = ("resident", "per-step")
INSTALL_HINT = "pip install pyopencl pocl-binary-distribution"

# A kernel every working OpenCL C compiler builds: the probe's test that a device can compile.
_PROBE_SOURCE = "__kernel void clothbench_probe(__global float *a) { a[get_global_id(0)] = 1.0f; }"

# Module-level caches, so that a sweep building many backends builds each program once.
_contexts: dict = {}  # device int_ptr -> Context
_programs: dict = {}  # (context int_ptr, source, build options) -> built Program


def _cl():
    import pyopencl
    import pyopencl.cltypes  # noqa: F401  (float4 argument dtypes)

    return pyopencl


def probe() -> Availability:
    try:
        _cl()
    except ImportError:
        return Availability(False, f"pyopencl not installed ({INSTALL_HINT})")
    try:
        device = _choose_device(os.environ.get("PYOPENCL_CTX"))
    except ClothbenchError as e:
        return Availability(False, str(e))
    return Availability(True, device=device.name)


def _platforms() -> list:
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # the ICD loader reports "no platform" as PLATFORM_NOT_FOUND_KHR
        platforms = []
    if not platforms:
        raise ClothbenchError(
            f"no OpenCL platform found ({INSTALL_HINT} for PoCL's CPU device, or install a vendor driver)"
        )
    return platforms


def _devices_listing() -> str:
    return ", ".join(
        f"{p}:{d} {dev.name}"
        for p, platform in enumerate(_platforms())
        for d, dev in enumerate(platform.get_devices())
    )


def _choose_device(spec: str | None):
    """The device `spec` names ('platform:device' indices or names, as PYOPENCL_CTX), else
    the first device that can compile a kernel. Listed is not enough: PoCL 3.0's LLVM 14
    lists CPUs it cannot compile for ("unknown target CPU 'generic'")."""
    cl = _cl()
    platforms = _platforms()
    if spec:
        try:
            return cl.choose_devices(interactive=False, answers=spec.split(":"))[0]
        except (cl.Error, RuntimeError, ValueError, IndexError):
            raise ClothbenchError(
                f"no OpenCL device {spec!r} (give 'platform:device', e.g. 0:0; here: {_devices_listing()})"
            ) from None
    failures: dict[str, None] = {}  # ordered and without repeats
    for platform in platforms:
        for device in platform.get_devices():
            try:
                _build(_context(device), _PROBE_SOURCE, ())
                return device
            except ClothbenchError as e:
                failures[f"{device.name}: {_first_error_line(str(e))}"] = None
    hint = "check the OpenCL driver's installation"
    if any("unknown target CPU" in f for f in failures):
        hint = "this PoCL's LLVM predates the CPU: install a newer PoCL (Debian: apt-get install pocl-opencl-icd)"
    raise ClothbenchError(f"no OpenCL device here can compile a kernel ({'; '.join(failures)}): {hint}")


def _first_error_line(message: str) -> str:
    """The compiler's first error, without its 'error: <file>:line:col:' prefix."""
    for line in message.splitlines():
        if line.startswith("error:"):
            return line.split(": ")[-1].strip()
    return message.splitlines()[-1].strip() if message else "?"


def _context(device):
    key = device.int_ptr
    if key not in _contexts:
        _contexts[key] = _cl().Context([device])
    return _contexts[key]


def _build(context, source: str, options: tuple[str, ...]):
    """A built program, from the module cache when this source and options were built before.
    A build error becomes one ClothbenchError carrying the compiler's log."""
    cl = _cl()
    key = (context.int_ptr, source, options)
    if key not in _programs:
        program = cl.Program(context, source)
        try:
            program.build(options=list(options))
        except cl.Error as e:
            device = context.devices[0]
            try:
                log = program.get_build_info(device, cl.program_build_info.LOG).strip()
            except cl.Error:
                log = str(e)
            raise ClothbenchError(
                f"OpenCL build failed on {device.name} (options: {' '.join(options) or 'none'}):\n{log}"
            ) from None
        _programs[key] = program
    return _programs[key]


class OpenCLBackend(Backend):
    name = "opencl"
    has_local_size = True
    sweep_variants = ({"strict": True}, {"strict": False}, {"strict": False, "transfer": "per-step"})

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        cl = self._cl = _cl()
        if options.precision != "f32":
            raise ClothbenchError(f"opencl runs in f32 only (got {options.precision}); f64 is the numpy reference")
        self.transfer = options.transfer or "resident"
        if self.transfer not in TRANSFERS:
            raise ClothbenchError(
                f"opencl transfer must be one of {', '.join(TRANSFERS)}, got {options.transfer!r}"
            )
        if scene.cylinders or scene.planes:
            raise ClothbenchError(
                f"opencl collides with spheres only so far; scene {scene.name!r} has "
                f"{len(scene.cylinders)} cylinder(s) and {len(scene.planes)} plane(s)"
            )
        self.strict = options.strict
        self.local_size = options.local_size
        n = self.n = scene.grid
        self.n2 = n * n

        self._device = _choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        context = _context(self._device)
        self.queue = cl.CommandQueue(
            context, self._device, properties=cl.command_queue_properties.PROFILING_ENABLE
        )
        self._context, self._source = context, read_kernel(KERNEL_FILE)

        # The numbers, rounded once from float64 (docs/semantics.md, Constants), typed below.
        f32, float4 = np.float32, cl.cltypes.make_float4
        rest = scene.rest_lengths()
        self._constants = (
            f32(scene.stiffness),  # k
            f32(scene.damping),  # b
            f32(scene.dt),  # dt
            f32(scene.dt * scene.dt),  # dt2, rounded once
            float4(*scene.gravity, 0.0),  # g
            float4(rest[0], rest[4], rest[8], 0.0),  # rest: structural, shear, bend
        )
        self._constant_dtypes = [np.float32] * 4 + [cl.cltypes.float4] * 2
        spheres = np.array([(*s.center, s.radius) for s in scene.spheres] or [(0, 0, 0, 0)], np.float32)
        mf = cl.mem_flags
        self._spheres = cl.Buffer(context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=spheres)

        # State buffers: float4 per particle (strict) or three SoA planes (fast), twice over.
        state_bytes = self.n2 * 4 * (4 if self.strict else 3)
        self._state = [cl.Buffer(context, mf.READ_WRITE, state_bytes) for _ in range(4)]
        self._host = [np.zeros(state_bytes // 4, np.float32) for _ in range(2)]  # per-step copy
        self._w = np.zeros(self.n2, np.float32)  # inverse mass, as uploaded
        self._w_prev = self._w

        # One step's launches as (kernel, work items, arguments after the constants).
        launches = self._strict_launches() if self.strict else self._fast_launches()
        self.kernels = [k for k, _, _ in launches]
        if self.local_size is not None:
            for k in self.kernels:
                limit = k.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, self._device)
                if self.local_size > limit:
                    raise ClothbenchError(f"local size {self.local_size} exceeds this device's limit {limit}")
        # OpenCL 1.2 wants the global size a multiple of the work-group size: pad, the kernels
        # return early past their last work item.
        ls = self.local_size or 1
        local = None if self.local_size is None else (self.local_size,)
        self._launches = [(k, (-(-items // ls) * ls,), local, extra) for k, items, extra in launches]
        self._events: list = []

    def _program(self, *options: str):
        """The kernel file built for this scene's shape (see its header) plus `options`."""
        shape = (f"-DCLOTH_N={self.n}", f"-DCLOTH_NUM_SPHERES={len(self.scene.spheres)}")
        return _build(self._context, self._source, shape + options)

    def _kernel(self, program, name: str, buffers: int, extra_dtypes=()):
        """A kernel object, created once, with every argument's type declared: a wrongly typed
        argument raises instead of being reinterpreted."""
        k = self._cl.Kernel(program, name)
        k.set_scalar_arg_dtypes([None] * buffers + self._constant_dtypes + list(extra_dtypes))
        return k

    def _strict_launches(self):
        program = self._program("-DCLOTH_STRICT", "-cl-fp32-correctly-rounded-divide-sqrt")
        return [(self._kernel(program, "verlet_cloth", 5), self.n2, ())]

    def _fast_launches(self):
        """The interior (rows and columns 2..n-3) in vectors of V particles, V the device's
        preferred float width, then every other particle through the border kernel."""
        cl, n = self._cl, self.n
        v = max(1, self._device.preferred_vector_width_float)
        vectors_per_row = -(-(n - 4) // v) if n - 4 >= v else 0
        self._inv_mass = cl.Buffer(self._context, cl.mem_flags.READ_ONLY, self.n2 * 4)
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : n - 2] = vectors_per_row > 0
        particles = np.flatnonzero(~covered).astype(np.int32)
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        self._border = cl.Buffer(self._context, flags, hostbuf=particles)
        border = self._kernel(
            self._program("-cl-mad-enable", "-DCLOTH_VECTOR_WIDTH=1"), "verlet_cloth_border", 6, (None, np.int32)
        )
        launches = [(border, particles.size, (self._border, np.int32(particles.size)))]
        if vectors_per_row:
            program = self._program("-cl-mad-enable", f"-DCLOTH_VECTOR_WIDTH={v}")
            interior = self._kernel(program, "verlet_cloth_interior", 6)
            launches.insert(0, (interior, vectors_per_row * (n - 4), ()))
        return launches

    # --- Backend interface -------------------------------------------------------------
    @property
    def device(self) -> str:
        return self._device.name

    @property
    def mode(self) -> str:
        return f"{'strict' if self.strict else 'fast'}/{self.transfer}/ls={self.local_size or 'auto'}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.queue.finish()  # pending per-step copies may still read the host copies
        self._w = np.ascontiguousarray(pos[:, 3], np.float32)
        self._w_prev = np.ascontiguousarray(prev[:, 3], np.float32)
        for host, state in zip(self._host, (pos, prev)):
            host[:] = self._pack(np.asarray(state, np.float32))
        if not self.strict:
            self._cl.enqueue_copy(self.queue, self._inv_mass, self._w)
        for buf, host in zip(self._state[:2], self._host):
            self._cl.enqueue_copy(self.queue, buf, host)
        self.queue.finish()

    def advance(self, steps: int) -> None:
        cl, queue = self._cl, self.queue
        per_step = self.transfer == "per-step"
        self._events = []
        for _ in range(steps):
            pos, prev, pos_out, prev_out = self._state
            if per_step:  # the chapter's variant: the host's state goes up at every step
                cl.enqueue_copy(queue, pos, self._host[0], is_blocking=False)
                cl.enqueue_copy(queue, prev, self._host[1], is_blocking=False)
            inputs = (pos, prev) if self.strict else (pos, prev, self._inv_mass)
            for kernel, global_size, local_size, extra in self._launches:
                args = (*inputs, pos_out, prev_out, self._spheres, *self._constants, *extra)
                self._events.append(kernel(queue, global_size, local_size, *args))
            self._state = [pos_out, prev_out, pos, prev]  # ping-pong: swap references, no copy
            if per_step:  # ... and comes back down, so the host owns the next step's input
                cl.enqueue_copy(queue, self._host[0], pos_out, is_blocking=False)
                cl.enqueue_copy(queue, self._host[1], prev_out, is_blocking=False)
        if steps > 0:
            self._w_prev = self._w  # prev_out carries pos's inverse mass

    def synchronize(self) -> None:
        self.queue.finish()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        out = []
        for buf, w in zip(self._state[:2], (self._w, self._w_prev)):
            flat = np.empty(self._host[0].size, np.float32)
            self._cl.enqueue_copy(self.queue, flat, buf)  # blocking: waits for the steps
            out.append(self._unpack(flat, w))
        return out[0], out[1]

    def device_elapsed_ms(self) -> float | None:
        """Kernel time of the last advance() from profiling events (transfers not included)."""
        if not self._events:
            return None
        self._cl.wait_for_events(self._events)
        return 1e-6 * sum(e.profile.end - e.profile.start for e in self._events)

    def close(self) -> None:
        if getattr(self, "queue", None) is None:
            return
        self.queue.finish()
        self._events = []
        for buf in self._state:
            buf.release()
        self.queue = None

    # --- layouts -----------------------------------------------------------------------
    def _pack(self, state: np.ndarray) -> np.ndarray:
        """(n2, 4) -> the device layout: float4 rows (strict) or x, y, z planes (fast)."""
        return state.reshape(-1) if self.strict else state[:, :3].T.reshape(-1)

    def _unpack(self, flat: np.ndarray, w: np.ndarray) -> np.ndarray:
        if self.strict:
            return flat.reshape(self.n2, 4)
        out = np.empty((self.n2, 4), np.float32)
        out[:, :3] = flat.reshape(3, self.n2).T
        out[:, 3] = w
        return out
