"""The PBD solver (docs/pbd.md) on OpenCL: kernels/pbd_cloth.cl through pyopencl.

Host code only. Also home of what the two GPU PBD backends share (PbdDeviceBackend: the
constants, the state's conversion to and from velocity, the substep as a list of stage
launches, per-stage profiling); glsl_compute_pbd.py supplies the GL side of the same.

One substep is a fixed list of launches on an in-order queue (each sees the previous one's
writes): predict, then `iterations` Jacobi passes ping-ponging two buffers (or 12 coloured
batches per iteration), collide, update. Every launch is a kernel object whose arguments are
set once at construction, so advance() only enqueues. The device, its probe, the program
cache and the build-error report are opencl.py's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..constraints import coloured_batches
from ..errors import ClothbenchError
from ..kernel_source import read_kernel
from ..scene import Scene
from .base import Backend, BackendOptions
from .gl_context import collider_rows
from .opencl import _build, _choose_device, _cl, _context
from .opencl import probe  # noqa: F401  (the same device as the Verlet kernels)

KERNEL_FILE = "pbd_cloth.cl"


@dataclass(frozen=True)
class PbdConstants:
    """docs/pbd.md, "Constants": computed in float64 from the scene, rounded once to float32,
    exactly as the NumPy reference (numpy_pbd.py) rounds them."""

    dt: np.float32
    h: np.float32  # dt / substeps
    gh: tuple  # g * h, three components
    at: tuple  # compliance / h^2: structural, shear, bend
    rest: tuple  # rest lengths: structural, shear, bend
    damp: np.float32  # 1 - 12 b h / m, clamped at 0
    relax: np.float32  # Jacobi over-relaxation

    @classmethod
    def of(cls, scene: Scene) -> "PbdConstants":
        f32 = np.float32
        h = scene.dt / scene.substeps
        rest = scene.rest_lengths()
        return cls(
            dt=f32(scene.dt),
            h=f32(h),
            gh=tuple(f32(g * h) for g in scene.gravity),
            at=tuple(f32(c / (h * h)) for c in scene.pbd_compliance()),
            rest=(f32(rest[0]), f32(rest[4]), f32(rest[8])),
            damp=f32(max(0.0, 1.0 - 12.0 * scene.damping * h / scene.mass)),
            relax=f32(scene.relaxation),
        )


def batch_stage_name(batch) -> str:
    """The profile's name of a coloured batch: its direction and parity."""
    dr, dc = batch.direction
    return f"batch ({dr},{dc:+d}) parity {batch.parity}"


