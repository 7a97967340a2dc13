"""numba-cuda (peer): the step as one `@cuda.jit` kernel, one thread per particle, as
numba-cuda users write it.

docs/semantics.md, scalar float32 code over (n*n, 4) device arrays, the same as the numba
CPU peer (peers/numba.py): `i = cuda.grid(1)`, the 12 neighbours in the documented order,
the scene's colliders (spheres, then cylinders, then planes) as float4 rows
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

import math

import numpy as np

from clothbench.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import VerletConstants, collider_rows

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
    except ModuleNotFoundError as e:
        if e.name == "numba":
            return Availability(False, f"numba not installed ({_INSTALL})")
        return Availability(False, f"numba.cuda does not import: {e}")
    except Exception as e:  # e.g. "Numba needs NumPy 2.3 or less" (an ImportError)
        return Availability(False, f"numba.cuda does not import: {type(e).__name__}: {e}")
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
    d_row = np.array([dr for dr, _ in OFFSETS], dtype=np.int64)
    d_col = np.array([dc for _, dc in OFFSETS], dtype=np.int64)
    zero = np.float32(0.0)

    if strict and not _simulated():  # the simulator's libdevice is stubs; its float32 products are IEEE
        from numba.cuda import libdevice

        @cuda.jit(device=True, inline=True)
        def mul(a, b):
            return libdevice.fmul_rn(a, b)  # rounded on its own: never fused into an FMA

    else:

        @cuda.jit(device=True, inline=True)
        def mul(a, b):
            return a * b

    @cuda.jit(fastmath=not strict)
    def step(pos, prev, n, dt, dt2, k, b, g, rest, spheres, cylinders, planes):
        """One step; writes x_new into prev (see the module docstring)."""
        i = cuda.grid(1)
        if i >= n * n:
            return
        row = i // n
        col = i - row * n
        x0, x1, x2, w = pos[i, 0], pos[i, 1], pos[i, 2], pos[i, 3]
        xp0, xp1, xp2 = prev[i, 0], prev[i, 1], prev[i, 2]
        # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
        bv0 = mul(b, (x0 - xp0) / dt)
        bv1 = mul(b, (x1 - xp1) / dt)
        bv2 = mul(b, (x2 - xp2) / dt)
        f0, f1, f2 = zero, zero, zero
        for o in range(12):  # step 5: the 12 neighbours, in the documented order
            r = row + d_row[o]
            c = col + d_col[o]
            if r < 0 or r >= n or c < 0 or c >= n:
                continue  # outside the grid: no spring
            j = r * n + c
            d0 = pos[j, 0] - x0
            d1 = pos[j, 1] - x1
            d2 = pos[j, 2] - x2
            l2 = (mul(d0, d0) + mul(d1, d1)) + mul(d2, d2)
            s = zero
            if l2 > zero:  # coincident particles: no direction, no spring force
                length = math.sqrt(l2)
                s = mul(k, length - rest[o]) / length
            f0 += mul(s, d0) - bv0
            f1 += mul(s, d1) - bv1
            f2 += mul(s, d2) - bv2
        if w == zero:  # pinned: does not move
            prev[i, 0], prev[i, 1], prev[i, 2], prev[i, 3] = x0, x1, x2, w
            return
        # step 6: Verlet, acceleration = gravity + force * inverse mass
        n0 = ((x0 + x0) - xp0) + mul(g[0] + mul(f0, w), dt2)
        n1 = ((x1 + x1) - xp1) + mul(g[1] + mul(f1, w), dt2)
        n2 = ((x2 + x2) - xp2) + mul(g[2] + mul(f2, w), dt2)
        for m in range(spheres.shape[0]):  # colliders, in scene order
            c0, c1, c2, radius = spheres[m, 0], spheres[m, 1], spheres[m, 2], spheres[m, 3]
            e0, e1, e2 = n0 - c0, n1 - c1, n2 - c2
            l2 = (mul(e0, e0) + mul(e1, e1)) + mul(e2, e2)
            length = math.sqrt(l2)
            if length < radius:
                if l2 > zero:
                    s = radius / length
                    n0, n1, n2 = c0 + mul(e0, s), c1 + mul(e1, s), c2 + mul(e2, s)
                else:  # exactly at the centre: straight up
                    n0, n1, n2 = c0, c1 + radius, c2
        for m in range(cylinders.shape[0] // 3):  # then cylinders, in scene order
            j = 3 * m  # rows: (start, length), (unit axis, radius), (radial_r, 0)
            a0, a1, a2 = cylinders[j, 0], cylinders[j, 1], cylinders[j, 2]
            u0, u1, u2 = cylinders[j + 1, 0], cylinders[j + 1, 1], cylinders[j + 1, 2]
            cyl_len, radius = cylinders[j, 3], cylinders[j + 1, 3]
            e0, e1, e2 = n0 - a0, n1 - a1, n2 - a2
            t = (mul(e0, u0) + mul(e1, u1)) + mul(e2, u2)  # axial coordinate (m) from the start cap
            q0, q1, q2 = mul(u0, t), mul(u1, t), mul(u2, t)
            p0, p1, p2 = e0 - q0, e1 - q1, e2 - q2  # radial vector
            rho2 = (mul(p0, p0) + mul(p1, p1)) + mul(p2, p2)
            rho = math.sqrt(rho2)
            if t > zero and t < cyl_len and rho < radius:
                # push out the shortest way: through the side, or the nearer cap
                side = radius - rho
                to_end = cyl_len - t
                if side <= t and side <= to_end:
                    if rho2 > zero:
                        s = radius / rho
                        n0 = (a0 + q0) + mul(p0, s)
                        n1 = (a1 + q1) + mul(p1, s)
                        n2 = (a2 + q2) + mul(p2, s)
                    else:  # on the axis
                        n0 = (a0 + q0) + cylinders[j + 2, 0]
                        n1 = (a1 + q1) + cylinders[j + 2, 1]
                        n2 = (a2 + q2) + cylinders[j + 2, 2]
                elif t <= to_end:
                    n0, n1, n2 = n0 - q0, n1 - q1, n2 - q2
                else:
                    n0, n1, n2 = n0 + mul(u0, to_end), n1 + mul(u1, to_end), n2 + mul(u2, to_end)
        for m in range(planes.shape[0] // 2):  # then planes, in scene order
            j = 2 * m  # rows: (point, 0), (unit normal, 0)
            v0, v1, v2 = planes[j + 1, 0], planes[j + 1, 1], planes[j + 1, 2]
            e0, e1, e2 = n0 - planes[j, 0], n1 - planes[j, 1], n2 - planes[j, 2]
            dist = (mul(e0, v0) + mul(e1, v1)) + mul(e2, v2)
            if dist < zero:
                n0, n1, n2 = n0 - mul(v0, dist), n1 - mul(v1, dist), n2 - mul(v2, dist)
        prev[i, 0], prev[i, 1], prev[i, 2], prev[i, 3] = n0, n1, n2, w

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
        c = VerletConstants.of(scene, solver)
        colliders = collider_rows(scene)
        self._args = (
            np.int64(scene.grid),
            c.dt,
            c.dt2,
            c.k,
            c.b,
            cuda.to_device(np.array(c.g, dtype=np.float32)),
            cuda.to_device(np.array([c.rest[kind] for kind in OFFSET_KIND], dtype=np.float32)),  # by offset
            *(
                cuda.to_device(np.ascontiguousarray(colliders[kind.plural]))
                for kind in self.capabilities.collider_kinds()  # its kernel's arguments
            ),
        )
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
