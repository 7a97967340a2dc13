"""What both OpenCL backends (verlet.py, pbd.py) share: the probe, the default device (one
that compiles; the fastest by measurement where several do), one context per device,
program sources and the program cache keyed by build options, and OpenCLDeviceMixin, the
queue, buffers, launch sizes and profiling events. Which runtimes a process sees, and
making Intel's pip runtime one of them: runtimes.py."""

from __future__ import annotations

import json
import os
import re
import time
import warnings
from dataclasses import dataclass, replace

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.kernel_source import read_kernel, resolve_includes
from clothbench.backends.base import Availability, BackendOptions
from clothbench.backends.opencl import runtimes
from clothbench.backends.opencl.bodies import collider_counts
from clothbench.backends.opencl.build_log import compiler_log
from clothbench.backends.opencl.isolated import in_child_per_device
from clothbench.backends.opencl.runtimes import INTEL_EXTRA
from clothbench.backends.tuning import median_seconds
from clothbench.native import cache_dir

INSTALL_HINT = "pip install pyopencl pocl-binary-distribution"  # both are clothbench's own dependencies
# The one command that gives a machine an OpenCL CPU device that compiles, with pip alone
# (Intel's runtime is x86-64 only), and the root alternative (Debian's PoCL, whose LLVM is
# newer than the PoCL wheel's): docs/opencl-devices.md
FIX_HINT = f"{INTEL_EXTRA}, or as root apt-get install pocl-opencl-icd"
NO_PLATFORM_HINT = f"{FIX_HINT}, or a vendor's driver"

# The probe's test that a device can compile: a kernel every working OpenCL C compiler builds,
# with the float16 square root the step kernels take (the PoCL wheel's LLVM 14 built a scalar
# kernel on a Zen 5, then aborted the whole process on this one: docs/opencl-devices.md).
_PROBE_SOURCE = (
    "__kernel void clothbench_probe(__global float16 *a) { size_t i = get_global_id(0); a[i] = sqrt(a[i]); }"
)
PROBE_CACHE = "opencl-probe"  # <cache>/tuning/opencl-probe.json: each device's probe, per CPU

# The default device's measurement (docs/opencl-devices.md): the project's own step, short,
# at the smallest grid the benchmarks report (at 128² launch overhead decides, not the step).
TIMING_GRID, TIMING_STEPS = 256, 10
# Times closer than this are a tie, given to the earlier runtime in RUNTIME_ORDER: run to run
# the same device's time moves by more (docs/opencl-devices.md, "The default device").
TIE_MARGIN = 0.10

# Module-level caches, so that a sweep building many backends builds each program once.
_contexts: dict = {}  # device int_ptr -> Context
_programs: dict = {}  # (context int_ptr, source, build options) -> built Program
_compiles: dict = {}  # (device int_ptr, probe source) -> None (it compiles) or the error line
_defaults: dict = {}  # compiling devices' int_ptrs -> DefaultDevice, once per process
_retuned = False  # whether this process measured the default again (--retune) already


def import_pyopencl():
    import pyopencl
    import pyopencl.cltypes  # noqa: F401  (float4 argument dtypes)

    runtimes.prepare_loader(pyopencl)  # before the loader's first look at its vendors
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
    return Availability(True, device=device.name, driver=platform_driver(device))


def _platforms() -> list:
    cl = import_pyopencl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # the ICD loader reports "no platform" as PLATFORM_NOT_FOUND_KHR
        platforms = []
    if not platforms:
        raise ClothbenchError(f"no OpenCL platform found ({NO_PLATFORM_HINT})")
    return platforms


def _devices_listing() -> str:
    return ", ".join(
        f"{p}:{d} {dev.name}" for p, platform in enumerate(_platforms()) for d, dev in enumerate(platform.get_devices())
    )


def compile_error(device) -> str | None:
    """None if `device` builds and runs the probe kernel, else why not, in one line. Listed is
    not enough: PoCL 3.0's LLVM 14 lists CPUs it cannot compile for ("unknown target CPU"), and
    a compiler may abort the process instead of failing the build. So every listed device is
    probed at once in a child process (each alone in one of its own where that child dies),
    once per device, driver, CPU and probe, and the answers kept on disk."""
    key = (device.int_ptr, _PROBE_SOURCE)
    if key not in _compiles:
        _compiles.update(_probe_listed(_PROBE_SOURCE))
    return _compiles.get(key)


