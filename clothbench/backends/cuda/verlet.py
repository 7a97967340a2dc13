"""CUDA: kernels/verlet_cloth.cu through CuPy, the chapter's section 22.7.

Host code only; the step itself is docs/semantics.md, performed by the kernels, and how they
are launched is launch.py (the kernel shapes and PingPong). The chapter keeps two pairs of
device buffers, (pos, pos_prev) x (in, out), and copies each output to its input with
cudaMemcpyDeviceToDevice after every launch; `--transfer copy` does exactly that. The
default, `swap`, keeps two buffers, x(t) and x(t - dt): a launch writes its latest state over
x(t - dt) in place and the host exchanges the two pointers, moving 48 bytes a particle a step
where the chapter's pairs move 64 (and the copies 64 more), so the harness shows what both cost.

Kernel shapes (docs/cuda.md): one step a launch in blocks of 64..512 threads ("block=N"), or,
where the grid fits one block's shared memory, K steps a launch ("steps/launch=K"). The
backend times each on the device with CUDA events and keeps the fastest per device, driver,
grid, colliders and arithmetic (backends/tuning.py); `--shape` names one.

Specialisation: by default the kernels are built for the scene and solver, its constants and
colliders compile-time constants (exact float literals in -D defines) and the code of a
collider kind the scene lacks left out; `--generic` builds the one module that takes them all
as arguments. `kernel_defines` gives the -D switches, and compiled modules are cached by them.
Meshes (kernels/collide_mesh.cuh) and motion are switched in only for a scene that has them
(docs/cuda.md, "Meshes and motion"), and so is [self_collision] (kernels/self_collision.cuh,
self_contact.py: its pass after every verlet_step launch; not verlet_steps, which has no launch
between steps to run it in, so its shapes are not offered then).

Compilation: we compile the kernels ourselves (NVRTC through CuPy's binding, or nvcc) and
load the binary with RawModule(path=...). CuPy's own RawModule(code=...) path appends
`-ftz=true`, flushing denormals that NumPy keeps, which `--strict` cannot allow.

CuPy of either CUDA major runs it: cupy-cuda12x (the `cuda` extra) or cupy-cuda13x
(`cuda13`), with NVRTC where its library loads (the extra's wheel or a toolkit), else nvcc;
probe() and `driver` name the CuPy build, its CUDA runtime and the compiler found
(docs/cuda.md, "CUDA 12 or 13").

cupy is an optional extra and is imported only inside functions: importing this module
never needs it, and probe() says how to install it.
"""

from __future__ import annotations

import statistics
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from clothbench.model.colliders.kinds import kinds_in
from clothbench.errors import ClothbenchError
from clothbench.kernel_source import c_float, kernel_hash, read_kernel, resolve_includes
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.cuda import launch
from clothbench.backends.cuda.runtime import (  # noqa: F401 (re-exported: tests and peers use them from here)
    CUPY_PACKAGES,
    EXTRAS,
    INSTALL_HINT,
    compiler,
    compiler_name,
    cuda_major,
    driver_note,
    error_name,
    install_hint,
    installed_version,
    nvcc_available,
    nvrtc_available,
    version_string,
)
from clothbench.backends.cuda.launch import (
    AUTO_BLOCK,
    TRANSFERS,
    PingPong,
    attached_pins,
    kernel_constants,
    motion_rows,
)
from clothbench.backends.cuda.self_contact import KERNELS as SELF_KERNELS, self_collision_defines
from clothbench.model.kernel_inputs import collider_rows

__all__ = ["AUTO_BLOCK", "TRANSFERS", "PingPong", "CudaBackend", "kernel_constants", "kernel_defines"]

KERNEL_FILE = "verlet_cloth.cu"
KERNEL_NAME = launch.STEP_KERNEL
TUNING_STEPS = 64  # steps a candidate shape is timed over: a multiple of every steps/launch
TUNING_REPEATS = 3


def compile_options(strict: bool) -> tuple[str, ...]:
    """nvcc/NVRTC options (both accept these spellings) for the strict or fast kernel."""
    if strict:
        # every float operation rounded on its own and correctly, denormals kept: as NumPy
        return (
            "--std=c++17",
            "--fmad=false",
            "--ftz=false",
            "--prec-div=true",
            "--prec-sqrt=true",
            "-DCLOTH_STRICT",
        )
    return ("--std=c++17", "--use_fast_math")


