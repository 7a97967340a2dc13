"""CUDA: kernels/verlet_cloth.cu through CuPy, the chapter's section 22.7.

Host code only; the step itself is docs/semantics.md, performed by the kernel. The chapter
keeps two pairs of device buffers, (pos, pos_prev) x (in, out), and copies each output to
its input with cudaMemcpyDeviceToDevice after every step; `--transfer copy` does exactly
that, and the default `swap` exchanges the pointers instead, so the harness shows what the
copy costs. `PingPong` holds that logic once, written against a small runtime (allocate,
copy, launch), so the CPU build of the same kernel (tests/test_cuda.py, through shim/ beside
this module) is driven with the same argument list, launch geometry and swap.

Specialisation: by default the kernel is built for the scene and solver, its constants and
colliders compile-time constants (exact float literals in -D defines) and the code of a
collider kind the scene lacks left out; `--generic` builds the one kernel that takes them all
as arguments. `kernel_defines` gives the -D switches, and compiled kernels are cached by them.

Compilation: we compile the kernel ourselves (NVRTC through CuPy's binding, or nvcc) and
load the binary with RawModule(path=...). CuPy's own RawModule(code=...) path appends
`-ftz=true`, flushing denormals that NumPy keeps, which `--strict` cannot allow.

cupy is an optional extra and is imported only inside functions: importing this module
never needs it, and probe() says how to install it.
"""

from __future__ import annotations

import math
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.kernel_source import c_float, read_kernel
from clothbench.scene import Scene
from clothbench.solver import Solver
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import ROWS_PER_COLLIDER, VerletConstants, collider_rows

KERNEL_FILE = "verlet_cloth.cu"
KERNEL_NAME = "verlet_step"
TRANSFERS = ("swap", "copy")  # the first is the default
AUTO_BLOCK = 256  # threads per block when --local-size is not given
INSTALL_HINT = "cupy not installed (pip install 'clothbench[cuda]')"
NO_COMPILER = "no CUDA compiler (pip install 'clothbench[cuda]' for NVRTC, or put nvcc on PATH)"


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


def kernel_constants(scene: Scene, solver: Solver) -> dict[str, object]:
    """The step's constants (kernel_inputs.VerletConstants), in kernel parameter order."""
    c = VerletConstants.of(scene, solver)
    (gx, gy, gz), (structural, shear, bend) = c.g, c.rest
    return {
        "n": np.int32(scene.grid),
        "dt": c.dt, "dt2": c.dt2, "k": c.k, "b": c.b,
        "gx": gx, "gy": gy, "gz": gz,
        "rest_structural": structural, "rest_shear": shear, "rest_bend": bend,
    }  # fmt: skip


def kernel_defines(
    scene: Scene, solver: Solver, normals: bool = False, generic: bool = False
) -> tuple[str, ...]:
    """The -D switches that build verlet_cloth.cu for this scene and solver: the
    specialisation key.

    Generic: only CLOTH_GENERIC (and CLOTH_NORMALS), so every scene shares one kernel.
    Specialised: the constants as exact float literals, the collider counts, and the
    colliders of each kind the scene has as a brace list of float4 rows.
    """
    defines = ["-DCLOTH_NORMALS"] if normals else []
    if generic:
        return (*defines, "-DCLOTH_GENERIC")
    for name, value in kernel_constants(scene, solver).items():
        literal = str(value) if name == "n" else c_float(value)
        defines.append(f"-DCLOTH_{name.upper()}={literal}")
    for kind, rows in collider_rows(scene).items():
        singular = kind[:-1].upper()
        defines.append(f"-DCLOTH_{singular}_COUNT={len(rows) // ROWS_PER_COLLIDER[kind]}")
        if len(rows):
            items = ",".join("{" + ",".join(c_float(v) for v in row) + "}" for row in rows)
            defines.append(f"-DCLOTH_{kind.upper()}={{{items}}}")
    return tuple(defines)


# --- availability ---------------------------------------------------------------------


