"""Native code built at first use: a C file of kernels/ compiled with the system's C compiler
into a shared library, cached on disk by what changes the machine code (the source with its
includes, the flags, the compiler's own version line, the CPU it is built for), and loaded
with ctypes.

Used by the `c` backend (kernels/verlet_cloth.c) and the machine-bound measurement
(kernels/machine_bounds.c). No compiler: `compiler()` says so in one line, and the callers
turn that into a skip with the reason.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from clothbench.errors import ClothbenchError
from clothbench.kernel_source import kernel_path, read_kernel, resolve_includes

CACHE_ENV = "CLOTHBENCH_CACHE"  # where built libraries and tuning results live
COMPILER_ENV = "CC"  # the compiler to use, as make's convention


def cache_dir(*parts: str) -> Path:
    """clothbench's cache folder (CLOTHBENCH_CACHE, else $XDG_CACHE_HOME/clothbench, else
    ~/.cache/clothbench), with `parts` below it, created."""
    root = os.environ.get(CACHE_ENV) or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "clothbench"
    )
    path = Path(root, *parts)
    path.mkdir(parents=True, exist_ok=True)
    return path


@dataclass(frozen=True)
class Compiler:
    path: str
    version: str  # the first line of `cc --version`: part of every cache key


@lru_cache(maxsize=None)
def compiler() -> Compiler | None:
    """The C compiler ($CC, else cc, gcc, clang on PATH) that can build with OpenMP, or None."""
    names = [os.environ[COMPILER_ENV]] if os.environ.get(COMPILER_ENV) else ["cc", "gcc", "clang"]
    for name in names:
        path = shutil.which(name)
        if path is None:
            continue
        try:
            out = subprocess.run([path, "--version"], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.SubprocessError):
            continue
        if out.returncode == 0 and out.stdout:
            return Compiler(path, out.stdout.splitlines()[0].strip())
    return None


def no_compiler_reason() -> str:
    wanted = os.environ.get(COMPILER_ENV) or "cc, gcc or clang"
    return f"no C compiler found ({wanted}; Debian: apt-get install gcc)"


@lru_cache(maxsize=1)
def cpu_identity() -> str:
    """The CPU's model and feature flags: -march=native makes code for this CPU, so a cache
    shared between machines (a home folder on several) must not hand one's build to another."""
    text = ""
    try:
        with open("/proc/cpuinfo") as f:
            text = "".join(line for line in f if line.startswith(("model name", "flags", "Features")))
    except OSError:
        import platform

        text = platform.processor() or platform.machine()
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def build_library(filename: str, flags: tuple[str, ...]) -> ctypes.CDLL:
    """kernels/`filename` built with `flags` into a shared library and loaded: from the cache
    when this source, these flags and this compiler built it before. A compile error becomes
    one ClothbenchError with the compiler's first error line."""
    cc = compiler()
    if cc is None:
        raise ClothbenchError(no_compiler_reason())
    source = resolve_includes(filename, read_kernel(filename), lambda line, _, name: f'#line {line} "{name}"')[0]
    key = hashlib.sha256("\0".join((source, *flags, cc.path, cc.version, cpu_identity())).encode()).hexdigest()[:20]
    stem = Path(filename).stem
    library = cache_dir("native") / f"{stem}-{key}.so"
    if not library.exists():
        _compile(cc, filename, source, flags, library)
    return ctypes.CDLL(str(library))


def _compile(cc: Compiler, filename: str, source: str, flags: tuple[str, ...], library: Path) -> None:
    with tempfile.TemporaryDirectory(prefix="clothbench-cc-") as tmp:
        src = Path(tmp, Path(filename).name)
        src.write_text(source)
        built = Path(tmp, "out.so")
        command = [
            cc.path,
            *flags,
            "-shared",
            "-fPIC",
            "-I",
            str(kernel_path(filename).parent),
            str(src),
            "-o",
            str(built),
            "-lm",
        ]
        out = subprocess.run(command, capture_output=True, text=True, timeout=300)
        if out.returncode != 0:
            errors = [line for line in out.stderr.splitlines() if "error" in line] or out.stderr.splitlines() or ["?"]
            raise ClothbenchError(f"{Path(cc.path).name} could not build kernels/{filename}: {errors[0].strip()}")
        # atomic: a concurrent build of the same key (two sweep workers) leaves one whole file
        fd, partial = tempfile.mkstemp(dir=library.parent, suffix=".so.partial")
        os.close(fd)
        shutil.copyfile(built, partial)
        os.replace(partial, library)
