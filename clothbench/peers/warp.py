"""NVIDIA Warp (peer): the step as one `@wp.kernel` over `wp.array(dtype=wp.vec4)`.

docs/semantics.md, written as Warp users write it: one thread per particle, vec3
arithmetic, `wp.length_sq`, the stencil unrolled with `wp.static`, the colliders
(spheres, cylinders, boxes, then planes) in small float4 arrays (kernel_inputs.collider_rows).
Ping-pong without copies: particle i reads prev[i] only itself, so it writes x_new
there, and the two arrays swap roles (prev_out = pos, as the semantics ask).

Warp's defaults are IEEE on the CPU: no fast math, and although `fuse_fp` is on, its
generated C++ calls one inline function per operation, so clang never sees `a*b + c` in
one expression and emits no FMA. The result is bit-exact with the NumPy float32
reference (tests/test_peers.py asserts it), so `--strict` needs no other kernel.
Warp compiles the kernel on the first launch (the harness's warm-up) and keeps it in its
kernel cache (~/.cache/warp). On the CPU a launch runs on one thread.
"""

from __future__ import annotations

import os
import sys
import tempfile

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities, import_failure
from clothbench.model.kernel_inputs import VerletConstants, collider_rows

_INSTALL = "pip install 'clothbench[peers]'"
# What Warp's native library prints wherever libcuda is missing: on a CPU-only machine that
# is every run, and `clothbench backends` already says where warp runs.
_NO_DRIVER_WARNING = "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver"
_KERNEL = None  # the step, defined on first use so clothbench imports without warp


def import_warp():
    import warp as wp

    # no banner or per-module load lines on stdout (they would corrupt --json)
    if hasattr(wp.config, "log_level"):
        wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    else:  # Warp before log levels
        wp.config.quiet = True
    # no adjoint kernels: clothbench never differentiates a step, and Warp otherwise compiles a
    # backward form of every kernel of every module it loads, Newton's among them (the same
    # forward code; Newton's cold VBD test 47 -> 40 s on the Zen 3, 2026-12-06)
    wp.config.enable_backward = False
    return wp


def init_quietly(wp) -> None:
    """wp.init() without _NO_DRIVER_WARNING. Warp has no setting for it: its C++ core
    fprintf's it to stderr while loading the driver (native/cuda_util.cpp, init_cuda_driver),
    before any Python-level log level applies. So file descriptor 2 is pointed at a temporary
    file while Warp initialises, and whatever else it wrote there is passed on to stderr."""
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no stderr to keep clean
        wp.init()
        return
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        lines = captured.read().decode("utf-8", "replace").splitlines(keepends=True)
    rest = "".join(line for line in lines if _NO_DRIVER_WARNING not in line)
    if rest:
        sys.stderr.write(rest)


def probe() -> Availability:
    try:
        wp = import_warp()
        init_quietly(wp)
    except Exception as e:  # not installed, or e.g. a warp build that does not load here
        return import_failure(e, "warp", _INSTALL, broken="does not initialise")
    return Availability(True, device=f"warp {wp.__version__} ({_default_device(wp)})")


def _default_device(wp) -> str:
    return "cuda" if wp.is_cuda_available() else "cpu"