def _probe_listed(source: str) -> dict:
    """{(device int_ptr, source): None or the error} for every listed device."""
    from clothbench.native import cpu_identity

    listed = {
        f"{p}:{d}": (dev, _timing_name(dev, runtimes.runtime_of(platform)))
        for p, platform in enumerate(_platforms())
        for d, dev in enumerate(platform.get_devices())
    }
    path = cache_dir("tuning") / f"{PROBE_CACHE}.json"
    try:
        kept = json.loads(path.read_text())
    except (OSError, ValueError):
        kept = {}
    kept = kept if isinstance(kept, dict) else {}
    known = kept.setdefault(json.dumps({"cpu": cpu_identity(), "probe": source}), {})
    todo = [spec for spec, (_, name) in listed.items() if name not in known]
    if todo:
        for spec, answer in in_child_per_device(
            "clothbench.backends.opencl.isolated:probe_devices", todo, source
        ).items():
            known[listed[spec][1]] = answer if isinstance(answer, (str, type(None))) else str(answer)
        try:
            path.write_text(json.dumps(kept, indent=1, sort_keys=True))
        except OSError:  # an unwritable cache costs a probe next time, nothing else
            pass
    return {(dev.int_ptr, source): known.get(name) for dev, name in listed.values()}


@dataclass(frozen=True)
class DefaultDevice:
    device: object  # pyopencl.Device
    spec: str  # 'platform:device'
    reason: str  # one line: why this one


def choose_device(spec: str | None, retune: bool = False):
    """The device `spec` names ('platform:device' indices or names, as PYOPENCL_CTX), else
    default_device()'s."""
    cl = import_pyopencl()
    _platforms()
    if spec:
        try:
            chosen = cl.choose_devices(interactive=False, answers=spec.split(":"))[0]
        except (cl.Error, RuntimeError, ValueError, IndexError):
            raise ClothbenchError(
                f"no OpenCL device {spec!r} (give 'platform:device', e.g. 0:0; here: {_devices_listing()})"
            ) from None
        error = compile_error(chosen)
        if error is not None:  # building the step there could take the process down with it
            raise ClothbenchError(f"OpenCL device {spec} ({chosen.name}) cannot compile clothbench's kernels: {error}")
        return chosen
    return default_device(retune).device


def ordered_devices() -> list[tuple[str, object, str]]:
    """Every device as ('platform:device', device, runtime), in RUNTIME_ORDER, then as listed."""
    found = [
        (f"{p}:{d}", device, runtimes.runtime_of(platform))
        for p, platform in enumerate(_platforms())
        for d, device in enumerate(platform.get_devices())
    ]
    return sorted(found, key=lambda row: runtimes.RUNTIME_ORDER.index(row[2]))


def default_device(retune: bool = False) -> DefaultDevice:
    """Among the devices that compile: the only one; else, with tuning on, the fastest at the
    project's own step, measured once per set of installed (device, driver version) and kept
    on disk (--retune measures again, once per process); else (CLOTHBENCH_TUNING=off) the
    first in runtimes.RUNTIME_ORDER: system PoCL, Intel's CPU runtime, other, the PoCL wheel."""
    rows = ordered_devices()
    compiling = [(spec, dev, runtime) for spec, dev, runtime in rows if compile_error(dev) is None]
    if not compiling:
        raise ClothbenchError(_none_compiles(rows))
    global _retuned
    key = tuple(dev.int_ptr for _, dev, _ in compiling)
    retune = retune and not _retuned  # a sweep's every backend asks: measure once
    if retune or key not in _defaults:
        _retuned = _retuned or retune
        _defaults[key] = _pick_default(compiling, retune)
    return _defaults[key]


