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

Which kernel runs (kernels/verlet_cloth.cl, whose header says what is a -D option and what
an argument):
  default    `verlet_cloth_interior` + `verlet_cloth_border`, built for the scene: SoA planes,
             V particles per work item (the device's preferred float width, 16 here), the
             grid side and the collider counts as -D constants, the code of a collider kind
             only when the scene has one. Programs are cached by their build options
             (`key`), so backends of the same shape (a dt or stiffness sweep too) build
             nothing. `--strict` runs them with the documented operation order and
             FP_CONTRACT OFF: bit-exact with the NumPy float32 reference.
  --generic  `verlet_cloth`, the float4 kernel that reads beside Listing 22.1: one program
             for every scene, grid side, constants and collider counts all arguments.
             Bit-exact too in strict mode; the tests hold the two builds to each other.
Normals (docs/normals.md, options.normals): both builds compute them with -DCLOTH_NORMALS,
in the documented order (bit-exact with clothbench.harness.normals in strict mode), for the
state the step read: read_normals() belongs to read()[1]. Without the option the kernels
neither compute them nor take their buffer.

Measured at n = 256 in one process (2 shared cores at load 3.5-5.7; 21 interleaved rounds
of 40 steps; ms/step wall, median with the fastest round in brackets; by a throwaway script
that built every variant side by side, the literal one by patching the source):
                             strict        fast          strict per-step  strict normals
  sphere     specialised     0.66 (0.32)   0.57 (0.27)   0.90 (0.43)      0.96 (0.48)
             generic         5.12 (2.51)   5.24 (2.69)   5.49 (2.65)      7.90 (3.39)
  all kinds  specialised     1.50 (0.79)   1.40 (0.76)   1.70 (0.84)      1.91 (0.91)
  (5 colliders) generic      6.75 (2.76)   7.39 (3.20)   6.96 (3.18)     10.98 (5.88)
Ratios within a round (medians): generic/specialised 7.9x strict and 9.4x fast for the
sphere, 4.1x and 4.5x with all kinds; strict/fast 1.21x specialised, 1.0x generic (PoCL
vectorises neither float4 build); per-step/resident 1.0-1.4x; normals 1.2-1.6x. Where the
specialisation gain comes from: baking the grid side and collider counts into the float4
kernel gained 1-5%, and every number as an exact hex literal (-D, c_float) instead of an
argument nothing measurable in the specialised kernels (0.94-1.03x); the rest is the
vectorised SoA shape. So the numbers stay arguments: one program serves every scene of a
shape.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import ClothbenchError
from ..kernel_source import read_kernel, resolve_includes
from ..scene import Scene
from .base import Availability, Backend, BackendOptions
from .kernel_inputs import VerletConstants, collider_rows

KERNEL_FILE = "verlet_cloth.cl"
TRANSFERS = ("resident", "per-step")
INSTALL_HINT = "pip install pyopencl pocl-binary-distribution"

# A kernel every working OpenCL C compiler builds: the probe's test that a device can compile.
_PROBE_SOURCE = "__kernel void clothbench_probe(__global float *a) { a[get_global_id(0)] = 1.0f; }"

# Module-level caches, so that a sweep building many backends builds each program once.
_contexts: dict = {}  # device int_ptr -> Context
_programs: dict = {}  # (context int_ptr, source, build options) -> built Program


def import_pyopencl():
    import pyopencl
    import pyopencl.cltypes  # noqa: F401  (float4 argument dtypes)

    return pyopencl


def probe() -> Availability:
    try:
        import_pyopencl()
    except ImportError:
        return Availability(False, f"pyopencl not installed ({INSTALL_HINT})")
    try:
        device = choose_device(os.environ.get("PYOPENCL_CTX"))
    except ClothbenchError as e:
        return Availability(False, str(e))
    return Availability(True, device=device.name)


def _platforms() -> list:
    cl = import_pyopencl()
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


def choose_device(spec: str | None):
    """The device `spec` names ('platform:device' indices or names, as PYOPENCL_CTX), else
    the first device that can compile a kernel. Listed is not enough: PoCL 3.0's LLVM 14
    lists CPUs it cannot compile for ("unknown target CPU 'generic'")."""
    cl = import_pyopencl()
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
                build_program(device_context(device), _PROBE_SOURCE, ())
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


def device_context(device):
    """The process's one context for `device`, shared by every backend on it."""
    key = device.int_ptr
    if key not in _contexts:
        _contexts[key] = import_pyopencl().Context([device])
    return _contexts[key]


def program_source(filename: str) -> str:
    """kernels/`filename` with its includes resolved (collide.cl) and `#line` directives
    naming each file, so that a build log points into the file it is about. Resolved here
    rather than by the compiler (-I): the source is then all of the program, and the
    program caches keyed on it (build_program's, PoCL's own) see an edit to an included
    file, and no include path has to survive being passed as a build option."""
    return resolve_includes(filename, read_kernel(filename), lambda line, _, name: f'#line {line} "{name}"')[0]


def build_program(context, source: str, options: tuple[str, ...]):
    """A built program, from the module cache when this source and options were built before.
    A build error becomes one ClothbenchError carrying the compiler's log."""
    cl = import_pyopencl()
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


class OpenCLDeviceMixin:
    """What both OpenCL backends (OpenCLBackend below, opencl_pbd.OpenCLPbdBackend) do the same
    way: one in-order profiling queue on the device the options name, read-only buffers, the
    collider table, padded launch sizes, the kernel time of the last advance() from its events,
    and releasing their buffers. A backend lists its buffers in _buffers()."""

    local_size: int | None = None

    def _open_queue(self, options: BackendOptions) -> None:
        cl = self._cl = import_pyopencl()
        self._device = choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        self._context = device_context(self._device)
        self.queue = cl.CommandQueue(
            self._context, self._device, properties=cl.command_queue_properties.PROFILING_ENABLE
        )
        self._events: list = []

    def _read_only_buffer(self, array: np.ndarray):
        flags = self._cl.mem_flags.READ_ONLY | self._cl.mem_flags.COPY_HOST_PTR
        return self._cl.Buffer(self._context, flags, hostbuf=np.ascontiguousarray(array))

    def _collider_buffer(self):
        """Every collider as rows of float4 in one constant buffer (kernels/collide.cl has the
        layout), rounded once from float64 as the other backends round them."""
        rows = collider_rows(self.scene)
        table = np.concatenate([rows["spheres"], rows["cylinders"], rows["planes"]])
        limit = self._device.max_constant_buffer_size
        if table.nbytes > limit:
            raise ClothbenchError(
                f"the scene's {len(self.scene.colliders)} colliders take {table.nbytes} bytes, more "
                f"than this device's {limit}-byte constant buffer; use fewer colliders"
            )
        if not len(table):
            table = np.zeros((1, 4), np.float32)  # OpenCL has no empty buffers; never read
        return self._read_only_buffer(table)

    def _check_local_size(self, kernel, name: str) -> None:
        if self.local_size is None:
            return
        limit = kernel.get_work_group_info(self._cl.kernel_work_group_info.WORK_GROUP_SIZE, self._device)
        if self.local_size > limit:
            raise ClothbenchError(f"local size {self.local_size} exceeds this device's limit {limit} for {name}")

    def _launch_size(self, items: int) -> tuple[tuple[int], tuple[int] | None]:
        """(global, local) size of a launch of `items` work items. OpenCL 1.2 wants the global
        size a multiple of the work-group size: pad; the kernels return early past their last
        work item."""
        ls = self.local_size or 1
        local = None if self.local_size is None else (self.local_size,)
        return (-(-items // ls) * ls,), local

    def _buffers(self) -> tuple:
        """Every device buffer the backend made (None where it has none), for close()."""
        raise NotImplementedError

    @property
    def device(self) -> str:
        return self._device.name

    def synchronize(self) -> None:
        self.queue.finish()

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
        for buf in self._buffers():
            if buf is not None:
                buf.release()
        self.queue = None


class OpenCLBackend(OpenCLDeviceMixin, Backend):
    name = "opencl"
    has_local_size = True
    has_generic = True  # --generic: the float4 kernel, one program for every scene
    sweep_variants = ({"strict": True}, {"strict": False}, {"strict": False, "transfer": "per-step"})

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        if options.precision != "f32":
            raise ClothbenchError(f"opencl runs in f32 only (got {options.precision}); f64 is the numpy reference")
        self.transfer = options.transfer or "resident"
        if self.transfer not in TRANSFERS:
            raise ClothbenchError(
                f"opencl transfer must be one of {', '.join(TRANSFERS)}, got {options.transfer!r}"
            )
        self.strict, self.generic = options.strict, options.generic
        self.local_size = options.local_size
        n = self.n = scene.grid
        self.n2 = n * n

        self._open_queue(options)
        cl, context = self._cl, self._context

        # The numbers, rounded once from float64 (docs/semantics.md, Constants), typed below.
        c, float4 = VerletConstants.of(scene), cl.cltypes.make_float4
        self._constants = (c.k, c.b, c.dt, c.dt2, float4(*c.g, 0.0), float4(*c.rest, 0.0))
        self._constant_dtypes = [np.float32] * 4 + [cl.cltypes.float4] * 2
        self._colliders = self._collider_buffer()

        # State buffers, twice over: float4 per particle (generic) or x, y, z planes.
        mf = cl.mem_flags
        state_bytes = self.n2 * 4 * (4 if self.generic else 3)
        self._state = [cl.Buffer(context, mf.READ_WRITE, state_bytes) for _ in range(4)]
        self._host = [np.zeros(state_bytes // 4, np.float32) for _ in range(2)]  # per-step copy
        self._w = np.zeros(self.n2, np.float32)  # inverse mass, as uploaded
        self._w_prev = self._w
        self._inv_mass = None if self.generic else cl.Buffer(context, mf.READ_ONLY, self.n2 * 4)
        self._border = None  # specialised: the particles of the border kernel
        # normals (docs/normals.md) of the state each step reads, only when asked for
        self.normals = options.normals
        self._normals = cl.Buffer(context, mf.WRITE_ONLY, state_bytes) if self.normals else None
        self._normals_of_prev = False  # is there a step whose normals belong to read()[1]?

        # One step's launches as (kernel, work items, arguments after the state buffers), and
        # the programs they come from with the options each was built with (the key).
        self.programs: list = []
        self.key: tuple[tuple[str, ...], ...] = ()
        launches = self._generic_launches() if self.generic else self._specialised_launches()
        self.kernels = [k for k, _, _ in launches]
        for k in self.kernels:
            self._check_local_size(k, k.function_name)
        normals = (self._normals,) if self.normals else ()
        self._launches = [(k, *self._launch_size(items), (*args, *normals)) for k, items, args in launches]

    def build_options(self, vector_width: int = 1) -> tuple[str, ...]:
        """The specialisation key: what this scene's program is built with (the module's
        program cache is keyed by it). Generic: one key for every scene."""
        if self.strict:
            arithmetic = ("-DCLOTH_STRICT", "-cl-fp32-correctly-rounded-divide-sqrt")
        else:
            arithmetic = ("-cl-mad-enable",)
        if self.normals:
            arithmetic += ("-DCLOTH_NORMALS",)
        if self.generic:
            return ("-DCLOTH_GENERIC", *arithmetic)
        s = self.scene
        counts = (("SPHERES", len(s.spheres)), ("CYLINDERS", len(s.cylinders)), ("PLANES", len(s.planes)))
        shape = (f"-DCLOTH_N={self.n}", *(f"-DCLOTH_{kind}={count}" for kind, count in counts if count))
        return (*shape, *arithmetic, f"-DCLOTH_VECTOR_WIDTH={vector_width}")

    def _kernel(self, name: str, dtypes, vector_width: int = 1):
        """Kernel `name` of this scene's program (built once per key, see build_program),
        created once, with every argument's type declared: a wrongly typed argument raises
        instead of being reinterpreted."""
        options = self.build_options(vector_width)
        program = build_program(self._context, program_source(KERNEL_FILE), options)
        self.programs.append(program)
        self.key += (options,)
        k = self._cl.Kernel(program, name)
        k.set_scalar_arg_dtypes([*dtypes, *([None] if self.normals else [])])
        return k

    def _generic_launches(self):
        """The float4 kernel, one work item per particle; n and the counts are arguments."""
        i32, s = np.int32, self.scene
        dtypes = [None] * 4 + [i32, *self._constant_dtypes, None, i32, i32, i32]
        args = (i32(self.n), *self._constants, self._colliders)
        args += (i32(len(s.spheres)), i32(len(s.cylinders)), i32(len(s.planes)))
        return [(self._kernel("verlet_cloth", dtypes), self.n2, args)]

    def _specialised_launches(self):
        """The interior (rows and columns 2..n-3) in vectors of V particles, V the device's
        preferred float width, then every other particle through the border kernel."""
        n = self.n
        v = max(1, self._device.preferred_vector_width_float)
        vectors_per_row = -(-(n - 4) // v) if n - 4 >= v else 0
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : n - 2] = vectors_per_row > 0
        particles = np.flatnonzero(~covered).astype(np.int32)
        self._border = self._read_only_buffer(particles)
        dtypes = [None] * 5 + self._constant_dtypes + [None]
        args = (*self._constants, self._colliders)
        launches = []
        if vectors_per_row:
            interior = self._kernel("verlet_cloth_interior", dtypes, v)
            launches.append((interior, vectors_per_row * (n - 4), args))
        border = self._kernel("verlet_cloth_border", dtypes + [None, np.int32])
        launches.append((border, particles.size, (*args, self._border, np.int32(particles.size))))
        return launches

    def _buffers(self) -> tuple:
        return (*self._state, self._colliders, self._inv_mass, self._border, self._normals)

    # --- Backend interface -------------------------------------------------------------
    @property
    def mode(self) -> str:
        parts = ["strict" if self.strict else "fast"]
        parts += ["normals"] * self.normals + ["generic"] * self.generic
        return "/".join([*parts, self.transfer, f"ls={self.local_size or 'auto'}"])

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.queue.finish()  # pending per-step copies may still read the host copies
        self._w = np.ascontiguousarray(pos[:, 3], np.float32)
        self._w_prev = np.ascontiguousarray(prev[:, 3], np.float32)
        self._normals_of_prev = False
        for host, state in zip(self._host, (pos, prev)):
            host[:] = self._pack(np.asarray(state, np.float32))
        if self._inv_mass is not None:
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
            state = (pos, prev, pos_out, prev_out) if self.generic else (pos, prev, self._inv_mass, pos_out, prev_out)
            for kernel, global_size, local_size, args in self._launches:
                self._events.append(kernel(queue, global_size, local_size, *state, *args))
            self._state = [pos_out, prev_out, pos, prev]  # ping-pong: swap references, no copy
            if per_step:  # ... and comes back down, so the host owns the next step's input
                cl.enqueue_copy(queue, self._host[0], pos_out, is_blocking=False)
                cl.enqueue_copy(queue, self._host[1], prev_out, is_blocking=False)
        if steps > 0:
            self._w_prev = self._w  # prev_out carries pos's inverse mass
            self._normals_of_prev = self.normals

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        out = []
        for buf, w in zip(self._state[:2], (self._w, self._w_prev)):
            flat = np.empty(self._host[0].size, np.float32)
            self._cl.enqueue_copy(self.queue, flat, buf)  # blocking: waits for the steps
            out.append(self._unpack(flat, w))
        return out[0], out[1]

    def read_normals(self) -> np.ndarray | None:
        """(n*n, 4) normals of the positions the last step read, read()[1] (docs/normals.md);
        None unless options.normals, or before the first step."""
        if not self._normals_of_prev:
            return None
        flat = np.empty(self._host[0].size, np.float32)
        self._cl.enqueue_copy(self.queue, flat, self._normals)  # blocking: waits for the steps
        return self._unpack(flat, np.zeros(self.n2, np.float32))

    # --- layouts -----------------------------------------------------------------------
    def _pack(self, state: np.ndarray) -> np.ndarray:
        """(n2, 4) -> the device layout: float4 rows (generic) or x, y, z planes."""
        return state.reshape(-1) if self.generic else state[:, :3].T.reshape(-1)

    def _unpack(self, flat: np.ndarray, w: np.ndarray) -> np.ndarray:
        if self.generic:
            return flat.reshape(self.n2, 4)
        out = np.empty((self.n2, 4), np.float32)
        out[:, :3] = flat.reshape(3, self.n2).T
        out[:, 3] = w
        return out