def _kernel(wp):
    global _KERNEL
    if _KERNEL is not None:
        return _KERNEL

    @wp.kernel(enable_backward=False)
    def step(
        pos: wp.array(dtype=wp.vec4),
        prev: wp.array(dtype=wp.vec4),
        n: int,
        dt: float,
        dt2: float,
        k: float,
        b: float,
        g: wp.vec3,
        rest: wp.array(dtype=float),
        spheres: wp.array(dtype=wp.vec4),
        cylinders: wp.array(dtype=wp.vec4),
        boxes: wp.array(dtype=wp.vec4),
        planes: wp.array(dtype=wp.vec4),
    ):
        """pos[i] is x(t), prev[i] is x(t - dt) and receives x(t + dt)."""
        i = wp.tid()
        row = i // n
        col = i - row * n
        p = pos[i]
        q = prev[i]
        x = wp.vec3(p[0], p[1], p[2])
        w = p[3]
        xp = wp.vec3(q[0], q[1], q[2])
        # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
        vel = (x - xp) / dt
        bv = b * vel
        force = wp.vec3(0.0)
        for o in range(12):  # step 5: the 12 neighbours, in order (unrolled)
            r = row + wp.static(OFFSETS[o][0])
            c = col + wp.static(OFFSETS[o][1])
            if r >= 0 and r < n and c >= 0 and c < n:  # outside the grid: no spring
                pj = pos[r * n + c]
                d = wp.vec3(pj[0], pj[1], pj[2]) - x
                l2 = wp.length_sq(d)
                s = float(0.0)
                if l2 > 0.0:  # coincident particles: no direction, no spring force
                    length = wp.sqrt(l2)
                    s = (k * (length - rest[o])) / length
                force = force + (s * d - bv)
        x_new = x
        if w != 0.0:  # pinned particles do not move
            # step 6: Verlet, acceleration = gravity + force * inverse mass
            acc = g + force * w
            x_new = (2.0 * x - xp) + acc * dt2
            for m in range(spheres.shape[0]):  # colliders, in scene order
                sphere = spheres[m]
                center = wp.vec3(sphere[0], sphere[1], sphere[2])
                radius = sphere[3]
                e = x_new - center
                l2 = wp.length_sq(e)
                length = wp.sqrt(l2)
                if length < radius:
                    if l2 > 0.0:
                        x_new = center + e * (radius / length)
                    else:  # exactly at the centre: straight up
                        x_new = center + wp.vec3(0.0, radius, 0.0)
            for m in range(cylinders.shape[0] // 3):  # then cylinders, in scene order
                row0 = cylinders[3 * m]  # (start, length)
                row1 = cylinders[3 * m + 1]  # (unit axis, radius)
                row2 = cylinders[3 * m + 2]  # (radial_r, 0)
                a = wp.vec3(row0[0], row0[1], row0[2])
                cyl_len = row0[3]
                u = wp.vec3(row1[0], row1[1], row1[2])
                radius = row1[3]
                radial_r = wp.vec3(row2[0], row2[1], row2[2])
                e = x_new - a
                t = (e[0] * u[0] + e[1] * u[1]) + e[2] * u[2]  # axial coordinate (m) from the start cap
                qa = u * t
                rv = e - qa  # radial vector
                rho2 = (rv[0] * rv[0] + rv[1] * rv[1]) + rv[2] * rv[2]
                rho = wp.sqrt(rho2)
                if t > 0.0 and t < cyl_len and rho < radius:
                    # push out the shortest way: through the side, or the nearer cap
                    side = radius - rho
                    to_end = cyl_len - t
                    if side <= t and side <= to_end:
                        if rho2 > 0.0:
                            x_new = (a + qa) + rv * (radius / rho)
                        else:  # on the axis
                            x_new = (a + qa) + radial_r
                    elif t <= to_end:
                        x_new = x_new - qa
                    else:
                        x_new = x_new + u * to_end
            for m in range(boxes.shape[0] // 4):  # then boxes, in scene order
                cr = boxes[4 * m]  # (centre, 0), then (axis i, half extent i) for i = 0, 1, 2
                r0, r1, r2 = boxes[4 * m + 1], boxes[4 * m + 2], boxes[4 * m + 3]
                e = x_new - wp.vec3(cr[0], cr[1], cr[2])
                ax0, ax1, ax2 = wp.vec3(r0[0], r0[1], r0[2]), wp.vec3(r1[0], r1[1], r1[2]), wp.vec3(r2[0], r2[1], r2[2])
                l0 = (e[0] * ax0[0] + e[1] * ax0[1]) + e[2] * ax0[2]  # the box's own coordinates
                l1 = (e[0] * ax1[0] + e[1] * ax1[1]) + e[2] * ax1[2]
                l2 = (e[0] * ax2[0] + e[1] * ax2[1]) + e[2] * ax2[2]
                p0, p1, p2 = r0[3] - wp.abs(l0), r1[3] - wp.abs(l1), r2[3] - wp.abs(l2)  # depth through each face pair
                if p0 > 0.0 and p1 > 0.0 and p2 > 0.0:  # strictly inside: out through the least deep face
                    u = ax0
                    lk = l0
                    hk = r0[3]
                    pk = p0
                    if p1 < pk:  # ties go to the lower axis
                        u = ax1
                        lk = l1
                        hk = r1[3]
                        pk = p1
                    if p2 < pk:
                        u = ax2
                        lk = l2
                        hk = r2[3]
                    x_new = x_new + u * (wp.where(lk >= 0.0, hk, -hk) - lk)  # the face on its side
            for m in range(planes.shape[0] // 2):  # then planes, in scene order
                pr = planes[2 * m]  # (point, 0)
                nr = planes[2 * m + 1]  # (unit normal, 0)
                e = x_new - wp.vec3(pr[0], pr[1], pr[2])
                nrm = wp.vec3(nr[0], nr[1], nr[2])
                dist = (e[0] * nrm[0] + e[1] * nrm[1]) + e[2] * nrm[2]
                if dist < 0.0:
                    x_new = x_new - nrm * dist
        prev[i] = wp.vec4(x_new[0], x_new[1], x_new[2], w)

    _KERNEL = step
    return step


class WarpBackend(Backend):
    name = "warp"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    # --strict and fast run the same kernel, Warp's CPU default being IEEE already (module
    # docstring): one sweep variant
    capabilities = Capabilities(device=True, boxes=("verlet",))

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        wp = self._wp = import_warp()
        init_quietly(wp)
        name = options.device or _default_device(wp)
        try:
            self._device = wp.get_device(name)
        except Exception as e:
            raise ClothbenchError(f"warp has no device {name!r} here ({e}); try cpu") from None
        self._step = _kernel(wp)
        n2 = scene.particles
        self.pos = wp.zeros(n2, dtype=wp.vec4, device=self._device)
        self.prev = wp.zeros(n2, dtype=wp.vec4, device=self._device)
        c = VerletConstants.of(scene, solver)
        colliders = collider_rows(scene)
        rest = np.array([c.rest[kind] for kind in OFFSET_KIND], dtype=np.float32)  # by offset
        self._consts = [
            scene.grid,
            c.dt,
            c.dt2,
            c.k,
            c.b,
            wp.vec3(*c.g),
            wp.array(rest, dtype=float, device=self._device),
            *(
                wp.array(colliders[kind.plural], dtype=wp.vec4, device=self._device)
                for kind in self.capabilities.collider_kinds()  # its kernel's arguments
            ),
        ]

    @property
    def device(self) -> str:
        d = self._device
        return f"warp {d.alias} (1 thread)" if d.is_cpu else f"warp {d.alias} ({d.name})"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.pos.assign(np.ascontiguousarray(pos, dtype=np.float32))
        self.prev.assign(np.ascontiguousarray(prev, dtype=np.float32))

    def advance(self, steps: int) -> None:
        wp = self._wp
        for _ in range(steps):
            inputs = [self.pos, self.prev, *self._consts]
            wp.launch(self._step, dim=self.scene.particles, inputs=inputs, device=self._device)
            self.pos, self.prev = self.prev, self.pos  # x_new was written over prev

    def synchronize(self) -> None:
        self._wp.synchronize_device(self._device)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pos.numpy().copy(), self.prev.numpy().copy()

    def close(self) -> None:
        self.pos = self.prev = None
        self._consts = []