def _short(e: BaseException) -> str:
    """'cudaErrorInsufficientDriver' from 'cudaErrorInsufficientDriver: CUDA driver ...'."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return text.split(":", 1)[0].strip() or type(e).__name__


def _nvrtc_available() -> bool:
    try:
        from cupy_backends.cuda.libs import nvrtc

        nvrtc.getVersion()  # loads libnvrtc (the nvidia-cuda-nvrtc-cu12 wheel or a toolkit)
        return True
    except Exception:
        return False


def _nvcc_available() -> bool:
    try:
        from cupy.cuda import get_nvcc_path  # the nvcc compile_using_nvcc will run

        return get_nvcc_path() is not None
    except Exception:
        return False


def compiler() -> str | None:
    """'nvrtc' where libnvrtc loads, else 'nvcc' where CuPy finds it, else None."""
    if _nvrtc_available():
        return "nvrtc"
    return "nvcc" if _nvcc_available() else None


def probe() -> Availability:
    try:
        import cupy
    except ImportError:
        return Availability(False, INSTALL_HINT)
    except Exception as e:  # installed but broken, e.g. built against another numpy
        return Availability(False, f"cupy failed to import: {type(e).__name__}: {_short(e)}")
    try:
        count = cupy.cuda.runtime.getDeviceCount()
    except Exception as e:  # no driver: cudaErrorInsufficientDriver / cudaErrorNoDevice
        return Availability(False, f"no CUDA device (cupy: {_short(e)})")
    if count < 1:
        return Availability(False, "no CUDA device (cupy: 0 devices)")
    if compiler() is None:
        return Availability(False, NO_COMPILER)
    name = cupy.cuda.runtime.getDeviceProperties(0)["name"]
    return Availability(True, device=name.decode() if isinstance(name, bytes) else str(name))


# --- compilation ----------------------------------------------------------------------


def _nvcc_escaped(option: str) -> str:
    """nvcc splits an option's value at commas (-D a,b defines a and b); '\\,' keeps one."""
    return option.replace(",", "\\,") if option.startswith("-D") else option


@lru_cache(maxsize=64)
def compile_kernel(
    strict: bool, arch: str, using: str, code: str = "cubin", defines: tuple[str, ...] = ()
) -> bytes:
    """verlet_cloth.cu compiled for compute capability `arch` (e.g. "80") with NVRTC or nvcc.

    `code` is "cubin" (for one device) or "ptx"; `defines` are kernel_defines(...), so the
    cache holds one binary per specialisation. Needs no device: tests/test_cuda.py runs it
    on machines without a GPU.
    """
    source = read_kernel(KERNEL_FILE)
    options = (*compile_options(strict), *defines)
    if using == "nvrtc":
        from cupy_backends.cuda.libs import nvrtc

        supported = [a for a in nvrtc.getSupportedArchs() if a <= int(arch)]
        if not supported:
            raise ClothbenchError(f"NVRTC cannot compile for sm_{arch}")
        if code == "cubin" and supported[-1] != int(arch):
            code = "ptx"  # a device newer than this NVRTC: PTX, which the driver compiles
        target = f"sm_{supported[-1]}" if code == "cubin" else f"compute_{supported[-1]}"
        prog = nvrtc.createProgram(source, KERNEL_FILE, (), ())
        try:
            try:
                nvrtc.compileProgram(prog, (*options, f"--gpu-architecture={target}"))
            except nvrtc.NVRTCError:
                raise ClothbenchError(
                    f"NVRTC could not compile {KERNEL_FILE}: {nvrtc.getProgramLog(prog).strip()}"
                ) from None
            return nvrtc.getCUBIN(prog) if code == "cubin" else nvrtc.getPTX(prog)
        finally:
            nvrtc.destroyProgram(prog)
    if using == "nvcc":
        from cupy.cuda.compiler import CompileException, compile_using_nvcc

        try:
            options = tuple(_nvcc_escaped(o) for o in options)
            return compile_using_nvcc(source, options, arch=arch, filename=KERNEL_FILE, code_type=code)
        except CompileException as e:
            raise ClothbenchError(f"nvcc could not compile {KERNEL_FILE}: {e.get_message()}") from None
    raise ValueError(f"unknown CUDA compiler {using!r} (nvrtc or nvcc)")


# --- the ping-pong, shared by the CuPy backend and the CPU build in the tests ----------


