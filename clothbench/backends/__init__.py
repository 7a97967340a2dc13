"""The backend registry: every backend by name, whether it can run here, and why not.

Each backend is a module exposing `probe() -> Availability` (cheap, never raises) and one
`Backend` subclass per solver it implements, named here as "module:Class". Modules are
imported only when asked for, so a missing optional package costs nothing until its backend
is used. Options are checked against the class's declared Capabilities before it is built.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache

from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.scene import Scene
from clothbench.solver import SOLVERS, Solver
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities


@dataclass(frozen=True)
class BackendEntry:
    name: str
    verlet: str | None  # "module:Class" of its Verlet backend (None: PBD only); the module's probe() says if it runs
    pbd: str | None = None  # "module:Class" of its PBD backend, if it has one
    peer: bool = False  # a system users would pick instead of clothbench (not ours)
    summary: str = ""

    def solvers(self) -> tuple[str, ...]:
        return tuple(s for s in SOLVERS if getattr(self, s) is not None)


_OWN = "clothbench.backends"
BACKENDS: dict[str, BackendEntry] = {
    e.name: e
    for e in (
        BackendEntry("numpy", f"{_OWN}.numpy.verlet:NumpyBackend", f"{_OWN}.numpy.pbd:NumpyPbdBackend",
                     summary="vectorised NumPy reference (CPU)"),
        BackendEntry("c", f"{_OWN}.c.verlet:CBackend", summary="native C with OpenMP (CPU line)"),
        BackendEntry("opencl", f"{_OWN}.opencl.verlet:OpenCLBackend", f"{_OWN}.opencl.pbd:OpenCLPbdBackend",
                     summary="OpenCL kernel via pyopencl"),
        BackendEntry("glsl", f"{_OWN}.gl.fragment:GLSLBackend", summary="GLSL fragment shader, FBO ping-pong"),
        BackendEntry("glsl-compute", f"{_OWN}.gl.compute:GLSLComputeBackend",
                     f"{_OWN}.gl.compute_pbd:GLSLComputePbdBackend", summary="GLSL compute shader"),
        BackendEntry("cuda", f"{_OWN}.cuda.verlet:CudaBackend", summary="CUDA kernel via CuPy RawKernel"),
        BackendEntry("taichi", "clothbench.peers.taichi:TaichiBackend", peer=True, summary="Taichi (peer)"),
        BackendEntry("warp", "clothbench.peers.warp:WarpBackend", peer=True, summary="NVIDIA Warp (peer)"),
        BackendEntry("numba", "clothbench.peers.numba:NumbaBackend", peer=True, summary="Numba (peer)"),
        BackendEntry("newton", None, "clothbench.peers.newton:NewtonPbdBackend", peer=True,
                     summary="NVIDIA Newton XPBD (peer, pbd only)"),
        BackendEntry("torch", "clothbench.peers.torch:TorchBackend", peer=True, summary="PyTorch tensors (peer)"),
        BackendEntry("jax", "clothbench.peers.jax:JaxBackend", peer=True, summary="JAX jit (peer)"),
        BackendEntry("cupy", "clothbench.peers.cupy_numpy:CupyNumpyBackend", peer=True,
                     summary="the NumPy step on CuPy arrays (peer)"),
        BackendEntry("numba-cuda", "clothbench.peers.numba_cuda:NumbaCudaBackend", peer=True,
                     summary="numba-cuda @cuda.jit kernel (peer)"),
    )
}  # fmt: skip


def check_name(name: str) -> BackendEntry:
    if name not in BACKENDS:
        raise ClothbenchError(f"unknown backend {name!r} (known: {', '.join(BACKENDS)})")
    return BACKENDS[name]


def _load(target: str):
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)


@lru_cache(maxsize=None)
def availability(name: str) -> Availability:
    """Can `name` run on this machine? Never raises for a known backend."""
    entry = check_name(name)
    target = entry.verlet or entry.pbd  # a PBD-only peer is probed through its PBD module
    try:
        return importlib.import_module(target.partition(":")[0]).probe()
    except Exception as e:  # a probe must not take the whole CLI down
        return Availability(False, f"probe failed: {type(e).__name__}: {e}")


def backend_class(name: str, solver: str = "verlet") -> type[Backend]:
    """The Backend subclass of `name` for `solver`; one line saying so where it has none."""
    entry = check_name(name)
    if solver not in SOLVERS:
        raise ClothbenchError(f"unknown solver {solver!r} (known: {', '.join(SOLVERS)})")
    target = getattr(entry, solver)
    if target is None:
        raise ClothbenchError(f"{name} has no {solver} solver (it runs on: {', '.join(solver_backends(solver))})")
    return _load(target)


def capabilities(name: str, solver: str = "verlet") -> Capabilities:
    return backend_class(name, solver).capabilities


def solver_backends(solver: str) -> list[str]:
    """The backends that implement `solver`."""
    return [name for name, e in BACKENDS.items() if getattr(e, solver) is not None]


def create_backend(name: str, scene: Scene, solver: Solver, options: BackendOptions | None = None) -> Backend:
    """A ready backend for `scene` stepped by `solver`, or one line saying why not."""
    options = options or BackendOptions()
    check_name(name)
    avail = availability(name)
    if not avail.usable:
        raise BackendUnavailable(name, avail.reason)
    return backend_class(name, solver.name)(scene, solver, options)


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
    "BackendEntry",
    "BackendOptions",
    "BACKENDS",
    "Capabilities",
    "availability",
    "backend_class",
    "capabilities",
    "create_backend",
    "resolve_names",
    "solver_backends",
]