def _pick_default(compiling: list, retune: bool) -> DefaultDevice:
    from clothbench.backends.tuning import choose_shape, tuning_enabled

    names = [_timing_name(dev, runtime) for _, dev, runtime in compiling]
    if len(compiling) == 1:
        return DefaultDevice(compiling[0][1], compiling[0][0], "the only OpenCL device here that compiles")
    if not tuning_enabled():
        spec, dev, runtime = compiling[0]
        order = ", ".join(runtimes.RUNTIME_ORDER)
        return DefaultDevice(dev, spec, f"first that compiles in the order {order} (CLOTHBENCH_TUNING=off)")
    specs = dict(zip(names, (spec for spec, _, _ in compiling)))
    key = {"devices": "; ".join(sorted(names)), "grid": str(TIMING_GRID), "mode": "fast"}
    timed: dict = {}

    def time_candidate(name: str) -> float:
        if not timed:  # all at once, interleaved, the first time choose_shape asks
            timed.update(isolated_seconds_per_step(list(specs.values())))
        if isinstance(timed[specs[name]], ClothbenchError):
            raise timed[specs[name]]
        return timed[specs[name]]

    choice = choose_shape(DEFAULT_TUNING, key, names, time_candidate, retune)
    measured = {n: ms for n, ms in _measured_ms(key).items() if n in specs and isinstance(ms, (int, float))}
    if measured:  # a near-tie is noise: the earlier in RUNTIME_ORDER (names are in that order)
        best = min(measured.values())
        choice = next(n for n in names if measured.get(n, float("inf")) <= best * (1 + TIE_MARGIN))
    times = ", ".join(f"{specs[n]} {measured[n]:.2f}" for n in names if n in measured)
    detail = f": {times} ms/step" if times else ""
    reason = (
        f"fastest of {len(names)} that compile (a tie within {TIE_MARGIN:.0%} to the earlier of "
        f"{', '.join(runtimes.RUNTIME_ORDER)}), sphere {TIMING_GRID}² fast{detail}; --retune measures again"
    )
    index = names.index(choice)
    return DefaultDevice(compiling[index][1], compiling[index][0], reason)


DEFAULT_TUNING = "opencl-device"  # its tuning file: <cache>/tuning/opencl-device.json


def _timing_name(device, runtime: str) -> str:
    """A device's name in the tuning file: the same across processes, whatever the order in
    which the loader lists its platforms."""
    return f"{device.name} [{runtime}: {' '.join(device.platform.version.split())}; driver {device.driver_version}]"


def _seconds_per_step(specs: list[str]) -> dict:
    """Seconds per step of the project's own Verlet step (sphere scene, fast, the default
    kernel shape) on each device of `specs`, or the ClothbenchError that stopped it: what the
    default device is chosen by. The devices take turns, so that a load that comes and goes
    on a shared machine falls on each alike, and each keeps its fastest turn (noise only
    ever adds time)."""
    from contextlib import ExitStack

    from clothbench.backends.opencl.verlet import OpenCLBackend
    from clothbench.model.scene import load_setup

    setup = load_setup("sphere").replace(grid=TIMING_GRID)
    result: dict = {}
    with ExitStack() as stack:
        running = {}
        for spec in specs:
            options = BackendOptions(device=spec)  # explicit: building it never asks for the default
            shapes = OpenCLBackend.kernel_shapes(setup.scene, options) if OpenCLBackend.capabilities.shapes else ()
            if shapes:  # its first shape: no kernel-shape tuning inside this measurement
                options = replace(options, shape=shapes[0])
            try:
                backend = stack.enter_context(OpenCLBackend(setup.scene, setup.solver, options))
                backend.upload(*backend.initial_state())
                backend.advance(TIMING_STEPS)  # warm-up: first launches, page faults
                backend.synchronize()
            except ClothbenchError as e:
                result[spec] = e
                continue
            except import_pyopencl().Error as e:  # a build that "succeeded" without the kernel
                result[spec] = ClothbenchError(f"OpenCL device {spec}: {type(e).__name__}: {e}")
                continue
            running[spec], result[spec] = backend, float("inf")
        for _ in range(7):
            for spec, backend in running.items():
                start = time.perf_counter()
                backend.advance(TIMING_STEPS)
                backend.synchronize()
                result[spec] = min(result[spec], (time.perf_counter() - start) / TIMING_STEPS)
    return result


# _seconds_per_step, as isolated.py's child imports it
SECONDS_PER_STEP = f"{__name__}:_seconds_per_step"