def kernel_defines(
    scene: Scene,
    solver: Solver,
    normals: bool = False,
    generic: bool = False,
    mesh_collision: str | None = None,
    transfer: str = TRANSFERS[0],
) -> tuple[str, ...]:
    """The -D switches that build verlet_cloth.cu for this scene and solver: the
    specialisation key. `transfer` copy adds CLOTH_TWO_PAIRS (the chapter's four buffers);
    swap, the default, builds the kernels that write in place.

    Generic: only CLOTH_GENERIC (and CLOTH_NORMALS), so every scene shares one kernel; a
    scene with meshes adds CLOTH_MESHES (every mesh scene shares one), a moving one CLOTH_MOTION.
    Specialised: the constants as exact float literals, then scene_defines (the colliders).
    A scene with [self_collision] adds CLOTH_SELF_COLLISION in either build (its numbers are
    kernel arguments).
    """
    if transfer not in TRANSFERS:
        raise ValueError(f"transfer must be one of {', '.join(TRANSFERS)}, got {transfer!r}")
    defines = ["-DCLOTH_NORMALS"] if normals else []
    defines += ["-DCLOTH_TWO_PAIRS"] if transfer == "copy" else []
    defines += self_collision_defines(scene)
    if generic:
        return (*defines, "-DCLOTH_GENERIC", *scene_defines(scene, mesh_collision, generic=True))
    for name, value in kernel_constants(scene, solver).items():
        literal = str(value) if name == "n" else c_float(value)
        defines.append(f"-DCLOTH_{name.upper()}={literal}")
    return (*defines, *scene_defines(scene, mesh_collision))


def scene_defines(scene: Scene, mesh_collision: str | None = None, generic: bool = False) -> tuple[str, ...]:
    """The -D switches of the scene's colliders, meshes and motion (kernels/collide.cuh), for
    either kernel. Generic: CLOTH_MESHES where the scene has meshes, CLOTH_MOTION where it
    moves. Specialised: the collider counts, and the colliders of each kind the scene has as a
    brace list of float4 rows (a moving scene: only the counts and the per-step table's size,
    CLOTH_MOTION_ROWS and CLOTH_PIN_COUNT), and the mesh count. `mesh_collision` (accelerated,
    the default, or naive) picks CLOTH_MESH_BVH.
    """
    algorithm = mesh_collision or "accelerated"
    if algorithm not in CudaBackend.capabilities.mesh_collisions:
        raise ValueError(f"mesh_collision must be accelerated or naive, got {mesh_collision!r}")
    mesh = ["-DCLOTH_MESH_BVH"] if scene.meshes and algorithm == "accelerated" else []
    moving = scene.has_motion
    if generic:
        return (*(["-DCLOTH_MESHES", *mesh] if scene.meshes else []), *(["-DCLOTH_MOTION"] if moving else []))
    defines = []
    table = collider_rows(scene)
    for kind in kinds_in("cuda"):  # the kinds collide.cuh takes
        rows = table[kind.plural]
        defines.append(f"-D{kind.count_name('cuda')}={len(rows) // kind.rows}")
        if len(rows) and not moving:  # a moving scene's rows are per step, not compiled in
            items = ",".join("{" + ",".join(c_float(v) for v in row) + "}" for row in rows)
            defines.append(f"-DCLOTH_{kind.plural.upper()}={{{items}}}")
    if scene.meshes:  # the triangles are buffers (launch.mesh_buffers): too large for literals
        defines += [f"-DCLOTH_MESH_COUNT={len(scene.meshes)}", *mesh]
    if moving:
        rows, pins = max(1, motion_rows(scene)), attached_pins(scene)
        defines += ["-DCLOTH_MOTION", f"-DCLOTH_MOTION_ROWS={rows}", f"-DCLOTH_PIN_COUNT={pins}"]
    return tuple(defines)


# --- availability ---------------------------------------------------------------------


