"""Finding the kernel sources in kernels/, from a checkout or from an installed wheel.

The wheel carries kernels/ as clothbench/kernels (see pyproject.toml); a checkout or an
editable install reads the top-level kernels/ folder beside the package.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from .errors import ClothbenchError

_REPO_KERNELS = Path(__file__).resolve().parent.parent / "kernels"


def kernel_path(filename: str) -> Path:
    installed = Path(str(resources.files("clothbench") / "kernels" / filename))
    for path in (installed, _REPO_KERNELS / filename):
        if path.is_file():
            return path
    raise ClothbenchError(
        f"kernel source {filename} not found (looked in {installed.parent} and {_REPO_KERNELS}); "
        "reinstall clothbench"
    )


def read_kernel(filename: str) -> str:
    return kernel_path(filename).read_text()


def c_float(x) -> str:
    """An exact C/OpenCL/CUDA float literal (hexadecimal), e.g. for -D build options."""
    return float.hex(float(np.float32(x))) + "f"


def glsl_float(x) -> str:
    """An exact GLSL float literal: the bit pattern, since GLSL has no hexadecimal floats."""
    bits = int(np.float32(x).view(np.uint32))
    return f"uintBitsToFloat(0x{bits:08x}u)"
