"""numba-cuda (peer): the step as one `@cuda.jit` kernel, one thread per particle, as
numba-cuda users write it.

docs/semantics.md, scalar float32 code over (n*n, 4) device arrays: the numba CPU peer's
particle step (peers/numba.py, particle_update) as a device function, called by thread
`i = cuda.grid(1)`: the 12 neighbours in the documented order, the scene's colliders
(spheres, then cylinders, then planes; boxes are not declared here yet) as float4 rows
(kernel_inputs.collider_rows). Ping-pong without copies: particle i reads prev[i] only
itself, so it writes x_new there, and the two arrays swap roles.

Fast mode is `fastmath=True` (flush-to-zero, approximate division and square root, FMA).
Strict mode is numba-cuda's default IEEE division and square root, and one departure from
plain numba code: every product is written `mul(a, b)`, which is `a * b` in fast mode and
libdevice's `fmul_rn` in strict mode, because NVVM contracts `a * b + c` into an FMA by
default (-fma=1) even without fastmath and `cuda.jit` has no switch for it; a product
rounded by fmul_rn cannot be fused. tests/test_gpu_peers.py runs the kernel on the CPU under
numba's CUDA simulator (NUMBA_ENABLE_CUDASIM=1) against NumPy.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities, import_failure
from clothbench.peers.numba import particle_update, step_arguments

_INSTALL = "pip install numba-cuda, with an NVIDIA driver"
THREADS_PER_BLOCK = 128
_KERNELS: dict[bool, object] = {}  # strict -> the kernel, built on first use
# numba.cuda, imported on first use; a module global, as kernels name it (numba's simulator
# swaps the kernel's global `cuda` for its own)
cuda = None


def _cuda():
    global cuda
    from numba import config, cuda as module

    # the grid a small scene launches is no mistake: no under-utilisation warning per launch
    config.CUDA_LOW_OCCUPANCY_WARNINGS = False
    cuda = module
    return module


def probe() -> Availability:
    try:
        _cuda()
    except Exception as e:  # not installed, or e.g. "Numba needs NumPy 2.3 or less" (an ImportError)
        return import_failure(e, "numba.cuda", _INSTALL, packages=("numba",))
    if _simulated():
        return Availability(True, device="numba CUDA simulator (NUMBA_ENABLE_CUDASIM=1, on the CPU)")
    try:
        if not cuda.is_available():
            return Availability(False, "no CUDA GPU or driver here (numba.cuda.is_available() is False)")
        return Availability(True, device=_device_name())
    except Exception as e:
        return Availability(False, f"numba.cuda cannot reach a GPU: {type(e).__name__}: {e}")


def _device_name() -> str:
    name = cuda.get_current_device().name  # bytes in numba's own numba.cuda, str elsewhere
    return name.decode() if isinstance(name, bytes) else str(name)


def _simulated() -> bool:
    from numba import config

    return bool(config.ENABLE_CUDASIM)


def _kernel(strict: bool):
    """Compile lazily: numba-cuda is optional, and the JIT belongs to the warm-up."""
    if strict in _KERNELS:
        return _KERNELS[strict]
    _cuda()

    if strict and not _simulated():  # the simulator's libdevice is stubs; its float32 products are IEEE
        from numba.cuda import libdevice

        @cuda.jit(device=True, inline=True)
        def mul(a, b):
            return libdevice.fmul_rn(a, b)  # rounded on its own: never fused into an FMA

    else:

        @cuda.jit(device=True, inline=True)
        def mul(a, b):
            return a * b

    update = cuda.jit(device=True, inline=True)(particle_update(mul))

    @cuda.jit(fastmath=not strict)
    def step(pos, prev, n, dt, dt2, k, b, g, rest, spheres, cylinders, boxes, planes):
        """One step; writes x_new into prev (see the module docstring)."""
        i = cuda.grid(1)
        if i < n * n:
            row = i // n
            update(pos, prev, i, row, i - row * n, n, dt, dt2, k, b, g, rest, spheres, cylinders, boxes, planes)

    _KERNELS[strict] = step
    return step


class NumbaCudaBackend(Backend):
    name = "numba-cuda"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    capabilities = Capabilities(sweep_variants=({"strict": False}, {"strict": True}))

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        self._cuda = _cuda()
        self._step = _kernel(strict=options.strict)
        # every kind the shared step takes: one this peer does not declare is refused before
        # here (Capabilities.scene_refusal), so its rows are empty
        self._args = tuple(cuda.to_device(a) if isinstance(a, np.ndarray) else a for a in step_arguments(scene, solver))
        n2 = scene.particles
        self._blocks = -(-n2 // THREADS_PER_BLOCK)
        self.pos = cuda.device_array((n2, 4), dtype=np.float32)
        self.prev = cuda.device_array((n2, 4), dtype=np.float32)

    @property
    def device(self) -> str:
        return f"numba-cuda {_device_name()}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos.copy_to_device(np.ascontiguousarray(pos, dtype=np.float32))
        self.prev.copy_to_device(np.ascontiguousarray(prev, dtype=np.float32))

    def advance(self, steps: int) -> None:
        for _ in range(steps):
            self._step[self._blocks, THREADS_PER_BLOCK](self.pos, self.prev, *self._args)
            self.pos, self.prev = self.prev, self.pos  # x_new was written over prev

    def synchronize(self) -> None:
        self._cuda.synchronize()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pos.copy_to_host(), self.prev.copy_to_host()

    def close(self) -> None:
        self.pos = self.prev = None
        self._args = ()
