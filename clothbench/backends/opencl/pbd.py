"""The PBD solver (docs/pbd.md) on OpenCL: kernels/pbd_cloth.cl through pyopencl.

Host code only: the substep plan, the state conversion and the profiling are
pbd_device.PbdDeviceBackend's (shared with gl/compute_pbd.py); the device, its queue, its
probe, the program cache and the build-error report are device.py's (OpenCLDeviceMixin).

One substep is a fixed list of launches on an in-order queue (each sees the previous one's
writes). Every launch is a kernel object whose arguments are set once at construction, so
advance() only enqueues.
"""

from __future__ import annotations

import numpy as np

from clothbench.scene import Scene
from clothbench.solver import Pbd
from clothbench.backends.base import BackendOptions, Capabilities
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    arithmetic_options,
    build_program,
    program_source,
    shape_options,
)
from clothbench.backends.pbd_device import PbdDeviceBackend

KERNEL_FILE = "pbd_cloth.cl"


class OpenCLPbdBackend(OpenCLDeviceMixin, PbdDeviceBackend):
    name = "opencl"
    capabilities = Capabilities(local_size=True, device=True, sweep_variants=({"strict": True}, {"strict": False}))

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self._open_queue(options)
        cl, context = self._cl, self._context
        self.program = build_program(context, program_source(KERNEL_FILE), self.build_options())

        mf = cl.mem_flags
        size = self.n2 * 16  # one float4 per particle
        self.x = cl.Buffer(context, mf.READ_WRITE, size)
        self.v = cl.Buffer(context, mf.READ_WRITE, size)
        self.xs = [cl.Buffer(context, mf.READ_WRITE, size) for _ in range(2)]  # Jacobi ping-pong
        self.lam = cl.Buffer(context, mf.READ_WRITE, 4 * self.lambda_count)
        self.colliders = self._collider_buffer()
        self.ij = self.border = None
        if self.jacobi:
            self._split_jacobi()
        else:
            self.ij = self._read_only_buffer(self.batch_pairs)

        self._kernels: dict = {}
        self.launches = self._plan_launches()

    def _split_jacobi(self) -> None:
        """The Jacobi pass's two launches: the interior (rows and columns 2 .. n-3) in vectors
        of V particles of a row, V the device's preferred float width (4, 8 or 16), and every
        particle those vectors do not cover, from an index list uploaded once."""
        n, v = self.n, self.vector_width
        per_row = (n - 4) // v if n > 4 else 0
        self.interior_vectors = per_row * (n - 4)
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : 2 + v * per_row] = per_row > 0
        self.border_particles = np.flatnonzero(~covered).astype(np.int32)
        self.border = self._read_only_buffer(self.border_particles)

    @property
    def vector_width(self) -> int:
        preferred = self._device.preferred_vector_width_float
        return 16 if preferred >= 16 else 8 if preferred >= 8 else 4

    def build_options(self) -> tuple[str, ...]:
        return (*shape_options(self.scene, self.vector_width), *arithmetic_options(self.strict))

    def _kernel(self, key, name: str, dtypes, args):
        """A kernel object with its typed arguments set once (a wrongly typed one raises);
        launches with the same arguments share it."""
        if key not in self._kernels:
            k = self._cl.Kernel(self.program, name)
            k.set_scalar_arg_dtypes(list(dtypes))
            k.set_args(*args)
            self._check_local_size(k, name)
            self._kernels[key] = k
        return self._kernels[key]

    def _launches_of(self, step) -> list:
        """[(kernel, global size, local size)] of one step of the plan."""
        c, f32, i32 = self.constants, np.float32, np.int32
        float4 = self._cl.cltypes.float4
        make4 = self._cl.cltypes.make_float4
        kind = step[0]
        if kind == "predict":
            k = self._kernel(kind, "pbd_predict", [None] * 3 + [f32, float4],
                             (self.x, self.v, self.xs[0], c.h, make4(*c.gh, 0.0)))
            kernels = [(k, self.n2)]
        elif kind == "jacobi":
            _, it, src, dst = step
            first = i32(it == 0)
            args = (self.xs[src], self.xs[dst], self.lam, first, make4(*c.rest, 0.0), make4(*c.at, 0.0), c.relax)
            dtypes = [None] * 3 + [i32, float4, float4, f32]
            border = len(self.border_particles)
            kernels = [(self._kernel((kind, "border", src, first), "pbd_jacobi_border", dtypes + [None, i32],
                                     args + (self.border, i32(border))), border)]
            if self.interior_vectors:
                interior = self._kernel((kind, "interior", src, first), "pbd_jacobi_interior", dtypes, args)
                kernels.insert(0, (interior, self.interior_vectors))
        elif kind == "coloured":
            _, it, b = step
            batch, first = self.batches[b], i32(it == 0)
            k = self._kernel((kind, b, first), "pbd_coloured", [None] * 3 + [i32, i32, i32, f32, f32],
                             (self.xs[0], self.ij, self.lam, i32(self.batch_offsets[b]), i32(len(batch.i)), first,
                              c.rest[batch.kind], c.at[batch.kind]))
            kernels = [(k, len(batch.i))]
        elif kind == "collide":
            k = self._kernel((kind, step[1]), "pbd_collide", [None, None], (self.xs[step[1]], self.colliders))
            kernels = [(k, self.n2)]
        else:
            k = self._kernel((kind, step[1]), "pbd_update", [None] * 3 + [f32, f32],
                             (self.x, self.v, self.xs[step[1]], c.h, c.damp))
            kernels = [(k, self.n2)]
        return [(k, *self._launch_size(items)) for k, items in kernels]

    # --- PbdDeviceBackend ----------------------------------------------------------------
    def _enqueue(self, launch) -> None:
        kernel, global_size, local_size = launch
        self._events.append(self._cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size))

    def _timed(self, launch) -> float:
        kernel, global_size, local_size = launch
        event = self._cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size)
        event.wait()  # synchronised after every launch; the time is the device's own
        return 1e-9 * (event.profile.end - event.profile.start)

    def _write_state(self, x: np.ndarray, v: np.ndarray) -> None:
        self.queue.finish()
        self._cl.enqueue_copy(self.queue, self.x, x)
        self._cl.enqueue_copy(self.queue, self.v, v)
        self.queue.finish()

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.empty((self.n2, 4), np.float32)
        v = np.empty((self.n2, 4), np.float32)
        self._cl.enqueue_copy(self.queue, x, self.x)
        self._cl.enqueue_copy(self.queue, v, self.v)  # blocking: waits for the steps
        return x, v

    def _buffers(self) -> tuple:
        return (self.x, self.v, *self.xs, self.lam, self.colliders, self.ij, self.border)

    # --- Backend interface -----------------------------------------------------------------
    def advance(self, steps: int) -> None:
        self._events = []
        super().advance(steps)


__all__ = ["OpenCLPbdBackend"]