# cupy_build and probe stay here: they look up compiler and installed_version in this module,
# where the tests replace them
def cupy_build(cupy) -> str:
    """'cupy-cuda13x 14.2.0, CUDA 13.2 runtime': the CuPy wheel (or source build) imported and
    the CUDA runtime it was built with; two wheels at once are both named (CuPy warns)."""
    found = [f"{p} {v}" for p in CUPY_PACKAGES if (v := installed_version(p)) is not None]
    build = " + ".join(found) or f"cupy {getattr(cupy, '__version__', '?')}"
    try:
        return f"{build}, CUDA {version_string(int(cupy.cuda.runtime.runtimeGetVersion()))} runtime"
    except Exception:
        return build


def probe() -> Availability:
    """Whether CUDA runs here; the reason names the CuPy build and its CUDA runtime, and the
    compiler found (for a usable backend too: what it will compile and run with)."""
    try:
        import cupy
    except ImportError:
        return Availability(False, INSTALL_HINT)
    except Exception as e:  # installed but broken, e.g. built against another numpy
        return Availability(False, f"cupy failed to import: {type(e).__name__}: {error_name(e)}")
    build, major = cupy_build(cupy), cuda_major(cupy)
    try:
        count = cupy.cuda.runtime.getDeviceCount()
    except Exception as e:  # no driver: cudaErrorInsufficientDriver / cudaErrorNoDevice
        return Availability(False, f"no CUDA device ({build}: {error_name(e)}{driver_note(cupy, major)})")
    if count < 1:
        return Availability(False, f"no CUDA device ({build}: 0 devices)")
    using = compiler()
    if using is None:
        return Availability(False, f"no CUDA compiler for {build} ({install_hint(major)}, or put nvcc on PATH)")
    name = cupy.cuda.runtime.getDeviceProperties(0)["name"]
    device = name.decode() if isinstance(name, bytes) else str(name)
    compiler_label = compiler_name(using)
    return Availability(
        True, reason=f"{build}, {compiler_label}", device=device, driver=cuda_driver(cupy, compiler_label, device)
    )


def cuda_driver(cupy, compiler_label: str, device: str) -> str:
    """What a CUDA run names as its driver (probe's and CudaBackend.driver): the NVIDIA
    driver's CUDA version, the CuPy build and its runtime, the compiler, the device, e.g.
    "CUDA driver 13.0, cupy-cuda13x 14.0.1, CUDA 13.0 runtime, NVRTC 13.0, NVIDIA H200"."""
    driver = version_string(cupy.cuda.runtime.driverGetVersion())
    return f"CUDA driver {driver}, {cupy_build(cupy)}, {compiler_label}, {device}"


# --- compilation ----------------------------------------------------------------------


def _nvcc_escaped(option: str) -> str:
    """nvcc splits an option's value at commas (-D a,b defines a and b); '\\,' keeps one."""
    return option.replace(",", "\\,") if option.startswith("-D") else option


