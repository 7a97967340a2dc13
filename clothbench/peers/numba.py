"""Numba (peer): the step as one `@njit(parallel=True)` prange loop, as Numba users write it.

docs/semantics.md, scalar float32 code over (n*n, 4) arrays: a prange over rows, the 12
neighbours in the documented order, the scene's colliders (spheres, cylinders, boxes, then
planes) as float4 rows (kernel_inputs.collider_rows). Fast mode compiles with
`fastmath=True` (LLVM may contract, reorder and vectorise); strict mode with Numba's
default IEEE arithmetic, which does neither and is bit-exact with the NumPy float32
reference (tests/test_peers.py asserts it).
Ping-pong without copies: particle i reads prev[i] only itself, so it writes x_new
there, and the two arrays swap roles (prev_out = pos, as the semantics ask).
Numba runs synchronously on its own thread pool (NUMBA_NUM_THREADS).
"""

from __future__ import annotations

import os

import numpy as np

from clothbench.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import VerletConstants, collider_rows

_INSTALL = "pip install 'clothbench[peers]'"
_KERNELS: dict[bool, object] = {}  # fastmath -> the jitted step, built on first use


def probe() -> Availability:
    try:
        import numba
    except ModuleNotFoundError as e:
        if e.name == "numba":
            return Availability(False, f"numba not installed ({_INSTALL})")
        return Availability(False, f"numba does not import: {e}")
    except Exception as e:  # e.g. "Numba needs NumPy 2.3 or less" (an ImportError)
        return Availability(False, f"numba does not import: {e}")
    threads = numba.get_num_threads()
    return Availability(True, device=f"numba {numba.__version__} parallel ({threads} threads)")