def isolated_seconds_per_step(specs: list[str], measure: str = SECONDS_PER_STEP) -> dict:
    """_seconds_per_step (or `measure`, 'module:function') in a child process (isolated.py):
    the probe tries one construct, not every kernel, and a compiler that aborts on one of the
    step's would take the command down with it. A device whose child dies is failed with what
    its compiler said; the command goes on with the others."""
    return in_child_per_device(measure, specs)


def _measured_ms(key: dict) -> dict[str, float]:
    """The ms/step the tuning file holds for `key` (empty if unreadable)."""
    try:
        data = json.loads((cache_dir("tuning") / f"{DEFAULT_TUNING}.json").read_text())
        return dict(data[json.dumps(key, sort_keys=True)]["ms"])
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def device_listing(retune: bool = False) -> tuple[list[dict], str]:
    """Every OpenCL device of every platform, as `clothbench backends` shows them, and one
    line saying which is the default and why. Raises ClothbenchError where there is no
    platform."""
    rows = []
    for p, platform in enumerate(_platforms()):
        for d, dev in enumerate(platform.get_devices()):
            llvm = re.search(r"LLVM[ -]?(\d+(?:\.\d+)*)", f"{platform.version} {dev.version}")
            error = compile_error(dev)
            rows.append(
                {
                    "device": f"{p}:{d}",
                    "name": dev.name,
                    "runtime": runtimes.runtime_of(platform),
                    "platform": platform.name,
                    "platform_version": " ".join(platform.version.split()),
                    "driver_version": dev.driver_version,
                    "llvm": llvm.group(1) if llvm else "",
                    "compiles": error is None,
                    "error": error or "",
                    "default": False,
                }
            )
    given = os.environ.get("PYOPENCL_CTX")
    try:
        if given:
            chosen, reason = choose_device(given), f"PYOPENCL_CTX={given} names it"
        else:
            default = default_device(retune)
            chosen, reason = default.device, default.reason
    except ClothbenchError as e:
        return rows, str(e)
    devices = [dev for platform in _platforms() for dev in platform.get_devices()]
    for row, dev in zip(rows, devices):
        if dev.int_ptr == chosen.int_ptr:
            row["default"] = True
            return rows, f"default: {row['device']} {dev.name} ({row['runtime']}): {reason}"
    return rows, reason


def _none_compiles(rows: list) -> str:
    failures = dict.fromkeys(f"{dev.name}: {compile_error(dev)}" for _, dev, _ in rows)  # ordered, no repeats
    if any(runtime == runtimes.INTEL_CPU for _, _, runtime in rows):
        hint = "check the OpenCL drivers' installation"
    elif any("unknown target CPU" in f for f in failures):
        hint = f"this PoCL's LLVM predates the CPU: {FIX_HINT}"
    else:
        hint = FIX_HINT
    return f"no OpenCL device here can compile a kernel ({'; '.join(failures)}): {hint}"


def platform_driver(device) -> str:
    """What a run on `device` names as its driver (probe's and the backends' `driver`): the
    platform's name and version and the device's driver version, e.g. "Portable Computing
    Language: OpenCL 3.0 PoCL 3.1+debian Linux, ...; driver 3.1+debian". The device's name
    alone is the same under two runtimes (Intel's and the PoCL wheel's both say the CPU's)."""
    platform = device.platform
    return f"{platform.name}: {' '.join(platform.version.split())}; driver {device.driver_version}"


def device_context(device):
    """The process's one context for `device`, shared by every backend on it."""
    key = device.int_ptr
    if key not in _contexts:
        _contexts[key] = import_pyopencl().Context([device])
    return _contexts[key]


def program_source(filename: str, generated: dict | None = None) -> str:
    """kernels/`filename` with its includes resolved (collide.cl) and `#line` directives
    naming each file, so that a build log points into the file it is about. Resolved here
    rather than by the compiler (-I): the source is then all of the program, and the
    program caches keyed on it (build_program's, PoCL's own) see an edit to an included
    file, and no include path has to survive being passed as a build option.
    `#include <name>` is an optional part of the program (a scene's meshes): its text is
    generated[name]() where given, else nothing."""
    text = read_kernel(filename)
    parts = {name: (lambda: "") for name in re.findall(r"^[ \t]*#include[ \t]+<([^>]+)>", text, re.M)}
    mark = lambda line, _, name: f'#line {line} "{name}"'  # noqa: E731
    return resolve_includes(filename, text, mark, {**parts, **(generated or {})})[0]