@lru_cache(maxsize=64)
def compile_kernel(
    strict: bool,
    arch: str,
    using: str,
    code: str = "cubin",
    defines: tuple[str, ...] = (),
    kernel_file: str = KERNEL_FILE,
) -> bytes:
    """kernels/`kernel_file` (verlet_cloth.cu, or vbd_cloth.cu) compiled for compute capability
    `arch` (e.g. "80") with NVRTC or nvcc.

    `code` is "cubin" (for one device) or "ptx"; `defines` are kernel_defines(...) (or the VBD
    kernel's), so the cache holds one binary per specialisation. Needs no device:
    tests/test_cuda.py runs it on machines without a GPU.
    """
    # collide.cuh, collide_mesh.cuh and any other include put in on the host: NVRTC and nvcc's temporary
    # folder would not find kernels/
    source = resolve_includes(kernel_file, read_kernel(kernel_file), lambda line, _, name: f'#line {line} "{name}"')[0]
    options = (*compile_options(strict), *defines)
    if using == "nvrtc":
        from cupy_backends.cuda.libs import nvrtc

        archs = sorted(nvrtc.getSupportedArchs())
        supported = [a for a in archs if a <= int(arch)]
        if not supported:  # CUDA 13 dropped what is older than sm_75; CUDA 12 compiles sm_50 on
            major, minor = nvrtc.getVersion()
            raise ClothbenchError(
                f"NVRTC {major}.{minor} compiles for sm_{archs[0]} and newer, not this sm_{arch} device: "
                "use a CuPy and NVRTC of an older CUDA (pip install 'clothbench[cuda]' for CUDA 12)"
            )
        if code == "cubin" and supported[-1] != int(arch):
            code = "ptx"  # a device newer than this NVRTC: PTX, which the driver compiles
        target = f"sm_{supported[-1]}" if code == "cubin" else f"compute_{supported[-1]}"
        prog = nvrtc.createProgram(source, kernel_file, (), ())
        try:
            try:
                nvrtc.compileProgram(prog, (*options, f"--gpu-architecture={target}"))
            except nvrtc.NVRTCError:
                raise ClothbenchError(
                    f"NVRTC could not compile {kernel_file}: {nvrtc.getProgramLog(prog).strip()}"
                ) from None
            return nvrtc.getCUBIN(prog) if code == "cubin" else nvrtc.getPTX(prog)
        finally:
            nvrtc.destroyProgram(prog)
    if using == "nvcc":
        from cupy.cuda.compiler import CompileException, compile_using_nvcc

        try:
            options = tuple(_nvcc_escaped(o) for o in options)
            return compile_using_nvcc(source, options, arch=arch, filename=kernel_file, code_type=code)
        except CompileException as e:
            raise ClothbenchError(f"nvcc could not compile {kernel_file}: {e.get_message()}") from None
    raise ValueError(f"unknown CUDA compiler {using!r} (nvrtc or nvcc)")


# --- the backend ------------------------------------------------------------------


class CupyRuntime:
    """PingPong's runtime on a CUDA device: CuPy arrays, one stream, one RawKernel."""

    def __init__(self, kernel, stream):
        import cupy

        self.cupy = cupy
        self.kernel = kernel
        self.stream = stream

    def alloc(self, host: np.ndarray):
        with self.stream:
            return self.cupy.array(host)

    def upload(self, buffer, host: np.ndarray) -> None:
        buffer.set(host, stream=self.stream)

    def download(self, buffer) -> np.ndarray:
        return buffer.get(stream=self.stream)  # blocking: waits for the stream

    def copy(self, dst, src) -> None:
        rt = self.cupy.cuda.runtime
        rt.memcpyAsync(dst.data.ptr, src.data.ptr, src.nbytes, rt.memcpyDeviceToDevice, self.stream.ptr)

    def launch(self, grid: int, block: int, args: tuple, shared_bytes: int = 0) -> None:
        with self.stream:
            self.kernel((grid,), (block,), args, shared_mem=shared_bytes)


def shared_memory_limit(device: str | None) -> int:
    """The dynamic shared memory one block of CUDA device `device` (an index) may opt into;
    where no device answers (no cupy, no GPU), the least of any sm_80+ device."""
    try:
        import cupy

        props = cupy.cuda.runtime.getDeviceProperties(int(device or 0))
        return int(props["sharedMemPerBlockOptin"])
    except Exception:  # any failure to ask means: assume the smallest device
        return launch.SMALLEST_SHARED_OPTIN


