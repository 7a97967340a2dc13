"""The backend registry: every backend by name, whether it can run here, and why not.

Each backend is one module in this folder exposing `probe() -> Availability` (cheap, never
raises) and a `Backend` subclass named in BACKENDS. Modules are imported only when asked
for, so a missing optional package costs nothing until its backend is used.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache

from ..errors import BackendUnavailable, ClothbenchError
from ..scene import Scene
from .base import Availability, Backend, BackendOptions


@dataclass(frozen=True)
class BackendEntry:
    name: str
    module: str
    cls: str
    peer: bool = False  # a system users would pick instead of clothbench (not ours)
    summary: str = ""
    pbd: tuple[str, str] | None = None  # (module, class) of its PBD solver, if it has one


BACKENDS: dict[str, BackendEntry] = {
    e.name: e
    for e in (
        BackendEntry(
            "numpy",
            "numpy",
            "NumpyBackend",
            summary="vectorised NumPy reference (CPU)",
            pbd=("numpy_pbd", "NumpyPbdBackend"),
        ),
        BackendEntry(
            "opencl",
            "opencl",
            "OpenCLBackend",
            summary="OpenCL kernel via pyopencl",
            pbd=("opencl_pbd", "OpenCLPbdBackend"),
        ),
        BackendEntry("glsl", "glsl", "GLSLBackend", summary="GLSL fragment shader, FBO ping-pong"),
        BackendEntry(
            "glsl-compute",
            "glsl_compute",
            "GLSLComputeBackend",
            summary="GLSL compute shader",
            pbd=("glsl_compute_pbd", "GLSLComputePbdBackend"),
        ),
        BackendEntry("cuda", "cuda", "CudaBackend", summary="CUDA kernel via CuPy RawKernel"),
        BackendEntry("taichi", "taichi", "TaichiBackend", peer=True, summary="Taichi (peer)"),
        BackendEntry("warp", "warp", "WarpBackend", peer=True, summary="NVIDIA Warp (peer)"),
        BackendEntry("numba", "numba", "NumbaBackend", peer=True, summary="Numba (peer)"),
    )
}

OWN_BACKENDS = [name for name, e in BACKENDS.items() if not e.peer]


def _module(name: str, module: str | None = None):
    full = f"{__name__}.{module or BACKENDS[name].module}"
    try:
        return importlib.import_module(full)
    except ModuleNotFoundError as e:
        if e.name == full:
            return None  # the backend's own file does not exist yet
        raise


def check_name(name: str) -> BackendEntry:
    if name not in BACKENDS:
        raise ClothbenchError(f"unknown backend {name!r} (known: {', '.join(BACKENDS)})")
    return BACKENDS[name]


@lru_cache(maxsize=None)
def availability(name: str) -> Availability:
    """Can `name` run on this machine? Never raises for a known backend."""
    check_name(name)
    module = _module(name)
    if module is None:
        return Availability(False, "not implemented yet")
    try:
        return module.probe()
    except Exception as e:  # a probe must not take the whole CLI down
        return Availability(False, f"probe failed: {type(e).__name__}: {e}")


def backend_class(name: str, solver: str = "verlet") -> type[Backend] | None:
    """The Backend subclass for `name` and `solver`, or None where there is none yet."""
    entry = check_name(name)
    module_name, cls = entry.module, entry.cls
    if solver == "pbd":
        if entry.pbd is None:
            return None
        module_name, cls = entry.pbd
    module = _module(name, module_name)
    return getattr(module, cls) if module is not None else None


def pbd_backends() -> list[str]:
    return [name for name in BACKENDS if backend_class(name, "pbd") is not None]


def create_backend(name: str, scene: Scene, options: BackendOptions | None = None) -> Backend:
    """A ready backend for `scene`, or BackendUnavailable saying why not."""
    options = options or BackendOptions()
    check_name(name)
    avail = availability(name)
    if not avail.usable:
        raise BackendUnavailable(name, avail.reason)
    cls = backend_class(name, scene.solver)
    if cls is None:
        raise ClothbenchError(
            f"{name} has no {scene.solver} solver (it runs on: {', '.join(pbd_backends())})"
        )
    return cls(scene, options)


def resolve_names(spec: str, include_peers: bool = True) -> list[str]:
    """'all' or a comma-separated list of names, checked."""
    if spec.strip() == "all":
        return [n for n, e in BACKENDS.items() if include_peers or not e.peer]
    names = [s.strip() for s in spec.split(",") if s.strip()]
    if not names:
        raise ClothbenchError("no backend named (give e.g. --backends numpy,opencl or all)")
    for n in names:
        check_name(n)
    return names


__all__ = [
    "Availability",
    "Backend",
    "BackendOptions",
    "BACKENDS",
    "OWN_BACKENDS",
    "availability",
    "backend_class",
    "pbd_backends",
    "create_backend",
    "resolve_names",
]