class PingPong:
    """The chapter's two pairs of buffers and one step on them, for any runtime that has

        alloc(host array) -> buffer       upload(buffer, host array)   download(buffer) -> array
        copy(dst, src)  (device to device)       launch(grid, block, args)

    CudaBackend's runtime is CuPy; tests/test_cuda.py's is the CPU build of the same
    kernel, so both launch it with the argument list built here, in this order. `generic`
    and `normals` must be those the kernel was built with (kernel_defines).
    """

    def __init__(
        self,
        runtime,
        scene: Scene,
        solver: Solver,
        transfer: str = TRANSFERS[0],
        block: int = AUTO_BLOCK,
        generic: bool = False,
        normals: bool = False,
    ):
        if transfer not in TRANSFERS:
            raise ValueError(f"transfer must be swap or copy, got {transfer!r}")
        self.runtime = runtime
        self.transfer = transfer
        self.block = block
        self.grid = math.ceil(scene.particles / block)  # blocks; the last may run past n*n
        self.scene_args: tuple = ()  # the specialised kernel has the scene compiled in
        if generic:
            colliders = []
            for kind, rows in collider_rows(scene).items():
                # never a zero-size buffer: its pointer is passed even when no collider is read
                buffer = runtime.alloc(rows if len(rows) else np.zeros((1, 4), np.float32))
                colliders += [buffer, np.int32(len(rows) // ROWS_PER_COLLIDER[kind])]
            self.scene_args = (*kernel_constants(scene, solver).values(), *colliders)
        empty = np.zeros((scene.particles, 4), dtype=np.float32)
        self.pos_in, self.prev_in = runtime.alloc(empty), runtime.alloc(empty)
        self.pos_out, self.prev_out = runtime.alloc(empty), runtime.alloc(empty)
        self.normals = runtime.alloc(empty) if normals else None  # written, never read back in
        self.has_normals = False  # whether the last step since upload() wrote them

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.runtime.upload(self.pos_in, np.ascontiguousarray(pos, dtype=np.float32))
        self.runtime.upload(self.prev_in, np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False

    def args(self) -> tuple:
        """The kernel's arguments, in verlet_step's parameter order."""
        buffers = (self.pos_in, self.prev_in, self.pos_out, self.prev_out)
        if self.normals is not None:
            buffers += (self.normals,)
        return (*buffers, *self.scene_args)

    def step(self) -> None:
        self.runtime.launch(self.grid, self.block, self.args())
        if self.transfer == "copy":  # the chapter: cudaMemcpy(in, out, DeviceToDevice)
            self.runtime.copy(self.pos_in, self.pos_out)
            self.runtime.copy(self.prev_in, self.prev_out)
        else:  # the output becomes the next input: swap the pointers, move no data
            self.pos_in, self.pos_out = self.pos_out, self.pos_in
            self.prev_in, self.prev_out = self.prev_out, self.prev_in
        self.has_normals = self.normals is not None

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) after the last step: always the input pair, whichever the transfer."""
        return self.runtime.download(self.pos_in), self.runtime.download(self.prev_in)

    def read_normals(self) -> np.ndarray | None:
        """The normals of read()[1], x(t) of the last step; None before a step or unasked."""
        return self.runtime.download(self.normals) if self.has_normals else None


class _CupyRuntime:
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

    def launch(self, grid: int, block: int, args: tuple) -> None:
        with self.stream:
            self.kernel((grid,), (block,), args)


class CudaBackend(Backend):
    name = "cuda"
    capabilities = Capabilities(
        transfers=TRANSFERS,
        local_size=True,
        generic=True,  # --generic: one program for every scene
        normals=True,
        device=True,  # --device: a CUDA device index
        sweep_variants=({"strict": True}, {"strict": False}, {"strict": False, "transfer": "copy"}),
    )

    def __init__(self, scene: Scene, solver: Solver, options: BackendOptions):
        super().__init__(scene, solver, options)
        transfer = options.transfer or TRANSFERS[0]
        block = options.local_size or AUTO_BLOCK
        self.effective_local_size = block
        import cupy

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
        props = cupy.cuda.runtime.getDeviceProperties(index)
        self._name = props["name"].decode() if isinstance(props["name"], bytes) else str(props["name"])
        self._binary_dir = None
        self.defines = kernel_defines(scene, solver, options.normals, options.generic)
        kernel = self._load_kernel(options.strict, self._device.compute_capability, self.defines)
        if block > kernel.max_threads_per_block:  # the base refused < 1; the limit is the device's
            raise ClothbenchError(
                f"cuda --local-size must be 1 .. {kernel.max_threads_per_block} here, got {block}"
            )
        self.stream = cupy.cuda.Stream(non_blocking=True)
        self._start, self._end = cupy.cuda.Event(), cupy.cuda.Event()
        self._timed = False
        runtime = _CupyRuntime(kernel, self.stream)
        self.state = PingPong(runtime, scene, solver, transfer, block, options.generic, options.normals)

    def _load_kernel(self, strict: bool, arch: str, defines: tuple[str, ...]):
        import cupy

        using = compiler()
        if using is None:
            raise ClothbenchError(NO_COMPILER)
        # RawModule loads from a file; keep it until close() in case CuPy reads it lazily
        self._binary_dir = tempfile.TemporaryDirectory(prefix="clothbench-cuda-")
        path = Path(self._binary_dir.name) / "verlet_cloth.bin"  # cuModuleLoad tells cubin from PTX
        path.write_bytes(compile_kernel(strict, arch, using, "cubin", defines))
        return cupy.RawModule(path=str(path)).get_function(KERNEL_NAME)

    @property
    def device(self) -> str:
        return self._name

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.state.upload(pos, prev)

    def advance(self, steps: int) -> None:
        self._start.record(self.stream)
        for _ in range(steps):
            self.state.step()
        self._end.record(self.stream)
        self._timed = True

    def synchronize(self) -> None:
        self.stream.synchronize()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.state.read()

    def read_normals(self) -> np.ndarray | None:
        """Normals of the positions the last step read (read()[1]), see docs/normals.md."""
        return self.state.read_normals()

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
