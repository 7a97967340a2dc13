"""CuPy (peer): the NumPy reference's step, unchanged, on CuPy arrays: what a NumPy user gets
by moving the arrays to the GPU.

The step is backends/numpy/verlet.py's own code, not a copy. It calls NumPy's functions
(np.sqrt, np.where, np.copyto, np.zeros_like) on the arrays it is given, and NumPy hands
each call on CuPy arrays to CuPy (NEP 13 and NEP 18 dispatch), so this class only puts the
state and the constants on the device (`xp.asarray`) and brings them back. Each NumPy
operation is one CuPy kernel, compiled by NVRTC with IEEE division and square root and
nothing to contract across operations, so the result should be NumPy's float32 bits: one
mode, like the reference (the GPU check holds it to that; no GPU has run it yet).
A collider test `if not inside.any()` reads one value back per collider per step, as that
NumPy code does on a GPU.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, BackendOptions, Capabilities
from clothbench.backends.numpy.verlet import NumpyBackend


def _first_line(e: BaseException) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def probe() -> Availability:
    from clothbench.backends.cuda.verlet import INSTALL_HINT, cupy_build

    try:
        import cupy
    except ImportError:
        return Availability(False, INSTALL_HINT)
    except Exception as e:  # installed but broken, e.g. built against another numpy
        return Availability(False, f"cupy failed to import: {type(e).__name__}: {_first_line(e)}")
    try:
        count = cupy.cuda.runtime.getDeviceCount()
    except Exception as e:  # no driver: cudaErrorInsufficientDriver / cudaErrorNoDevice
        return Availability(False, f"no CUDA device ({cupy_build(cupy)}: {_first_line(e)})")
    if count < 1:
        return Availability(False, f"no CUDA device ({cupy_build(cupy)}: 0 devices)")
    try:  # CuPy compiles every elementwise kernel with NVRTC on first use
        float((cupy.arange(4, dtype=cupy.float32) * 2).sum())
    except Exception as e:
        return Availability(False, f"cupy cannot build its kernels ({cupy_build(cupy)}): {_first_line(e)}")
    return Availability(True, reason=cupy_build(cupy), device=_device_name(cupy))


def _device_name(cupy) -> str:
    name = cupy.cuda.runtime.getDeviceProperties(cupy.cuda.Device().id)["name"]
    return name.decode() if isinstance(name, bytes) else str(name)


class CupyNumpyBackend(NumpyBackend):
    name = "cupy"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    # one mode, float32, fixed colliders: the reference's operations, each one IEEE kernel
    capabilities = Capabilities(strict=False)

    @staticmethod
    def array_module():
        """The module whose arrays the NumPy step runs on (tests/test_gpu_peers.py gives it a
        stand-in that refuses host arrays, as CuPy does, to run this class without a GPU)."""
        import cupy

        return cupy

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        self.xp = self.array_module()
        super().__init__(scene, solver, options)
        to = self.xp.asarray
        self.gravity = to(self.gravity)
        self.colliders = [
            (kind, {name: to(v) if isinstance(v, np.ndarray) else v for name, v in constants.items()})
            for kind, constants in self.colliders
        ]
        self.pos = self.prev = to(self.pos)
        self.w, self.free = to(self.w), to(self.free)

    @property
    def device(self) -> str:
        return f"cupy {_device_name(self.xp)}"

    def planes(self, state: np.ndarray):
        return self.xp.asarray(super().planes(state))

    def set_inverse_mass(self, pos: np.ndarray) -> None:
        super().set_inverse_mass(pos)
        self.w, self.free = self.xp.asarray(self.w), self.xp.asarray(self.free)

    def state(self, planes) -> np.ndarray:
        n2 = self.scene.particles
        a = np.empty((n2, 4), dtype=self.dtype)
        a[:, :3] = self.xp.asnumpy(planes).reshape(3, n2).T
        a[:, 3] = self.xp.asnumpy(self.w).reshape(n2)
        return a

    def synchronize(self) -> None:
        self.xp.cuda.get_current_stream().synchronize()

    def close(self) -> None:
        self.pos = self.prev = self.w = self.free = self.gravity = None
        self.colliders = []