class PbdDeviceBackend(Backend):
    """What the GPU PBD backends share. A subclass builds `self.launches`, one substep as
    [(stage name, launch)], and says how to enqueue a launch, time one on its own, and move
    the (x, v) state to and from the device."""

    sweep_variants = ({"strict": True}, {"strict": False})
    has_local_size = True

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        if options.precision != "f32":
            raise ClothbenchError(f"{self.name} runs in f32 only (got {options.precision}); f64 is the numpy reference")
        if options.generic:
            raise ClothbenchError(f"the {self.name} PBD kernels are always specialised to the scene; drop --generic")
        if options.transfer is not None:
            raise ClothbenchError(f"the {self.name} PBD solver keeps its state on the device; drop --transfer")
        if options.normals:
            raise ClothbenchError(f"the {self.name} PBD solver does not compute normals; drop --save-normals")
        if options.local_size is not None and options.local_size < 1:
            raise ClothbenchError(f"local size must be >= 1, got {options.local_size}")
        self.strict = options.strict
        self.n = scene.grid
        self.n2 = scene.particles
        self.constants = PbdConstants.of(scene)
        self.jacobi = scene.pbd_method == "jacobi"
        self.batches = [] if self.jacobi else coloured_batches(self.n)
        self.launches: list[tuple[str, object]] = []  # one substep: (stage, launch)

    # --- what a subclass supplies ------------------------------------------------------
    local_size: int | None = None

    def _write_state(self, x: np.ndarray, v: np.ndarray) -> None:
        raise NotImplementedError

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _enqueue(self, launch) -> None:
        raise NotImplementedError

    def _timed(self, launch) -> float:
        """Run one launch on its own, synchronised; its time in seconds."""
        raise NotImplementedError

    def _finish(self) -> None:
        """Wait for every enqueued launch (inside whatever the device needs around calls)."""
        raise NotImplementedError

    # --- the substep as launches -------------------------------------------------------
    def _substep_plan(self):
        """One substep as (stage, what, ...) in launch order: ("predict",), ("jacobi",
        iteration, source index, target index), ("coloured", iteration, batch index),
        ("collide", buffer index), ("update", buffer index), where a buffer index names one
        of the two predicted-position buffers (predict writes 0)."""
        plan = [("predict",)]
        for it in range(self.scene.iterations):
            if self.jacobi:
                plan.append(("jacobi", it, it % 2, 1 - it % 2))
            else:
                plan += [("coloured", it, b) for b in range(len(self.batches))]
        final = self.scene.iterations % 2 if self.jacobi else 0
        if self.scene.colliders:
            plan.append(("collide", final))
        plan.append(("update", final))
        return plan

    def _launches_of(self, step) -> list:
        """The launches (one or more) of one step of the plan."""
        raise NotImplementedError

    def _plan_launches(self) -> list[tuple[str, object]]:
        return [(self.stage_of(step), launch) for step in self._substep_plan() for launch in self._launches_of(step)]

    def stage_of(self, step) -> str:
        if step[0] == "jacobi":
            return "project (jacobi)"
        if step[0] == "coloured":
            return batch_stage_name(self.batches[step[2]])
        return step[0]

    # --- Backend interface ---------------------------------------------------------------
    @property
    def mode(self) -> str:
        arithmetic = "strict" if self.strict else "fast"
        return f"{arithmetic}/pbd-{self.scene.pbd_method}/wg={self.local_size or 'auto'}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        x = np.array(pos, dtype=np.float32)
        v = np.zeros_like(x)
        # docs/pbd.md: v = (x - xp) / dt, once, in float32 as the reference does it
        v[:, :3] = (x[:, :3] - np.asarray(prev, dtype=np.float32)[:, :3]) / self.constants.dt
        self._write_state(x, v)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        x, v = self._read_state()
        prev = x.copy()
        prev[:, :3] = x[:, :3] - v[:, :3] * self.constants.dt  # docs/pbd.md: prev = x - v dt
        return x, prev

    def advance(self, steps: int) -> None:
        enqueue = self._enqueue
        for _ in range(steps * self.scene.substeps):
            for _, launch in self.launches:
                enqueue(launch)

    def profile_stages(self, steps: int) -> dict[str, float]:
        """Advance `steps` steps with a synchronisation after every launch; ms per step of
        each stage (a stage's launches summed over iterations and substeps)."""
        self._finish()
        totals: dict[str, float] = {}
        for _ in range(steps * self.scene.substeps):
            for stage, launch in self.launches:
                totals[stage] = totals.get(stage, 0.0) + self._timed(launch)
        return {stage: 1e3 * seconds / max(steps, 1) for stage, seconds in totals.items()}


