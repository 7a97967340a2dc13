"""The PBD solver (docs/pbd.md) on OpenCL: kernels/pbd_cloth.cl through pyopencl.

Host code only: the substep plan, the state conversion and the profiling are
pbd_device.PbdDeviceBackend's (shared with gl/compute_pbd.py); the device, its queue, its
probe, the program cache and the build-error report are device.py's (OpenCLDeviceMixin).

Three kinds of kernel shape (docs/pbd.md, "Launches"): `per-stage`, one substep as a fixed
list of launches on an in-order queue (each sees the previous one's writes), `one-launch`, up
to SUBSTEPS_PER_LAUNCH substeps in one launch of one work-group, and (Jacobi) `bands-R`, a
substep's predict and passes in one launch of a work-group per band of R rows, each in its own
scratch grid (temporal blocking), then the per-stage collide and update, and (coloured)
`one-launch-vectors`, one-launch's plan with each batch swept V constraints at a time on a
planar scratch grid. Every launch is a
kernel object whose arguments are set once at construction, so advance() only enqueues.

Meshes, moving colliders and pins attached to a body (docs/pbd.md, "Colliders, motion and
attached pins"): the host side is bodies.py's, shared with verlet.py, with one collider table
(and one set of pin targets) per substep, at the end of the substep; a launch that reads them
takes the index of its (first) substep in the upload, set before each enqueue (OpenCL takes a
kernel's arguments when it is enqueued). The per-substep constants go up inside advance()
(so the harness times them), bodies.STEPS_PER_UPLOAD substeps at a time.

Self-collision ([self_collision], docs/pbd.md and docs/semantics.md), only where the scene has
it (-DCLOTH_SELF_COLLISION, kernels/self_collision.cl): per substep, the last iterate's cells
are keyed and sorted (self_contact.py), and pbd_self_collision reads the iterate, pushes the
pairs apart, collides, and writes the other predicted-position buffer, which update then reads
(in place of collide). Only the per-stage shape is offered there.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Pbd
from clothbench.backends.base import BackendOptions, Capabilities
from clothbench.backends.opencl.bodies import OpenCLBodiesMixin
from clothbench.backends.opencl.self_contact import SelfContact, include_text
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    arithmetic_options,
    build_program,
    program_source,
    shape_options,
)
from clothbench.backends.opencl.verlet_shapes import tuning_key
from clothbench.backends.tuning import sweeps_key, turn_steps
from clothbench.backends.pbd_device import PbdDeviceBackend

KERNEL_FILE = "pbd_cloth.cl"
# The kernel shapes, chosen per device and scene by measurement (backends/tuning.py):
# `per-stage`, one launch per stage (predict, each Jacobi pass or coloured batch, collide,
# update), and `one-launch`, whole substeps in one launch of one work-group (pbd_substeps):
# one core instead of all, no launch per pass. One-launch is offered up to this many
# particles, past which one core cannot win (docs/pbd.md, "Launches").
ONE_LAUNCH_MAX_PARTICLES = 256 * 256
SHAPES = ("per-stage", "one-launch")
# Jacobi only: `bands-R`, a substep's predict and every pass in one launch, a work-group per
# band of R rows computing 2 * iterations rows either side again (pbd_jacobi_bands). Offered
# where there are at least two bands (the last may be short) and every band's scratch grid
# (two planar grids and 12 multipliers per particle, 24 with Chebyshev) fits
# BANDS_SCRATCH_LIMIT bytes together.
BAND_ROWS = (8, 16, 32, 64, 128)
BANDS_SCRATCH_LIMIT = 512 << 20
# The planar program's layout (pbd_cloth.cl): floats of room before and after the bands' grids
# (CLOTH_PLANAR_MARGIN: an edge vector of jacobi_lanes reads up to two floats past a grid, and
# drops what it read), and the padding of each plane of a grid or of the multipliers
# (CLOTH_PLANE_PAD: with planes n * n floats apart, a particle's 12 multipliers and 4
# coordinates fell in one cache set whenever n * n * 4 bytes is a multiple of 4 KiB).
PLANAR_MARGIN_FLOATS = 16
PLANE_PAD_FLOATS = 16


def planar_plane(particles: int) -> int:
    """Floats from one plane of a planar grid (or of the multipliers) to the next."""
    return particles + PLANE_PAD_FLOATS


def band_scratch_bytes(particles: int, chebyshev: bool) -> tuple[int, int]:
    """One band's scratch: (its two planar grids, its multipliers: 12 planes, twice with
    Chebyshev), in bytes."""
    plane = planar_plane(particles)
    return 2 * 16 * plane, (2 if chebyshev else 1) * 12 * 4 * plane


# Substeps per launch of pbd_substeps: bounds how long one launch holds the device.
SUBSTEPS_PER_LAUNCH = 32
# the argument index of the substep count (the first substep's index next) of pbd_substeps and
# pbd_coloured_vectors
SUBSTEPS_ARG = {"one-launch": 19, "one-launch-vectors": 11}
# Coloured only: `one-launch-vectors`, whole substeps in one launch of one work-group like
# one-launch, on a planar scratch copy of the positions, each batch V constraints at a time
# (pbd_coloured_vectors).
VECTOR_SHAPES = ("one-launch-vectors",)


class OpenCLPbdBackend(OpenCLBodiesMixin, OpenCLDeviceMixin, PbdDeviceBackend):
    name = "opencl"
    capabilities = Capabilities(
        local_size=True,
        device=True,
        shapes=True,
        sweep_variants=({"strict": True}, {"strict": False}),
        meshes=("pbd",),
        moving_colliders=("pbd",),
        boxes=("pbd",),
        self_collision=("pbd",),
        mesh_collisions=("accelerated", "naive"),  # verlet.py's default, for the same reason
    )

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self._open_queue(options)
        cl, context = self._cl, self._context
        # meshes, motion, attached pins (bodies.py): one table per substep, at its end
        self._open_bodies(solver.dt / solver.substeps, SUBSTEPS_PER_LAUNCH)
        # [self_collision]: its numbers and sort buffers; None: no pass, no code
        self._contact = SelfContact.of(scene, cl, context)
        generated = {"mesh_colliders": self._mesh_source, "self_collision": lambda: include_text(self._contact)}
        self._source = program_source(KERNEL_FILE, generated)
        self.program = build_program(context, self._source, self.build_options())

        mf = cl.mem_flags
        size = self.n2 * 16  # one float4 per particle
        self.x = cl.Buffer(context, mf.READ_WRITE, size)
        self.v = cl.Buffer(context, mf.READ_WRITE, size)
        self.xs = [cl.Buffer(context, mf.READ_WRITE, size) for _ in range(2)]  # Jacobi ping-pong
        self.lam = cl.Buffer(context, mf.READ_WRITE, 4 * self.lambda_count)
        # Chebyshev: the lambdas ping-pong as the iterates do (a pass extrapolates from the one before)
        second = cl.Buffer(context, mf.READ_WRITE, 4 * self.lambda_count) if self.chebyshev else self.lam
        self.lams = [self.lam, second]
        self.colliders = self._colliders  # the table: fixed, or room for the per-substep ones
        self._step_kernels: list = []  # (kernel, argument index) of each launch's substep index
        self.ij = self.border = self.offsets = None
        if self.jacobi:
            self._split_jacobi()
        else:
            self.ij = self._read_only_buffer(self.batch_pairs)
            starts = np.append(self.batch_offsets, len(self.batch_pairs)).astype(np.int32)  # and the end
            self.offsets = self._read_only_buffer(starts)

        self._kernels: dict = {}
        # per-stage: advance() in that shape, and profile_stages() in every shape
        self.launches = self._per_stage = self._plan_launches()
        self.one_launch, self.substeps_kernel, self.substeps_kernels = False, None, {}
        # the planar program (bands, vectors) and the scratch grids, built when first used
        self.planar_program = self.band_scratch = self.vector_scratch = None
        # the Jacobi passes' Chebyshev weights, one per iteration (all 1 without): bands, one-launch
        self.omega_buffer = self._read_only_buffer(np.array(self.constants.omega, np.float32))
        key = tuning_key(self._device, scene, options, self._source, self.mesh_collision)
        key.update(sweeps_key(solver))  # Chebyshev too: a second multiplier buffer, and the bands' scratch doubles
        self._use_shape(self.pick_shape(key, self._time_shape))

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver: Pbd | None = None) -> tuple[str, ...]:
        """The shapes for `scene`; with `solver`, only those its method has (bands: Jacobi;
        one-launch-vectors: coloured)."""
        if scene.self_collision is not None:
            return SHAPES[:1]  # the pass is a launch of its own, between the passes and update
        small = scene.particles <= ONE_LAUNCH_MAX_PARTICLES
        shapes = SHAPES if small else SHAPES[:1]
        if (solver is None or solver.method != "jacobi") and small:
            shapes += VECTOR_SHAPES
        if solver is not None and solver.method != "jacobi":
            return shapes
        per_band = sum(band_scratch_bytes(scene.particles, solver is not None and solver.chebyshev_rho > 0))
        return shapes + tuple(
            f"bands-{rows}"
            for rows in BAND_ROWS
            if scene.grid > rows and -(-scene.grid // rows) * per_band <= BANDS_SCRATCH_LIMIT
        )

    def _use_shape(self, name: str) -> None:
        self.one_launch = name in SUBSTEPS_ARG
        if self.one_launch:
            if name not in self.substeps_kernels:
                self.substeps_kernels[name] = (
                    self._vectors_kernel() if name in VECTOR_SHAPES else self._substeps_kernel()
                )
            self.substeps_kernel, self.substeps_arg = self.substeps_kernels[name], SUBSTEPS_ARG[name]
        self.effective_local_size = self.substeps_local_size if self.one_launch else self.local_size
        self.launches, self.stage_launches = self._per_stage, None
        if name.startswith("bands-"):
            self.launches, self.stage_launches = self._band_launches(int(name[len("bands-") :])), self._per_stage
            self.effective_local_size = self.substeps_local_size

    def _band_launches(self, rows: int) -> list:
        """One substep in the bands-`rows` shape: pbd_jacobi_bands (predict and every pass),
        then the per-stage collide and update on the predicted-position buffer 0."""
        bands = -(-self.n // rows)
        if self.band_scratch is None:  # once, for the most bands any offered shape has (within the limit)
            offered = [s for s in self.kernel_shapes(self.scene, self.options, self.solver) if s.startswith("bands-")]
            most = max([-(-self.n // int(s[len("bands-") :])) for s in offered] + [bands])
            mf = self._cl.mem_flags
            grids, multipliers = band_scratch_bytes(self.n2, self.chebyshev)
            margins = 2 * 4 * PLANAR_MARGIN_FLOATS  # before and after the grids, 4 bytes a float
            self.band_scratch = (
                self._cl.Buffer(self._context, mf.READ_WRITE, most * grids + margins),
                self._cl.Buffer(self._context, mf.READ_WRITE, most * multipliers),
            )
        self.substeps_local_size = self._default_substeps_local_size()
        c, f32, i32 = self.constants, np.float32, np.int32
        step, step_dtypes = self._step_constants()
        args = (
            self.x,
            self.v,
            self.xs[0],
            *self.band_scratch,
            self.omega_buffer,
            *step,
            c.relax,
            i32(self.solver.iterations),
            i32(rows),
        )
        dtypes = [None] * 6 + step_dtypes + [f32, i32, i32]
        pins = self._body_args(0)[: self._per_step] + ((self._pin_slot, self._pin_target) if self._attached else ())
        k = self._kernel(("bands", rows), "pbd_jacobi_bands", dtypes, args, pins, self._planar_program())
        # the default group (the device's largest) within this kernel's limit, as for one-launch
        limit = k.get_work_group_info(self._cl.kernel_work_group_info.WORK_GROUP_SIZE, self._device)
        ls = self.substeps_local_size = min(self.substeps_local_size, limit)
        # the band kernel leaves the final iterate in buffer 0, where the plan's ends may read 1
        ends = [(step[0], 0) for step in self._substep_plan() if step[0] in ("collide", "update")]
        return [("project (jacobi, bands)", (k, (bands * ls,), (ls,)))] + [
            (self.stage_of(step), launch) for step in ends for launch in self._launches_of(step)
        ]

    timing_repeats = 3

    def _timing_steps(self) -> int:
        return turn_steps(self.n2, least=2, most=64, work=1 << 16)

    def _split_jacobi(self) -> None:
        """The Jacobi pass's two launches: the interior (rows and columns 2 .. n-3) in vectors
        of V particles of a row, V the device's preferred float width (4, 8 or 16), the last
        of a row overlapping the one before it where V does not divide n - 4, and every
        particle those vectors do not cover (the 2-wide ring, or every particle when the
        interior is narrower than V), from an index list uploaded once."""
        n, v = self.n, self.vector_width
        per_row = -(-(n - 4) // v) if n - 4 >= v else 0
        self.interior_vectors = per_row * (n - 4)
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : n - 2] = per_row > 0
        self.border_particles = np.flatnonzero(~covered).astype(np.int32)
        self.border = self._read_only_buffer(self.border_particles)

    @property
    def vector_width(self) -> int:
        preferred = self._device.preferred_vector_width_float
        return 16 if preferred >= 16 else 8 if preferred >= 8 else 4

    def build_options(self) -> tuple[str, ...]:
        method = ("-DCLOTH_CHEBYSHEV",) if self.chebyshev else () if self.jacobi else ("-DCLOTH_COLOURED",)
        shape = (*shape_options(self.scene, self.vector_width), *self._body_options())
        contact = self._contact.build_options if self._contact is not None else ()
        return (*shape, *arithmetic_options(self.strict), *method, *contact)

    def _default_substeps_local_size(self) -> int:
        """The one work-group of pbd_substeps: --local-size, else one work item on a CPU
        (it runs the vectors itself; PoCL does not vectorise across work items here) and the
        device's largest group (at most 1024) elsewhere."""
        if self.local_size:
            return self.local_size
        if self._device.type & self._cl.device_type.CPU:
            return 1
        return min(self._device.max_work_group_size, 1024)

    def _substeps_kernel(self):
        """pbd_substeps with its arguments set (the substep count is set per launch), and its
        work-group size (substeps_local_size) within the kernel's limit on this device."""
        self.substeps_local_size = self._default_substeps_local_size()
        c, f32, i32 = self.constants, np.float32, np.int32
        step, step_dtypes = self._step_constants()
        unused = self._unused = self._read_only_buffer(np.zeros(1, np.int32))  # the other method's tables: never read
        border = self.border if self.jacobi else unused
        count = len(self.border_particles) if self.jacobi else 0
        ij = unused if self.ij is None else self.ij
        offsets = unused if self.offsets is None else self.offsets
        args = (
            self.x,
            self.v,
            *self.xs,
            *self.lams,
            self.omega_buffer,
            border,
            i32(count),
            ij,
            offsets,
            *step,
            c.relax,
            c.damp,
            self.colliders,
            i32(self.solver.iterations),
            i32(1),
        )  # the last: substeps, set per launch
        dtypes = [None] * 8 + [i32, None, None] + step_dtypes + [f32, f32, None, i32, i32]
        return self._whole_substeps_kernel(self.program, "pbd_substeps", dtypes, args)

    def _step_constants(self) -> tuple[tuple, list]:
        """(values, dtypes) of h, g h, the rest lengths and `at`, as float, float4, float4,
        float4: the run of constants the substep, band and vector kernels take alike."""
        c, make4 = self.constants, self._cl.cltypes.make_float4
        float4 = self._cl.cltypes.float4
        return (c.h, make4(*c.gh, 0.0), make4(*c.rest, 0.0), make4(*c.at, 0.0)), [np.float32, float4, float4, float4]

    def _whole_substeps_kernel(self, program, name: str, dtypes, args):
        """Kernel `name` of the one-work-group shapes with `args` and the bodies' arguments set
        (the first substep's index is set per launch), substeps_local_size within its limit."""
        k = self._cl.Kernel(program, name)
        k.set_scalar_arg_dtypes(list(dtypes) + self._body_dtypes())
        k.set_args(*args, *self._body_args(0))
        limit = k.get_work_group_info(self._cl.kernel_work_group_info.WORK_GROUP_SIZE, self._device)
        if self.local_size and self.local_size > limit:
            raise ClothbenchError(f"local size {self.local_size} exceeds this device's limit {limit} for {name}")
        self.substeps_local_size = min(self.substeps_local_size, limit)
        return k

    def _planar_program(self):
        """The same source built with planar scratch iterates (CLOTH_PLANAR, pbd_cloth.cl): the
        bands' and the vector sweep's program, built when first asked for."""
        if self.planar_program is None:
            layout = (f"-DCLOTH_PLANAR_MARGIN={PLANAR_MARGIN_FLOATS}", f"-DCLOTH_PLANE_PAD={PLANE_PAD_FLOATS}")
            self.planar_program = build_program(
                self._context, self._source, (*self.build_options(), "-DCLOTH_PLANAR", *layout)
            )
        return self.planar_program

    def _vectors_kernel(self):
        """pbd_coloured_vectors with its arguments set (the substep count per launch), on its
        scratch: one planar grid and one multiplier per particle per batch."""
        self.substeps_local_size = self._default_substeps_local_size()
        cl, c, f32, i32 = self._cl, self.constants, np.float32, np.int32
        step, step_dtypes = self._step_constants()
        plane = planar_plane(self.n2)
        self.vector_scratch = (
            cl.Buffer(self._context, cl.mem_flags.READ_WRITE, 16 * plane),
            cl.Buffer(self._context, cl.mem_flags.READ_WRITE, 48 * plane),
        )
        args = (
            self.x,
            self.v,
            *self.vector_scratch,
            *step,
            c.damp,
            self.colliders,
            i32(self.solver.iterations),
            i32(1),
        )
        dtypes = [None] * 4 + step_dtypes + [f32, None, i32, i32]
        return self._whole_substeps_kernel(self._planar_program(), "pbd_coloured_vectors", dtypes, args)

    def _kernel(self, key, name: str, dtypes, args, bodies: tuple = (), program=None):
        """A kernel object with its typed arguments set once (a wrongly typed one raises);
        launches with the same arguments share it. `bodies`: the _body_args() it takes after
        `args` (the substep index first, where the scene moves, set per substep by advance());
        `program`: where the kernel is (default: self.program)."""
        if key not in self._kernels:
            k = self._cl.Kernel(program or self.program, name)
            body_dtypes = [np.int32 if isinstance(a, np.int32) else None for a in bodies]  # index, buffers
            k.set_scalar_arg_dtypes(list(dtypes) + body_dtypes)
            k.set_args(*args, *bodies)
            self._check_local_size(k, name)
            self._kernels[key] = k
            if bodies and self._per_step:
                self._step_kernels.append((k, len(args)))
        return self._kernels[key]

    def _launches_of(self, step) -> list:
        """[(kernel, global size, local size)] of one step of the plan."""
        c, f32, i32 = self.constants, np.float32, np.int32
        float4 = self._cl.cltypes.float4
        make4 = self._cl.cltypes.make_float4
        kind = step[0]
        if kind == "predict":
            # the substep index where the scene moves, and the attached pins' buffers (no meshes)
            pins = self._body_args(0)[: self._per_step] + ((self._pin_slot, self._pin_target) if self._attached else ())
            k = self._kernel(
                kind,
                "pbd_predict",
                [None] * 3 + [f32, float4],
                (self.x, self.v, self.xs[0], c.h, make4(*c.gh, 0.0)),
                pins,
            )
            kernels = [(k, self.n2)]
        elif kind == "jacobi":
            _, it, src, dst = step
            lam_in, lam_out = self.lams[it % 2], self.lams[1 - it % 2]
            args = (
                self.xs[src],
                self.xs[dst],
                lam_in,
                lam_out,
                i32(it),
                make4(*c.rest, 0.0),
                make4(*c.at, 0.0),
                c.relax,
                c.omega[it],
            )
            dtypes = [None] * 4 + [i32, float4, float4, f32, f32]
            border = len(self.border_particles)
            kernels = [
                (
                    self._kernel(
                        (kind, "border", it),
                        "pbd_jacobi_border",
                        dtypes + [None, i32],
                        args + (self.border, i32(border)),
                    ),
                    border,
                )
            ]
            if self.interior_vectors:
                interior = self._kernel((kind, "interior", it), "pbd_jacobi_interior", dtypes, args)
                kernels.insert(0, (interior, self.interior_vectors))
        elif kind == "coloured":
            _, it, b = step
            batch, first = self.batches[b], i32(it == 0)
            k = self._kernel(
                (kind, b, first),
                "pbd_coloured",
                [None] * 3 + [i32, i32, i32, f32, f32],
                (
                    self.xs[0],
                    self.ij,
                    self.lam,
                    i32(self.batch_offsets[b]),
                    i32(len(batch.i)),
                    first,
                    c.rest[batch.kind],
                    c.at[batch.kind],
                ),
            )
            kernels = [(k, len(batch.i))]
        elif kind == "self collision":
            _, src, dst = step
            meshes = self._body_args(0)[: self._per_step + 2 * bool(self._meshes)]  # no pins: predict's
            sizes = self._launch_size
            return self._contact.row_launches(self._kernel, sizes, self.xs[src], self.xs[dst], self.colliders, meshes)
        elif kind == "collide":
            meshes = self._body_args(0)[: self._per_step + 2 * bool(self._meshes)]  # no pins: predict's
            k = self._kernel((kind, step[1]), "pbd_collide", [None, None], (self.xs[step[1]], self.colliders), meshes)
            kernels = [(k, self.n2)]
        else:
            k = self._kernel(
                (kind, step[1]), "pbd_update", [None] * 3 + [f32, f32], (self.x, self.v, self.xs[step[1]], c.h, c.damp)
            )
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
        once = dict.fromkeys(self.lams)  # without Chebyshev both entries are one buffer
        return (
            self.x,
            self.v,
            *self.xs,
            *once,
            self.ij,
            self.border,
            self.offsets,
            self.omega_buffer,
            getattr(self, "_unused", None),
            *(self.band_scratch or ()),
            *(self.vector_scratch or ()),
            *self._body_buffers(),
            *(self._contact.buffers() if self._contact is not None else ()),
        )

    # --- Backend interface -----------------------------------------------------------------
    def _motion_block(self) -> int:
        return self._upload_steps if self._per_step else 0

    def _upload_motion(self, first: int, count: int) -> None:
        self._clock = first  # bodies.py's count: the tables and pin targets from substep `first`
        self._upload_step_constants(count)

    def _use_substep(self, j: int) -> None:
        for k, index in self._step_kernels:  # predict's and collide's substep index
            k.set_arg(index, np.int32(j))

    def advance(self, steps: int) -> None:
        self._events = []
        if not self.one_launch:
            super().advance(steps)
            return
        for count in self._blocks(steps):
            self._advance_in_launches(count)

    def _advance_in_launches(self, substeps: int) -> None:
        """pbd_substeps, up to SUBSTEPS_PER_LAUNCH substeps a launch."""
        k, ls = self.substeps_kernel, self.effective_local_size
        for done in range(0, substeps, SUBSTEPS_PER_LAUNCH):
            k.set_arg(self.substeps_arg, np.int32(min(SUBSTEPS_PER_LAUNCH, substeps - done)))
            if self._per_step:
                k.set_arg(self.substeps_arg + 1, np.int32(done))
            self._events.append(self._cl.enqueue_nd_range_kernel(self.queue, k, (ls,), (ls,)))


__all__ = ["OpenCLPbdBackend"]