def _kernel(fastmath: bool):
    """Compile lazily: numba is optional, and the JIT belongs to the warm-up."""
    if fastmath in _KERNELS:
        return _KERNELS[fastmath]
    from numba import njit, prange

    d_row = np.array([dr for dr, _ in OFFSETS], dtype=np.int64)
    d_col = np.array([dc for _, dc in OFFSETS], dtype=np.int64)
    zero = np.float32(0.0)

    # no cache=True: both variants come from this one closure and numba's on-disk cache
    # does not tell them apart, so the JIT runs once per process (in the warm-up)
    @njit(parallel=True, fastmath=fastmath)
    def step(pos, prev, n, dt, dt2, k, b, g, rest, spheres, cylinders, boxes, planes):
        """One step; writes x_new into prev (see the module docstring)."""
        for row in prange(n):
            for col in range(n):
                i = row * n + col
                x0, x1, x2, w = pos[i, 0], pos[i, 1], pos[i, 2], pos[i, 3]
                xp0, xp1, xp2 = prev[i, 0], prev[i, 1], prev[i, 2]
                # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
                bv0 = b * ((x0 - xp0) / dt)
                bv1 = b * ((x1 - xp1) / dt)
                bv2 = b * ((x2 - xp2) / dt)
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
                    l2 = (d0 * d0 + d1 * d1) + d2 * d2
                    s = zero
                    if l2 > zero:  # coincident particles: no direction, no spring force
                        length = np.sqrt(l2)
                        s = (k * (length - rest[o])) / length
                    f0 += s * d0 - bv0
                    f1 += s * d1 - bv1
                    f2 += s * d2 - bv2
                if w == zero:  # pinned: does not move
                    prev[i, 0], prev[i, 1], prev[i, 2], prev[i, 3] = x0, x1, x2, w
                    continue
                # step 6: Verlet, acceleration = gravity + force * inverse mass
                n0 = ((x0 + x0) - xp0) + (g[0] + f0 * w) * dt2
                n1 = ((x1 + x1) - xp1) + (g[1] + f1 * w) * dt2
                n2 = ((x2 + x2) - xp2) + (g[2] + f2 * w) * dt2
                for m in range(spheres.shape[0]):  # colliders, in scene order
                    c0, c1, c2, radius = spheres[m, 0], spheres[m, 1], spheres[m, 2], spheres[m, 3]
                    e0, e1, e2 = n0 - c0, n1 - c1, n2 - c2
                    l2 = (e0 * e0 + e1 * e1) + e2 * e2
                    length = np.sqrt(l2)
                    if length < radius:
                        if l2 > zero:
                            s = radius / length
                            n0, n1, n2 = c0 + e0 * s, c1 + e1 * s, c2 + e2 * s
                        else:  # exactly at the centre: straight up
                            n0, n1, n2 = c0, c1 + radius, c2
                for m in range(cylinders.shape[0] // 3):  # then cylinders, in scene order
                    j = 3 * m  # rows: (start, length), (unit axis, radius), (radial_r, 0)
                    a0, a1, a2 = cylinders[j, 0], cylinders[j, 1], cylinders[j, 2]
                    u0, u1, u2 = cylinders[j + 1, 0], cylinders[j + 1, 1], cylinders[j + 1, 2]
                    cyl_len, radius = cylinders[j, 3], cylinders[j + 1, 3]
                    e0, e1, e2 = n0 - a0, n1 - a1, n2 - a2
                    t = (e0 * u0 + e1 * u1) + e2 * u2  # axial coordinate (m) from the start cap
                    q0, q1, q2 = u0 * t, u1 * t, u2 * t
                    p0, p1, p2 = e0 - q0, e1 - q1, e2 - q2  # radial vector
                    rho2 = (p0 * p0 + p1 * p1) + p2 * p2
                    rho = np.sqrt(rho2)
                    if t > zero and t < cyl_len and rho < radius:
                        # push out the shortest way: through the side, or the nearer cap
                        side = radius - rho
                        to_end = cyl_len - t
                        if side <= t and side <= to_end:
                            if rho2 > zero:
                                s = radius / rho
                                n0 = (a0 + q0) + p0 * s
                                n1 = (a1 + q1) + p1 * s
                                n2 = (a2 + q2) + p2 * s
                            else:  # on the axis
                                n0 = (a0 + q0) + cylinders[j + 2, 0]
                                n1 = (a1 + q1) + cylinders[j + 2, 1]
                                n2 = (a2 + q2) + cylinders[j + 2, 2]
                        elif t <= to_end:
                            n0, n1, n2 = n0 - q0, n1 - q1, n2 - q2
                        else:
                            n0, n1, n2 = n0 + u0 * to_end, n1 + u1 * to_end, n2 + u2 * to_end
                for m in range(boxes.shape[0] // 4):  # then boxes, in scene order
                    j = 4 * m  # rows: (centre, 0), (axis i, half extent i) for i = 0, 1, 2
                    e0, e1, e2 = n0 - boxes[j, 0], n1 - boxes[j, 1], n2 - boxes[j, 2]
                    lk = zero
                    least = zero
                    axis = -1  # the axis of least penetration so far; -1: not strictly inside
                    for a in range(3):
                        r = j + 1 + a
                        ell = (e0 * boxes[r, 0] + e1 * boxes[r, 1]) + e2 * boxes[r, 2]
                        depth = boxes[r, 3] - abs(ell)
                        if not depth > zero:
                            axis = -1
                            break
                        if axis < 0 or depth < least:  # ties go to the lower axis
                            axis, least, lk = r, depth, ell
                    if axis >= 0:  # out onto the face on its side (+ at l == 0)
                        move = (boxes[axis, 3] if lk >= zero else -boxes[axis, 3]) - lk
                        n0 = n0 + boxes[axis, 0] * move
                        n1 = n1 + boxes[axis, 1] * move
                        n2 = n2 + boxes[axis, 2] * move
                for m in range(planes.shape[0] // 2):  # then planes, in scene order
                    j = 2 * m  # rows: (point, 0), (unit normal, 0)
                    v0, v1, v2 = planes[j + 1, 0], planes[j + 1, 1], planes[j + 1, 2]
                    e0, e1, e2 = n0 - planes[j, 0], n1 - planes[j, 1], n2 - planes[j, 2]
                    dist = (e0 * v0 + e1 * v1) + e2 * v2
                    if dist < zero:
                        n0, n1, n2 = n0 - v0 * dist, n1 - v1 * dist, n2 - v2 * dist
                prev[i, 0], prev[i, 1], prev[i, 2], prev[i, 3] = n0, n1, n2, w

    _KERNELS[fastmath] = step
    return step


class NumbaBackend(Backend):
    name = "numba"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    capabilities = Capabilities(boxes=("verlet",), sweep_variants=({"strict": False}, {"strict": True}))

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        import numba

        self._threads = numba.config.NUMBA_NUM_THREADS  # the pool's size: a run may use fewer (advance)
        self.run_note = self._fewer_threads_if_busy()
        # fast: fastmath=True, as Numba's performance tips suggest; strict: Numba's default
        self._step = _kernel(fastmath=not options.strict)
        c = VerletConstants.of(scene, solver)
        colliders = collider_rows(scene)
        self._args = (
            scene.grid,
            c.dt,
            c.dt2,
            c.k,
            c.b,
            np.array(c.g, dtype=np.float32),
            np.array([c.rest[kind] for kind in OFFSET_KIND], dtype=np.float32),  # by offset
            *(colliders[kind.plural] for kind in self.capabilities.collider_kinds()),  # its step's arguments
        )
        n2 = scene.particles
        self.pos = np.zeros((n2, 4), dtype=np.float32)
        self.prev = np.zeros((n2, 4), dtype=np.float32)

    @property
    def device(self) -> str:
        return f"numba parallel ({self._threads} threads)"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos[:] = pos
        self.prev[:] = prev

    def _fewer_threads_if_busy(self) -> str:
        """As the c backend: on a busy machine the prange's threads are the cores the others
        leave free, for this run (tuning.threads_for_this_run). The count is the user's with
        NUMBA_NUM_THREADS."""
        from clothbench.backends.tuning import threads_for_this_run

        free, why = threads_for_this_run(self._threads, "NUMBA_NUM_THREADS" in os.environ)
        if not why:
            return ""
        usual, self._threads = self._threads, free
        return f"{free} threads for this run, not {usual}: {why}"

    def advance(self, steps: int) -> None:
        import numba

        numba.set_num_threads(self._threads)  # per calling thread: this run's count (busy machine)
        for _ in range(steps):
            self._step(self.pos, self.prev, *self._args)
            self.pos, self.prev = self.prev, self.pos  # x_new was written over prev

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pos.copy(), self.prev.copy()
