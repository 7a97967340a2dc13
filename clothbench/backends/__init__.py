"""The backend registry: every backend by name, whether it can run here, and why not.

Each backend is a module exposing `probe() -> Availability` (cheap, never raises) and one
`Backend` subclass per solver it implements, named here as "module:Class". Modules are
imported only when asked for, so a missing optional package costs nothing until its backend
is used. Options are checked against the class's declared Capabilities before it is built.

Every other fact about a backend is its entry's: the name tables and figures give it, the
figures' panel it goes to, whether it is GPU-style, its viewer key, whether a forked child may
run it. None has a default, so an entry cannot leave one out; tests/test_registry_facts.py
checks each one's value. The one fact of the class instead is the device clock it reads
(Backend.device_timer), because a device's driver decides it (GL timestamps are no device's
clock on llvmpipe).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from functools import lru_cache

from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import SOLVERS, Solver
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities


@dataclass(frozen=True)
class BackendEntry:
    name: str
    verlet: str | None  # "module:Class" of its Verlet backend (None: PBD only); the module's probe() says if it runs
    pbd: str | None = None  # "module:Class" of its PBD backend, if it has one
    vbd: str | None = field(default=None, kw_only=True)  # "module:Class" of its VBD backend, if it has one
    peer: bool = False  # a system users would pick instead of clothbench (not ours)
    summary: str = ""
    # the facts the reports, the viewer and the executor read, keyword-only and required:
    display: str = field(kw_only=True)  # its name in tables and figure legends
    platform: str = field(kw_only=True)  # its figures' panel (PLATFORMS); every peer's is PEERS
    gpu_style: bool = field(kw_only=True)  # a GPGPU platform the chapter compares (the peer table's own side)
    view_key: str = field(kw_only=True)  # the viewer's key for it (clothbench/viewer/keys.py BACKEND_KEY_NAMES)
    # a forked child may run it: it touches no driver state a parent could hold half-made
    # (numpy's steppers only); any other gets a clean process (harness/executor.py)
    fork_safe: bool = field(kw_only=True)

    def solvers(self) -> tuple[str, ...]:
        return tuple(s for s in SOLVERS if getattr(self, s) is not None)


_OWN = "clothbench.backends"
PEERS = "peers"  # the platform of every peer: the figures give them a panel of their own
# the figures' panels, in the order they are drawn
PLATFORMS = ("CPU", "OpenCL", "GL", "CUDA", PEERS)
# the view keys are the chapter's F1 CPU, F2 GLSL, F3 OpenCL, F4 CUDA, then the registry's order;
# past F12 (moderngl-window has no F13) a backend's key is shift and an F-key
BACKENDS: dict[str, BackendEntry] = {
    e.name: e
    for e in (
        BackendEntry("numpy", f"{_OWN}.numpy.verlet:NumpyBackend", f"{_OWN}.numpy.pbd:NumpyPbdBackend",
                     vbd=f"{_OWN}.numpy.vbd:NumpyVbdBackend", summary="vectorised NumPy reference (CPU)",
                     display="CPU (numpy)", platform="CPU", gpu_style=False, view_key="F1", fork_safe=True),
        BackendEntry("c", f"{_OWN}.c.verlet:CBackend", vbd=f"{_OWN}.c.vbd:CVbdBackend", summary="native C with OpenMP (CPU line)",
                     display="C (OpenMP)", platform="CPU", gpu_style=False, view_key="F6", fork_safe=False),
        BackendEntry("opencl", f"{_OWN}.opencl.verlet:OpenCLBackend", f"{_OWN}.opencl.pbd:OpenCLPbdBackend",
                     vbd=f"{_OWN}.opencl.vbd:OpenCLVbdBackend", summary="OpenCL kernel via pyopencl",
                     display="OpenCL", platform="OpenCL", gpu_style=True, view_key="F3", fork_safe=False),
        BackendEntry("glsl", f"{_OWN}.gl.fragment:GLSLBackend", summary="GLSL fragment shader, FBO ping-pong",
                     display="GLSL", platform="GL", gpu_style=True, view_key="F2", fork_safe=False),
        BackendEntry("glsl-compute", f"{_OWN}.gl.compute:GLSLComputeBackend",
                     f"{_OWN}.gl.compute_pbd:GLSLComputePbdBackend", vbd=f"{_OWN}.gl.compute_vbd:GLSLComputeVbdBackend",
                     summary="GLSL compute shader",
                     display="GLSL compute", platform="GL", gpu_style=True, view_key="F5", fork_safe=False),
        BackendEntry("cuda", f"{_OWN}.cuda.verlet:CudaBackend", summary="CUDA kernel via CuPy RawKernel",
                     display="CUDA", platform="CUDA", gpu_style=True, view_key="F4", fork_safe=False),
        BackendEntry("taichi", "clothbench.peers.taichi:TaichiBackend", peer=True, summary="Taichi (peer)",
                     display="Taichi", platform=PEERS, gpu_style=False, view_key="F7", fork_safe=False),
        BackendEntry("warp", "clothbench.peers.warp:WarpBackend", peer=True, summary="NVIDIA Warp (peer)",
                     display="Warp", platform=PEERS, gpu_style=False, view_key="F8", fork_safe=False),
        BackendEntry("numba", "clothbench.peers.numba:NumbaBackend", peer=True, summary="Numba (peer)",
                     display="Numba", platform=PEERS, gpu_style=False, view_key="F9", fork_safe=False),
        BackendEntry("newton", None, "clothbench.peers.newton:NewtonPbdBackend", peer=True,
                     vbd="clothbench.peers.newton:NewtonVbdBackend",
                     summary="NVIDIA Newton XPBD and VBD (peer, pbd and vbd)",
                     display="Newton", platform=PEERS, gpu_style=False, view_key="F10", fork_safe=False),
        BackendEntry("torch", "clothbench.peers.torch:TorchBackend", peer=True, summary="PyTorch tensors (peer)",
                     display="PyTorch", platform=PEERS, gpu_style=False, view_key="F11", fork_safe=False),
        BackendEntry("jax", "clothbench.peers.jax:JaxBackend", peer=True, summary="JAX jit (peer)",
                     display="JAX", platform=PEERS, gpu_style=False, view_key="F12", fork_safe=False),
        BackendEntry("cupy", "clothbench.peers.cupy_numpy:CupyNumpyBackend", peer=True,
                     summary="the NumPy step on CuPy arrays (peer)",
                     display="CuPy (NumPy step)", platform=PEERS, gpu_style=False, view_key="shift+F1",
                     fork_safe=False),  # NumPy's step, but CuPy's CUDA context: not fork-safe
        BackendEntry("numba-cuda", "clothbench.peers.numba_cuda:NumbaCudaBackend", peer=True,
                     summary="numba-cuda @cuda.jit kernel (peer)",
                     display="Numba CUDA", platform=PEERS, gpu_style=False, view_key="shift+F2", fork_safe=False),
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
    target = entry.verlet or entry.pbd or entry.vbd  # a PBD-only peer is probed through its PBD module
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
        fix = " or ".join(f"--solver {s}" for s in entry.solvers())
        raise ClothbenchError(
            f"{name} has no {solver} solver: use {fix} ({solver} runs on: {', '.join(solver_backends(solver))})"
        )
    return _load(target)


def capabilities(name: str, solver: str = "verlet") -> Capabilities:
    return backend_class(name, solver).capabilities


def precision_backends(precision: str) -> list[str]:
    """The backends whose declared Capabilities take `precision` with some solver."""
    names = []
    for name, entry in BACKENDS.items():
        for solver in entry.solvers():
            try:
                if precision in capabilities(name, solver).precisions:
                    names.append(name)
                    break
            except Exception:  # a module that cannot be imported here declares nothing
                continue
    return names


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
    "PEERS",
    "PLATFORMS",
    "availability",
    "backend_class",
    "capabilities",
    "check_name",
    "create_backend",
    "resolve_names",
    "solver_backends",
]
