"""CuPy and its CUDA toolchain as found here: the NVRTC/nvcc probes, the version names, and
the install hints; separate from verlet.py, which builds and runs the kernels with them.

cupy is imported only inside functions, as in verlet.py: importing this module never needs it.
"""

from __future__ import annotations

import re
import shlex
import subprocess
from functools import lru_cache

from clothbench.environment import CUPY_PACKAGES  # noqa: F401 (cuda/verlet.py takes it from here with the rest)

# The extra that installs CuPy and NVRTC for each CUDA major (pyproject.toml)
EXTRAS = {12: "cuda", 13: "cuda13"}
INSTALL_HINT = "cupy not installed (pip install 'clothbench[cuda]' for CUDA 12, 'clothbench[cuda13]' for CUDA 13)"


def version_string(number: int) -> str:
    """13020 -> '13.2', as CUDA encodes its versions (1000 major + 10 minor)."""
    return f"{number // 1000}.{number % 1000 // 10}"


def error_name(e: BaseException) -> str:
    """'cudaErrorInsufficientDriver' from 'cudaErrorInsufficientDriver: CUDA driver ...'."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return text.split(":", 1)[0].strip() or type(e).__name__


def nvrtc_available() -> bool:
    try:
        from cupy_backends.cuda.libs import nvrtc

        nvrtc.getVersion()  # loads libnvrtc (the extra's nvidia-cuda-nvrtc wheel or a toolkit)
        return True
    except Exception:
        return False


def nvcc_available() -> bool:
    try:
        from cupy.cuda import get_nvcc_path  # the nvcc compile_using_nvcc will run

        return get_nvcc_path() is not None
    except Exception:
        return False


def compiler() -> str | None:
    """'nvrtc' where libnvrtc loads, else 'nvcc' where CuPy finds it, else None."""
    if nvrtc_available():
        return "nvrtc"
    return "nvcc" if nvcc_available() else None


def installed_version(package: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def cuda_major(cupy) -> int | None:
    """The CUDA major CuPy was built for (its runtime's), or None where it does not say."""
    try:
        return int(cupy.cuda.runtime.runtimeGetVersion()) // 1000
    except Exception:  # a CuPy too broken to answer: the reason says what else it found
        return None


@lru_cache(maxsize=None)
def _nvcc_release(command: str) -> str:
    """'13.0' from `nvcc --version` ('release 13.0, V13.0.88'), or '' where it does not say."""
    try:
        done = subprocess.run([*shlex.split(command), "--version"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return ""
    match = re.search(r"release (\d+\.\d+)", done.stdout)
    return match[1] if match else ""


def compiler_name(using: str | None) -> str:
    """'NVRTC 13.2' or 'nvcc 13.0 (/usr/local/cuda/bin/nvcc)': the compiler `using` names, as found."""
    if using == "nvrtc":
        from cupy_backends.cuda.libs import nvrtc

        major, minor = nvrtc.getVersion()
        return f"NVRTC {major}.{minor}"
    if using == "nvcc":
        from cupy.cuda import get_nvcc_path

        command = get_nvcc_path()
        release = _nvcc_release(command) if command else ""
        return f"nvcc {release} ({command})" if release else f"nvcc ({command or 'not found'})"
    return str(using)


def install_hint(major: int | None) -> str:
    """How to install NVRTC for CuPy's CUDA major: the extra that pins it."""
    extra = EXTRAS.get(major)
    return f"pip install 'clothbench[{extra}]' for NVRTC" if extra else "install NVRTC of CuPy's CUDA major"


def driver_note(cupy, major: int | None) -> str:
    """'; the NVIDIA driver supports CUDA 12.4: pip install ...' where the driver is older than
    CuPy's CUDA, '' where it answers nothing (no driver at all) or is new enough."""
    try:
        driver = int(cupy.cuda.runtime.driverGetVersion())
    except Exception:
        return ""
    if driver <= 0 or major is None or driver // 1000 >= major:
        return ""
    extra = EXTRAS.get(driver // 1000)
    fix = f": use cupy-cuda{driver // 1000}x (pip install 'clothbench[{extra}]')" if extra else ""
    return f"; the NVIDIA driver supports CUDA {version_string(driver)}{fix}"