class CudaDevice(Backend):
    """What each CUDA solver class shares: the --device it runs on, its module compiled for
    that device (kernels/`kernel_file`), one stream, and the CUDA events around every
    advance(). A subclass sets `self.state` (upload, advance, read: PingPong or the VBD launches)."""

    device_timer = "cuda-events"  # device_elapsed_ms: events around advance()'s launches (docs/timing.md)
    kernel_file = KERNEL_FILE

    def _open_device(self, options: BackendOptions, defines: tuple[str, ...]):
        """Select the device, compile `defines` for it; the loaded module."""
        import cupy

        self.state = self.stream = None
        self._binary_dir = None
        try:
            index = int(options.device or 0)
            if index < 0:
                raise ValueError(index)
            self._device = cupy.cuda.Device(index)
            self._device.use()
        except (ValueError, cupy.cuda.runtime.CUDARuntimeError):
            raise ClothbenchError(
                f"cuda --device must be a device index (0 .. {cupy.cuda.runtime.getDeviceCount() - 1}), "
                f"got {options.device!r}"
            ) from None
        rt = cupy.cuda.runtime
        props = rt.getDeviceProperties(index)
        self._name = props["name"].decode() if isinstance(props["name"], bytes) else str(props["name"])
        self.defines = defines
        module = self._load_module(options.strict, self._device.compute_capability, defines)
        # which CuPy (CUDA 12 or 13) and which compiler built the module: part of the tuning key
        self._driver = cuda_driver(cupy, self._compiler, self._name)
        self.stream = cupy.cuda.Stream(non_blocking=True)
        self._start, self._end = cupy.cuda.Event(), cupy.cuda.Event()
        self._timed = False
        return module

    tuning_steps = TUNING_STEPS  # steps a candidate shape is timed over

    def _shape_state(self, shape: str):
        """The device state (self.state's kind) that runs kernel shape `shape`."""
        raise NotImplementedError

    def _device_key(self) -> dict[str, str]:
        """What any CUDA solver's fastest shape depends on: the device and its software, the
        kernel's text (kernels/`kernel_file` and what it includes: an edit measures again), the
        grid and its colliders, the arithmetic and the local size; each solver adds its own."""
        o, s = self.options, self.scene
        return {
            "device": self._name,
            "driver": self._driver,
            "kernel": kernel_hash(self.kernel_file),
            "grid": str(s.grid),
            "colliders": f"{len(s.spheres)} spheres, {len(s.cylinders)} cylinders, {len(s.planes)} planes",
            "arithmetic": "strict" if o.strict else "fast",
            "local_size": str(o.local_size or "auto"),
            # only where the scene has them, so that a scene without them keeps its key
            **(
                {
                    "meshes": f"{sum(m.geometry.triangles for m in s.meshes)} triangles in {len(s.meshes)}, "
                    f"{self.mesh_collision}"
                }
                if s.meshes
                else {}
            ),
            **({"motion": "per-step poses"} if s.has_motion else {}),
            **({"boxes": str(len(s.boxes))} if s.boxes else {}),
        }

    def _time_shape(self, shape: str) -> float:
        """Device seconds a step of `shape`, from CUDA events around tuning_steps steps (the
        median of TUNING_REPEATS, after as many steps untimed), on the state the subclass
        makes for it (_shape_state)."""
        import cupy

        try:
            state = self._shape_state(shape)
            state.upload(*self.solver.initial_state(self.scene, np.float32))
            state.advance(self.tuning_steps)
            times = []
            for _ in range(TUNING_REPEATS):
                self._start.record(self.stream)
                state.advance(self.tuning_steps)
                self._end.record(self.stream)
                self._end.synchronize()
                times.append(cupy.cuda.get_elapsed_time(self._start, self._end) / 1e3 / self.tuning_steps)
        except ClothbenchError:
            raise
        except Exception as e:  # e.g. too many resources requested: this shape cannot run here
            raise ClothbenchError(f"cuda {shape}: {error_name(e)}") from None
        return statistics.median(times)

    def _check_local_size(self, kernel) -> None:
        limit = kernel.max_threads_per_block
        local_size = self.options.local_size
        if local_size is not None and local_size > limit:  # the base refused < 1
            raise ClothbenchError(f"cuda --local-size must be 1 .. {limit} here, got {local_size}")

    def _load_module(self, strict: bool, arch: str, defines: tuple[str, ...]):
        import cupy

        using = compiler()
        if using is None:
            raise ClothbenchError(f"no CUDA compiler ({install_hint(cuda_major(cupy))}, or put nvcc on PATH)")
        self._compiler = compiler_name(using)
        # RawModule loads from a file; keep it until close() in case CuPy reads it lazily
        self._binary_dir = tempfile.TemporaryDirectory(prefix="clothbench-cuda-")
        path = Path(self._binary_dir.name) / f"{Path(self.kernel_file).stem}.bin"  # cuModuleLoad tells cubin from PTX
        path.write_bytes(compile_kernel(strict, arch, using, "cubin", defines, self.kernel_file))
        return cupy.RawModule(path=str(path))

    @property
    def device(self) -> str:
        return self._name

    @property
    def driver(self) -> str:
        return self._driver

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.state.upload(pos, prev)

    def advance(self, steps: int) -> None:
        self._start.record(self.stream)
        self.state.advance(steps)
        self._end.record(self.stream)
        self._timed = True

    def synchronize(self) -> None:
        self.stream.synchronize()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state.read()

    def device_elapsed_ms(self) -> float | None:
        if not self._timed:
            return None
        import cupy

        self._end.synchronize()
        return float(cupy.cuda.get_elapsed_time(self._start, self._end))

    def close(self) -> None:
        if self.stream is not None:
            self.stream.synchronize()
        self.state = self.stream = None  # frees the device buffers
        if self._binary_dir is not None:
            self._binary_dir.cleanup()
            self._binary_dir = None


