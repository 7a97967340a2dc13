"""kernels/verlet_cloth.cu built for the CPU through shim/ (g++), and PingPong's runtime on it.

What proves the CUDA kernels on a machine without a GPU (tests/test_cuda.py,
tests/test_cuda_multistep.py): the unmodified .cu with -include shim/shim.h, the -D switches of
the GPU build, and shim/verlet_cloth_cpu.cpp's C entry points, which take cuLaunchKernel's
argument form. `ShimRuntime` launches one of its kernels with the argument list, launch geometry
and dynamic shared memory PingPong gives a CuPy kernel, after checking the argument types
against the kernel's signature (a real launch would reinterpret mismatched bytes silently).

Libraries are cached on disk (clothbench.native.cache_dir("cuda_shim")) by the sources, the
flags and g++'s version line.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.kernel_source import kernel_path, resolve_includes
from clothbench.native import cache_dir

SHIM = Path(__file__).parent / "shim"
# -ffp-contract=off and no -march=native: g++ would otherwise fuse a*b+c, and strict is only
# bit-exact with NumPy when every operation is rounded on its own (shim.h)
GXX_FLAGS = ("-std=c++17", "-O2", "-ffp-contract=off", "-Wall", "-Wextra", "-Wno-unknown-pragmas")
STATUS = {
    -1: "the argument count differs from the kernel's",
    -2: "__syncthreads() in a kernel exported without barriers",
    -3: "a barrier that some threads of the block never reach",
    -4: "more dynamic shared memory than the shim holds",
}


def gxx() -> str | None:
    return shutil.which(os.environ.get("CXX") or "g++")


@lru_cache(maxsize=None)
def _gxx_version(path: str) -> str:
    return subprocess.run([path, "--version"], capture_output=True, text=True, timeout=60).stdout.split("\n")[0]


@lru_cache(maxsize=64)
def build(strict: bool, defines: tuple[str, ...]) -> ctypes.CDLL:
    """The CPU build of verlet_cloth.cu with these switches (verlet.kernel_defines), loaded.
    Any compiler output (a warning) is an error: the tests hold the source to that."""
    compiler = gxx()
    if compiler is None:
        raise ClothbenchError("g++ not found: cannot build the CPU shim of the CUDA kernel")
    kernel = kernel_path("verlet_cloth.cu")
    # every file the build reads: the kernel, the headers it includes, the shim
    included = resolve_includes(kernel.name, kernel.read_text(), lambda *_: "")[1][1:]
    sources = [kernel, *map(kernel_path, included), SHIM / "shim.h", SHIM / "verlet_cloth_cpu.cpp"]
    flags = (*GXX_FLAGS, *(["-DCLOTH_STRICT"] if strict else []), *defines)
    text = "\0".join([*(p.read_text() for p in sources), *flags, _gxx_version(compiler)])
    library = cache_dir("cuda_shim") / f"verlet_cloth-{hashlib.sha256(text.encode()).hexdigest()[:20]}.so"
    if not library.exists():
        with tempfile.TemporaryDirectory(prefix="clothbench-shim-") as tmp:
            built = Path(tmp, "out.so")
            cmd = [compiler, *flags, "-fPIC", "-shared", "-include", str(SHIM / "shim.h"), "-I", str(kernel.parent),
                   str(SHIM / "verlet_cloth_cpu.cpp"), "-o", str(built)]  # fmt: skip
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
            if done.returncode != 0 or done.stderr.strip():
                lines = done.stderr.strip().splitlines()
                first = next(
                    (line for line in lines if "error" in line or "warning" in line), lines[0] if lines else "?"
                )
                raise ClothbenchError(f"g++ could not build the CUDA shim cleanly: {first}")
            fd, partial = tempfile.mkstemp(dir=library.parent, suffix=".so.partial")
            os.close(fd)
            shutil.copyfile(built, partial)
            os.replace(partial, library)  # atomic: concurrent builds leave one whole file
    return ctypes.CDLL(str(library))


class ShimRuntime:
    """PingPong's runtime (alloc, upload, download, copy, launch) on the CPU: NumPy arrays as
    device buffers (float32, or int32 for an int buffer, uint64 for cell ids), one kernel of a
    `build` library ("verlet_step", "verlet_steps", or one of the self-collision pass's)."""

    CODES = ((np.float32, "f"), (np.int32, "i"))
    BUFFER_CODES = {np.dtype(np.int32): "q", np.dtype(np.uint64): "k"}  # any other: float32, "p"

    def __init__(self, lib: ctypes.CDLL, kernel: str = "verlet_step"):
        self.lib = lib
        self.kernel = kernel
        self._launch = getattr(lib, f"{kernel}_launch")
        self._launch.argtypes = [
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.c_uint,
            ctypes.POINTER(ctypes.c_void_p),
            ctypes.c_int,
        ]
        self._launch.restype = ctypes.c_int
        signature = getattr(lib, f"{kernel}_signature")
        signature.restype = ctypes.c_char_p
        self.signature = signature().decode()
        self.launches = 0
        self.shared_bytes: list[int] = []  # per launch

    def schedule(self, seed: int) -> None:
        """The order a block's threads run in between barriers (verlet_steps): 0 in order."""
        schedule = getattr(self.lib, f"{self.kernel}_schedule")
        schedule.argtypes = [ctypes.c_ulonglong]
        schedule(seed)

    def alloc(self, host):
        dtype = np.asarray(host).dtype
        dtype = dtype if dtype in self.BUFFER_CODES else np.float32
        return np.array(host, dtype=dtype, order="C", copy=True)

    def upload(self, buffer, host):
        np.copyto(buffer, host)

    def download(self, buffer):
        return buffer.copy()

    def copy(self, dst, src):
        np.copyto(dst, src)

    def launch(self, grid: int, block: int, args: tuple, shared_bytes: int = 0) -> None:
        # CuPy would pass a Python float as a double: only exact types may reach the kernel
        codes = "".join(self.code(a) for a in args)
        if codes != self.signature:
            raise TypeError(f"arguments {codes} != kernel parameters {self.signature}")
        values = []
        for a in args:
            if isinstance(a, np.ndarray):
                if a.dtype not in (np.float32, *self.BUFFER_CODES) or not a.flags.c_contiguous:
                    raise TypeError("a buffer must be C-contiguous float32 (or int32, uint64 for those buffers)")
                values.append(ctypes.c_void_p(a.ctypes.data))
            elif isinstance(a, np.float32):
                values.append(ctypes.c_float(a))
            else:
                values.append(ctypes.c_int32(a))
        params = (ctypes.c_void_p * len(values))(*(ctypes.cast(ctypes.pointer(v), ctypes.c_void_p) for v in values))
        status = self._launch(grid, block, shared_bytes, params, len(values))
        if status != 0:
            raise RuntimeError(f"{self.kernel} launch failed: {STATUS.get(status, status)}")
        self.launches += 1
        self.shared_bytes.append(shared_bytes)

    @classmethod
    def code(cls, a) -> str:
        """The shim's type letter of one argument (shim.h: type_code): 'q' an int buffer, 'k' a
        uint64 one, 'p' any other buffer, 'f' float32, 'i' int32."""
        if isinstance(a, np.ndarray):
            return cls.BUFFER_CODES.get(a.dtype, "p")
        return next((c for t, c in cls.CODES if isinstance(a, t)), "?")
