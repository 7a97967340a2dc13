"""What both OpenCL backends (verlet.py, pbd.py) share: the probe, choosing a device that can
compile, one context per device, program sources and the program cache keyed by build
options, and OpenCLDeviceMixin, the queue, buffers, launch sizes and profiling events."""

from __future__ import annotations

import os

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.kernel_source import read_kernel, resolve_includes
from clothbench.backends.base import Availability, BackendOptions
from clothbench.backends.kernel_inputs import collider_rows

INSTALL_HINT = "pip install pyopencl pocl-binary-distribution"  # both are clothbench's own dependencies
# README's "System packages": PoCL's wheel has an LLVM too old for recent CPUs, Debian's has not
NO_PLATFORM_HINT = "pip install pocl-binary-distribution, or apt-get install pocl-opencl-icd, or a vendor's driver"

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
            f"no OpenCL platform found ({NO_PLATFORM_HINT})"
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


def shape_options(scene, vector_width: int) -> tuple[str, ...]:
    """The build options that specialise a program to the scene's shape: the grid side, the
    count of each collider kind it has, and the particles per work item."""
    counts = (("SPHERES", len(scene.spheres)), ("CYLINDERS", len(scene.cylinders)), ("PLANES", len(scene.planes)))
    return (
        f"-DCLOTH_N={scene.grid}",
        *(f"-DCLOTH_{kind}={count}" for kind, count in counts if count),
        f"-DCLOTH_VECTOR_WIDTH={vector_width}",
    )


def arithmetic_options(strict: bool) -> tuple[str, ...]:
    """Strict: the documented operation order, no contraction, correctly rounded division
    and sqrt (bit-exact with NumPy float32); fast: let the compiler fuse."""
    return ("-DCLOTH_STRICT", "-cl-fp32-correctly-rounded-divide-sqrt") if strict else ("-cl-mad-enable",)


class OpenCLDeviceMixin:
    """What both OpenCL backends do the same way: one in-order profiling queue on the device
    the options name, read-only buffers, the collider table, padded launch sizes, the kernel
    time of the last advance() from its events, and releasing their buffers. A backend lists
    its buffers in _buffers(). The options' local_size is the work-group size (None: the
    runtime chooses, and the mode says ls=auto)."""

    def _open_queue(self, options: BackendOptions) -> None:
        cl = self._cl = import_pyopencl()
        self._device = choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        self._context = device_context(self._device)
        self.queue = cl.CommandQueue(
            self._context, self._device, properties=cl.command_queue_properties.PROFILING_ENABLE
        )
        self._events: list = []

    @property
    def local_size(self) -> int | None:
        return self.options.local_size

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