def build_program(context, source: str, options: tuple[str, ...]):
    """A built program, from the module cache when this source and options were built before.
    A build error becomes one ClothbenchError carrying the compiler's log."""
    cl = import_pyopencl()
    key = (context.int_ptr, source, options)
    if key not in _programs:
        program = cl.Program(context, source)
        try:
            with warnings.catch_warnings():  # Intel's runtime logs every build; failures say more below
                warnings.simplefilter("ignore", cl.CompilerWarning)
                program.build(options=list(options))
        except cl.Error as e:
            # the log is in the exception on every runtime; the program's own only on PoCL's
            # (build_log.py), and asking an unbuilt one makes pyopencl warn and build nothing
            device = context.devices[0]
            raise ClothbenchError(
                f"OpenCL build failed on {device.name} (options: {' '.join(options) or 'none'}):\n"
                + compiler_log(str(e))
            ) from None
        _programs[key] = program
    return _programs[key]


def shape_options(scene, vector_width: int) -> tuple[str, ...]:
    """The build options that specialise a program to the scene's shape: the grid side, the
    count of each collider kind it has, and the particles per work item."""
    return (
        f"-DCLOTH_N={scene.grid}",
        *(f"-D{kind.count_name('opencl')}={count}" for kind, count in collider_counts(scene) if count),
        f"-DCLOTH_VECTOR_WIDTH={vector_width}",
    )


def arithmetic_options(strict: bool) -> tuple[str, ...]:
    """Strict: the documented operation order, no contraction, correctly rounded division
    and sqrt (bit-exact with NumPy float32); fast: let the compiler fuse."""
    return ("-DCLOTH_STRICT", "-cl-fp32-correctly-rounded-divide-sqrt") if strict else ("-cl-mad-enable",)


class OpenCLDeviceMixin:
    """What both OpenCL backends do the same way: one in-order profiling queue on the device
    the options name, read-only buffers, padded launch sizes, the kernel
    time of the last advance() from its events, and releasing their buffers. A backend lists
    its buffers in _buffers(). The options' local_size is the work-group size (None: the
    runtime chooses, and the mode says ls=auto)."""

    device_timer = "opencl-events"  # what device_elapsed_ms() reads (harness/timing.py DEVICE_TIMERS)

    def _open_queue(self, options: BackendOptions) -> None:
        cl = self._cl = import_pyopencl()
        self._device = choose_device(options.device or os.environ.get("PYOPENCL_CTX"), options.retune)
        self._context = device_context(self._device)
        self.queue = cl.CommandQueue(
            self._context, self._device, properties=cl.command_queue_properties.PROFILING_ENABLE
        )
        self._events: list = []

    @property
    def local_size(self) -> int | None:
        return self.options.local_size

    def _time_shape(self, name: str) -> float:
        """Seconds per step of a short synchronised run of shape `name` from the initial state
        (a backend tuning its shape measures on itself, then leaves the initial state
        uploaded): _timing_steps() steps, the median of timing_repeats, both the backend's."""
        try:
            self._use_shape(name)
            self.upload(*self.initial_state())
            steps = self._timing_steps()
            seconds = median_seconds(lambda: self.advance(steps), self.synchronize, repeats=self.timing_repeats)
            self.upload(*self.initial_state())
        except self._cl.Error as e:  # a shape this device cannot launch is not a candidate
            raise ClothbenchError(f"{name}: {e}") from None
        self._events = []  # device_elapsed_ms() is about the caller's advance(), not these
        return seconds / steps

    def _read_only_buffer(self, array: np.ndarray):
        flags = self._cl.mem_flags.READ_ONLY | self._cl.mem_flags.COPY_HOST_PTR
        return self._cl.Buffer(self._context, flags, hostbuf=np.ascontiguousarray(array))

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

    @property
    def driver(self) -> str:
        """Platform name and version and the device's driver version: which of several
        runtimes (PoCL's, Intel's, ...) ran it, and which build of it."""
        return platform_driver(self._device)

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