class CudaBackend(CudaDevice):
    name = "cuda"
    capabilities = Capabilities(
        transfers=TRANSFERS,
        local_size=True,
        generic=True,  # --generic: one program for every scene
        normals=True,
        device=True,  # --device: a CUDA device index
        shapes=True,  # block=N, steps/launch=K (launch.py)
        # meshes (kernels/collide_mesh.cuh) and per-step poses (launch.py: MotionTable), both kernels
        meshes=("verlet",),
        moving_colliders=("verlet",),
        boxes=("verlet",),  # collide_box, fixed and moving, both kernels
        self_collision=("verlet",),  # kernels/self_collision.cuh, after verlet_step (not verlet_steps)
        mesh_collisions=("accelerated", "naive"),
        sweep_variants=({"strict": True}, {"strict": False}, {"strict": False, "transfer": "copy"}),
    )

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        shapes = launch.kernel_shapes(scene.particles, options.local_size, shared_memory_limit(options.device))
        if scene.self_collision is not None:  # the pass runs between two steps: verlet_steps has no such launch
            return tuple(s for s in shapes if launch.parse_shape(s, scene.particles)[0] is None)
        return shapes

    def __init__(self, scene: Scene, solver: Solver, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.transfer = options.transfer or TRANSFERS[0]
        defines = kernel_defines(scene, solver, options.normals, options.generic, self.mesh_collision, self.transfer)
        module = self._open_device(options, defines)
        names = (launch.STEP_KERNEL, launch.STEPS_KERNEL, *(SELF_KERNELS if scene.self_collision is not None else ()))
        self._kernels = {name: module.get_function(name) for name in names}
        self._check_local_size(self._kernels[launch.STEP_KERNEL])
        self.state = self._pingpong(self.pick_shape(self._tuning_key(), self._time_shape))

    def _tuning_key(self) -> dict[str, str]:
        """What the fastest shape depends on: the device's key (CudaDevice._device_key, the
        kernel's text among it) and what else each launch does."""
        o, s = self.options, self.scene
        return {
            **self._device_key(),
            "generic": str(o.generic),
            "normals": str(o.normals),
            "transfer": self.transfer,
            **({"self_collision": "verlet_step and the pass"} if s.self_collision is not None else {}),
        }

    def _shape_state(self, shape: str) -> PingPong:
        return self._pingpong(shape)

    def _pingpong(self, shape: str) -> PingPong:
        """Device buffers and the kernel for one shape (launch.py)."""
        steps_per_launch, block = launch.parse_shape(shape, self.scene.particles, self.options.local_size)
        kernel = self._kernels[launch.STEP_KERNEL if steps_per_launch is None else launch.STEPS_KERNEL]
        if block > kernel.max_threads_per_block:
            raise ClothbenchError(f"cuda {shape}: {block} threads a block, at most {kernel.max_threads_per_block} here")
        self.effective_local_size = block
        contact = None
        if self.scene.self_collision is not None:
            contact = tuple(CupyRuntime(self._kernels[name], self.stream) for name in SELF_KERNELS)
        state = PingPong(
            CupyRuntime(kernel, self.stream),
            self.scene,
            self.solver,
            self.transfer,
            block,
            self.options.generic,
            self.options.normals,
            steps_per_launch,
            contact,
        )
        if state.shared_bytes:  # above 48 KiB a kernel must opt in, up to the device's limit
            kernel.max_dynamic_shared_size_bytes = state.shared_bytes
        return state

    def read_normals(self) -> np.ndarray | None:
        """Normals of the positions the last step read (read()[1]), see docs/normals.md."""
        return self.state.read_normals()