class OpenCLPbdBackend(PbdDeviceBackend):
    name = "opencl"

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        cl = self._cl = _cl()
        self.local_size = options.local_size
        self._device = _choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        context = self._context = _context(self._device)
        self.queue = cl.CommandQueue(context, self._device, properties=cl.command_queue_properties.PROFILING_ENABLE)
        self.program = _build(context, read_kernel(KERNEL_FILE), self.build_options())

        mf = cl.mem_flags
        size = self.n2 * 16  # one float4 per particle
        self.x = cl.Buffer(context, mf.READ_WRITE, size)
        self.v = cl.Buffer(context, mf.READ_WRITE, size)
        self.xs = [cl.Buffer(context, mf.READ_WRITE, size) for _ in range(2)]  # Jacobi ping-pong
        # lambda: 12 per particle (Jacobi) or one per constraint (coloured)
        lam_count = 12 * self.n2 if self.jacobi else sum(len(b.i) for b in self.batches)
        self.lam = cl.Buffer(context, mf.READ_WRITE, 4 * lam_count)
        self.colliders = self._read_only_buffer(self._collider_table())
        if self.jacobi:
            self._split_jacobi()
        else:  # every batch's (i, j) pairs, concatenated, uploaded once
            pairs = np.concatenate([np.stack([b.i, b.j], axis=1) for b in self.batches]).astype(np.int32)
            self.ij = self._read_only_buffer(pairs)
            self.batch_offsets = np.cumsum([0] + [len(b.i) for b in self.batches])[:-1]

        self._kernels: dict = {}
        self.launches = self._plan_launches()
        self._events: list = []

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
        s = self.scene
        counts = (("SPHERES", len(s.spheres)), ("CYLINDERS", len(s.cylinders)), ("PLANES", len(s.planes)))
        shape = (f"-DCLOTH_N={self.n}", *(f"-DCLOTH_{kind}={count}" for kind, count in counts if count),
                 f"-DCLOTH_VECTOR_WIDTH={self.vector_width}")
        if self.strict:
            return (*shape, "-DCLOTH_STRICT", "-cl-fp32-correctly-rounded-divide-sqrt")
        return (*shape, "-cl-mad-enable")

    def _collider_table(self) -> np.ndarray:
        rows = collider_rows(self.scene)
        table = np.concatenate([rows["spheres"], rows["cylinders"], rows["planes"]])
        limit = self._device.max_constant_buffer_size
        if table.nbytes > limit:
            raise ClothbenchError(
                f"the scene's {len(self.scene.colliders)} colliders take {table.nbytes} bytes, more "
                f"than this device's {limit}-byte constant buffer; use fewer colliders"
            )
        return table if len(table) else np.zeros((1, 4), np.float32)  # OpenCL has no empty buffers

    def _read_only_buffer(self, array: np.ndarray):
        flags = self._cl.mem_flags.READ_ONLY | self._cl.mem_flags.COPY_HOST_PTR
        return self._cl.Buffer(self._context, flags, hostbuf=np.ascontiguousarray(array))

    def _kernel(self, key, name: str, dtypes, args):
        """A kernel object with its typed arguments set once (a wrongly typed one raises);
        launches with the same arguments share it."""
        if key not in self._kernels:
            k = self._cl.Kernel(self.program, name)
            k.set_scalar_arg_dtypes(list(dtypes))
            k.set_args(*args)
            limit = k.get_work_group_info(self._cl.kernel_work_group_info.WORK_GROUP_SIZE, self._device)
            if self.local_size is not None and self.local_size > limit:
                raise ClothbenchError(f"local size {self.local_size} exceeds this device's limit {limit} for {name}")
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
        # OpenCL 1.2 wants the global size a multiple of the work-group size: pad; the
        # kernels return early past their last item
        ls = self.local_size or 1
        local = None if self.local_size is None else (self.local_size,)
        return [(k, (-(-items // ls) * ls,), local) for k, items in kernels]

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

    # --- Backend interface -----------------------------------------------------------------
    @property
    def device(self) -> str:
        return self._device.name

    def advance(self, steps: int) -> None:
        self._events = []
        super().advance(steps)

    def _finish(self) -> None:
        self.queue.finish()

    def synchronize(self) -> None:
        self.queue.finish()

    def device_elapsed_ms(self) -> float | None:
        """Kernel time of the last advance() from profiling events."""
        if not self._events:
            return None
        self._cl.wait_for_events(self._events)
        return 1e-6 * sum(e.profile.end - e.profile.start for e in self._events)

    def close(self) -> None:
        if getattr(self, "queue", None) is None:
            return
        self.queue.finish()
        self._events = []
        extra = (getattr(self, name, None) for name in ("ij", "border"))  # one method has each
        for buf in (self.x, self.v, *self.xs, self.lam, self.colliders, *extra):
            if buf is not None:
                buf.release()
        self.queue = None


__all__ = ["OpenCLPbdBackend", "PbdDeviceBackend", "PbdConstants", "probe"]
