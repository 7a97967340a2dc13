"""The VBD solver (docs/vbd.md) on OpenCL: kernels/vbd_cloth.cl through pyopencl.

Host code only; the step is the kernel file's and docs/vbd.md's. A substep is a fixed list of
launches on an in-order queue (each sees the one before): predict, then per iteration one
launch per vertex colour (and with Chebyshev one extrapolation), collide, update. Every launch
is a kernel object whose arguments are set once at construction, so advance() only enqueues;
the numbers are VbdConstants' (model/kernel_inputs.py).

Kernel shapes (chosen per device and scene by measurement, backends/tuning.py; docs/vbd.md,
"Kernel shapes"): `gather`, the sweeps on the float4 iterate, one work item per particle of a
colour through an index list of the particles sorted by colour (the runtime's work-item
vectoriser, where it has one, gathers each neighbour); and `planes/vW[/wg=L]`, the sweeps on
planar copies, W particles of a colour (every other float of a row) per work item in explicit
vectors, the rest of the colour one per work item (kernels/vbd_cloth.cl, "The planes shapes"):
the predict writes the planes and the update, which collides too, reads them. Every lane does
one particle's operations in the scalar order, so a strict build's bits are the same in each.

Meshes, moving colliders and pins attached to a body: bodies.py's host side, as the PBD
solver uses it, one collider table (and set of pin targets) per substep, at its end; predict
and collide take the substep's index in the upload, set before each substep is enqueued.

Self-collision ([self_collision], docs/vbd.md), only where the scene has it
(-DCLOTH_SELF_COLLISION, kernels/self_collision.cl): per substep after the last sweep (and
Chebyshev), the iterate's cells are keyed and sorted and pbd_self_collision pushes the pairs
apart and collides into y (which the sweeps no longer read), in place of vbd_collide; the
update reads y. self_contact.py's row_launches, as the PBD solver's.
"""

from __future__ import annotations

import os
import re

import numpy as np

from clothbench.model.constraints import VERTEX_COLOURS, vertex_colours
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import Backend, BackendOptions, Capabilities
from clothbench.model.kernel_inputs import VbdConstants
from clothbench.backends.opencl.bodies import OpenCLBodiesMixin
from clothbench.backends.opencl.self_contact import SelfContact, include_text
from clothbench.backends.opencl.verlet_shapes import tuning_key
from clothbench.backends.tuning import sweeps_key, turn_steps
from clothbench.backends.pbd_device import position_state, velocity_state
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    choose_device,
    arithmetic_options,
    build_program,
    program_source,
    shape_options,
)

KERNEL_FILE = "vbd_cloth.cl"
# the sweep kernel reads no vectors; shape_options wants a width, and the program ignores it
SCALAR = 1
# the kernel shapes (module docstring): `gather`, the default, and the planes shapes
GATHER = "gather"
VECTOR_WIDTHS = (16, 8, 4)  # the planes shape's lanes: the device's native float width, if one of these
# the vector sweep's work-groups besides the runtime's choice: PoCL 3.1 chose a slow one (1.8x
# at 256^2 on the Zen 4, 2026-12-05: results/vbd-shapes/)
PLANES_WORK_GROUPS = (4,)
PLANE_PAD = 16  # floats after each plane of the planes shape's copies (PLANE in the kernel)
_PLANES = re.compile(r"^planes/v(\d+)(?:/wg=(\d+))?$")


def planes_shapes(device, scene: Scene, options: BackendOptions) -> tuple[str, ...]:
    """The planes shapes on `device` for `scene`: planes/vW (W its native float width) with the
    runtime's work-groups and with each of PLANES_WORK_GROUPS (not where --local-size fixes
    them); none where W is not one of VECTOR_WIDTHS or no interior row has W particles of a colour."""
    width = int(device.native_vector_width_float)
    if width not in VECTOR_WIDTHS or interior_count(scene.grid, 2) < width:
        return ()
    groups = () if options.local_size else PLANES_WORK_GROUPS
    return (f"planes/v{width}", *(f"planes/v{width}/wg={g}" for g in groups))


def parse_planes(name: str) -> tuple[int, int | None] | None:
    """(lanes, work-group or None) of a planes shape's name; None for another shape."""
    m = _PLANES.match(name)
    return (int(m.group(1)), int(m.group(2)) if m.group(2) else None) if m else None


def interior_count(n: int, first: int) -> int:
    """The particles of one colour in an interior row whose first interior column of the colour
    is `first` (2 or 3): every other column up to n - 3 (INTERIOR_COUNT in the kernel)."""
    return max(0, ((n - 3) - first) // 2 + 1)


def vector_rest(n: int, width: int) -> np.ndarray:
    """Whether each particle is left to vbd_sweep_rest by the planes shape's vector launches:
    vbd_sweep_vectors takes every interior particle (rows and columns 2 .. n-3) of a colour in
    the rows that hold at least `width` of them (kernels/vbd_cloth.cl, FIRST_COLUMN)."""
    rest = np.ones((n, n), bool)
    for row in range(2, n - 2):
        for bit in (0, 1):
            first = 2 + ((bit + row // 2) & 1)
            if interior_count(n, first) >= width:
                rest[row, first : n - 2 : 2] = False
    return rest.reshape(-1)


class OpenCLVbdBackend(OpenCLBodiesMixin, OpenCLDeviceMixin, Backend):
    name = "opencl"
    capabilities = Capabilities(
        local_size=True,
        device=True,
        shapes=True,  # gather and the planes shapes (kernel_shapes)
        sweep_variants=({"strict": True}, {"strict": False}),
        meshes=("vbd",),
        moving_colliders=("vbd",),
        boxes=("vbd",),  # vbd_collide is collide.cl's, which the kinds table gives every kind
        self_collision=("vbd",),  # after the sweeps, before the colliders (docs/vbd.md)
        mesh_collisions=("accelerated", "naive"),  # verlet.py's default, for the same reason
    )

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.strict = options.strict
        self.n2 = scene.particles
        self.constants = VbdConstants.of(scene, solver)
        self.chebyshev = solver.chebyshev_rho > 0
        self._open_queue(options)
        cl, context = self._cl, self._context
        self._open_bodies(solver.dt / solver.substeps, 1)  # one table per substep, at its end
        # [self_collision]: its numbers and sort buffers (self_contact.py); None: no pass, no code
        self._contact = SelfContact.of(scene, cl, context)
        # the one program: what it was built from, kept to say what a scene compiles
        generated = {"mesh_colliders": self._mesh_source, "self_collision": lambda: include_text(self._contact)}
        self.source = program_source(KERNEL_FILE, generated)
        self.program = build_program(context, self.source, self.build_options())

        size = self.n2 * 16  # one float4 per particle
        buffer = lambda: cl.Buffer(context, cl.mem_flags.READ_WRITE, size)  # noqa: E731
        self.x, self.v, self.xs, self.y = buffer(), buffer(), buffer(), buffer()
        # Chebyshev: the inputs of the last two sweeps, taking turns
        self.before = (buffer(), buffer()) if self.chebyshev else ()
        # every particle, by colour (the sweep's order); a launch per colour reads its range
        colour = vertex_colours(scene.grid)
        self.order = self._read_only_buffer(np.argsort(colour, kind="stable").astype(np.int32))
        self.colour_counts = np.bincount(colour, minlength=VERTEX_COLOURS)
        self.substeps_done = 0  # since the last upload(): the clock of moving bodies
        self.planes = None  # the planes shape's copies and program, made when first used (_use_planes)
        key = tuning_key(self._device, scene, options, self.source, self.mesh_collision)
        key.update(sweeps_key(solver))
        self._use_shape(self.pick_shape(key, self._time_shape))

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver: Vbd | None = None) -> tuple[str, ...]:
        if scene.self_collision is not None:
            # the default only: the pass (its own launches: keys, sort, push) costs more than the
            # sweeps at the grids it is used on, so timing the shapes would mostly time the pass
            return (GATHER,)
        device = choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        return (GATHER, *planes_shapes(device, scene, options))

    def _use_shape(self, name: str) -> None:
        self._step_kernels: list = []  # (kernel, argument index) of each launch's substep index
        self._shape_program = self.program
        planes = parse_planes(name)
        if planes is not None:
            self._use_planes(planes[0])
        self.launches = self._plan_launches(planes)

    def _use_planes(self, width: int) -> None:
        """The planes shape's program (the same source with CLOTH_VECTOR_WIDTH = width), its
        planar copies and the index list of each colour's rest, made when first used."""
        if self.planes is None:
            cl, context = self._cl, self._context
            self.planes_program = build_program(context, self.source, self.build_options(width))
            plane = (self.n2 + PLANE_PAD) * 4
            buffer = lambda planes: cl.Buffer(context, cl.mem_flags.READ_WRITE, planes * plane)  # noqa: E731
            self.planes = (buffer(3), buffer(3), buffer(3), buffer(1))  # the iterate, y, x; inverse masses
            self.planes_before = (buffer(3), buffer(3)) if self.chebyshev else ()
            rest = vector_rest(self.scene.grid, width)
            colour = vertex_colours(self.scene.grid)
            ordered = np.argsort(colour, kind="stable")
            ordered = ordered[rest[ordered]]
            self.rest_order = self._read_only_buffer(ordered.astype(np.int32))
            self.rest_counts = np.bincount(colour[ordered], minlength=VERTEX_COLOURS)
        self._shape_program = self.planes_program

    timing_repeats = 3

    def _timing_steps(self) -> int:
        """A few milliseconds of sweeps at every grid (10 sweeps, one substep: 12 steps at 64^2)."""
        sweeps = self.n2 * max(self.solver.iterations, 1) * self.solver.substeps
        return turn_steps(sweeps, least=2, most=64, work=1 << 19)

    def build_options(self, width: int = SCALAR) -> tuple[str, ...]:
        """`width`: the planes shape's lanes (CLOTH_VECTOR_WIDTH), which no other kernel reads."""
        contact = self._contact.build_options if self._contact is not None else ()
        return (*shape_options(self.scene, width), *self._body_options(), *arithmetic_options(self.strict), *contact)

    def _kernel(self, name: str, dtypes: list, args: tuple, bodies: tuple = ()):
        """Kernel `name` with its typed arguments set once; `bodies`: the _body_args() it takes
        after `args` (the substep index first, where the scene moves, set per substep). Every
        launch has its own: the plan sets each kernel's arguments once."""
        k = self._cl.Kernel(self._shape_program, name)
        k.set_scalar_arg_dtypes(list(dtypes) + [np.int32 if isinstance(a, np.int32) else None for a in bodies])
        k.set_args(*args, *bodies)
        self._check_local_size(k, name)
        if bodies and self._per_step:
            self._step_kernels.append((k, len(args)))
        return k

    def _grid_launch(self, columns: int, rows: int, group: int | None) -> tuple[tuple[int, int], tuple | None]:
        """(global, local) size of a 2-D launch of `columns` by `rows` work items: work-groups
        of (`group` or --local-size, 1), or the runtime's choice."""
        ls = group or self.local_size
        return (-(-columns // (ls or 1)) * (ls or 1), rows), None if ls is None else (ls, 1)

    def _plan_launches(self, planes: tuple[int, int | None] | None) -> list:
        """One substep as [(stage, (kernel, global size, local size))] in launch order: in the
        gather shape, or (`planes`: lanes, work-group) in a planes shape, whose predict writes
        the planes the sweeps run on and whose update (with the colliders) reads them."""
        c, f32, i32 = self.constants, np.float32, np.int32
        make4, float4 = self._cl.cltypes.make_float4, self._cl.cltypes.float4
        plan = []

        def launch(stage: str, kernel, items: int) -> None:
            plan.append((stage, (kernel, *self._launch_size(items))))

        pins = self._body_args(0)[: self._per_step] + ((self._pin_slot, self._pin_target) if self._attached else ())
        step = (c.h, make4(*c.gh2, 0.0))
        if planes:
            predict = self._kernel(
                "vbd_predict_planes", [None] * 6 + [f32, float4], (self.x, self.v, *self.planes, *step), pins
            )
        else:
            predict = self._kernel(
                "vbd_predict", [None] * 4 + [f32, float4], (self.x, self.v, self.xs, self.y, *step), pins
            )
        launch("predict", predict, self.n2)
        sweeps = self._sweep_launches(planes)
        name, iterate, before, weights = "vbd_chebyshev", self.xs, self.before, ()
        if planes:  # on the planes, with their inverse masses
            name, iterate, before, weights = "vbd_chebyshev_planes", self.planes[0], self.planes_before, self.planes[3:]
        chebyshev = [None] * (2 + len(weights)) + [f32, i32]

        def extrapolate(before_buffer, omega, apply: int) -> None:
            args = (iterate, before_buffer, *weights, omega, i32(apply))
            launch("chebyshev", self._kernel(name, chebyshev, args), self.n2)

        if self.chebyshev:  # the first sweep's input: the predicted iterate
            extrapolate(before[0], f32(1), 0)
        for it in range(self.solver.iterations):
            plan.extend(("sweep", sized) for sized in sweeps)
            if self.chebyshev:  # extrapolate from sweep it - 1's input (none after sweep 0), keep sweep it + 1's
                extrapolate(before[(it + 1) % 2], c.omega[it], it > 0)
        meshes = self._body_args(0)[: self._per_step + 2 * bool(self._meshes)]  # no pins: predict's
        if planes:  # collide (where the scene has colliders) and update, from the planes
            args = (self.x, self.v, self.planes[0], c.h, self._colliders)
            launch("update", self._kernel("vbd_finish_planes", [None] * 3 + [f32, None], args, meshes), self.n2)
            return plan
        final = self.xs  # the iterate the update reads
        if self._contact is not None:  # the pass and then the colliders, from the final iterate into y
            fresh = lambda _key, *rest: self._kernel(*rest)  # noqa: E731 (here every launch has a kernel of its own)
            for sized in self._contact.row_launches(fresh, self._launch_size, self.xs, self.y, self._colliders, meshes):
                plan.append(("self collision", sized))
            final = self.y  # no longer read: the sweeps are done
        elif self.scene.colliders or self.scene.meshes:
            launch("collide", self._kernel("vbd_collide", [None, None], (self.xs, self._colliders), meshes), self.n2)
        update = self._kernel("vbd_update", [None] * 3 + [f32], (self.x, self.v, final, c.h))
        launch("update", update, self.n2)
        return plan

    def _sweep_launches(self, planes: tuple[int, int | None] | None) -> list:
        """[(kernel, global size, local size)] of one sweep, colour by colour: in the gather
        shape one launch a colour; in a planes shape its vectors and then its rest."""
        c, f32, i32 = self.constants, np.float32, np.int32
        numbers = (c.mh2, c.bh, c.k, self._cl.cltypes.make_float4(*c.rest, 0.0))
        numbers_dtypes = [f32, f32, f32, self._cl.cltypes.float4]
        sweeps, first = [], 0
        for colour, count in enumerate(self.colour_counts if not planes else self.rest_counts):
            if planes:
                width, group = planes
                parity, bit = i32(colour >> 1), i32(colour & 1)
                rows = interior_count(self.scene.grid, 2 + int(parity))  # interior rows of the parity
                vectors = -(-interior_count(self.scene.grid, 2) // width)  # the most a row has
                if rows and vectors:
                    args = (*self.planes, parity, bit, *numbers)
                    kernel = self._kernel("vbd_sweep_vectors", [None] * 4 + [i32, i32] + numbers_dtypes, args)
                    sweeps.append((kernel, *self._grid_launch(vectors, rows, group)))
                if count:  # the colour's rest
                    args = (*self.planes, self.rest_order, i32(first), i32(count), *numbers)
                    kernel = self._kernel("vbd_sweep_rest", [None] * 5 + [i32, i32] + numbers_dtypes, args)
                    sweeps.append((kernel, *self._launch_size(int(count))))
            else:
                args = (self.xs, self.y, self.x, self.order, i32(first), i32(count), *numbers)
                kernel = self._kernel("vbd_sweep", [None] * 4 + [i32, i32] + numbers_dtypes, args)
                sweeps.append((kernel, *self._launch_size(int(count))))
            first += int(count)
        return sweeps

    # --- Backend interface -----------------------------------------------------------------
    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.substeps_done = 0  # the uploaded state is at t = 0: moving bodies start over
        x, v = velocity_state(pos, prev, self.constants.dt)  # docs/vbd.md, as PBD's
        self.queue.finish()
        self._cl.enqueue_copy(self.queue, self.x, x)
        self._cl.enqueue_copy(self.queue, self.v, v)
        self.queue.finish()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        x = np.empty((self.n2, 4), np.float32)
        v = np.empty((self.n2, 4), np.float32)
        self._cl.enqueue_copy(self.queue, x, self.x)
        self._cl.enqueue_copy(self.queue, v, self.v)  # blocking: waits for the steps
        return position_state(x, v, self.constants.dt)

    def _substeps(self, steps: int):
        """Each substep of `steps` steps, after its collider table and pin targets are uploaded
        and its launches pointed at them (where the scene moves)."""
        total = steps * self.solver.substeps
        block = self._upload_steps if self._per_step else max(total, 1)
        for done in range(0, total, block):
            count = min(block, total - done)
            self._clock = self.substeps_done  # bodies.py's count: the tables from this substep
            self._upload_step_constants(count)
            for j in range(count):
                for k, index in self._step_kernels:
                    k.set_arg(index, np.int32(j))
                yield
            self.substeps_done += count

    def advance(self, steps: int) -> None:
        self._events = []
        enqueue, queue = self._cl.enqueue_nd_range_kernel, self.queue
        for _ in self._substeps(steps):
            for _, (kernel, global_size, local_size) in self.launches:
                self._events.append(enqueue(queue, kernel, global_size, local_size))

    def profile_stages(self, steps: int) -> dict[str, float]:
        """Advance `steps` steps with a synchronisation after every launch; ms per step of
        each stage (its launches summed over iterations and substeps)."""
        self.synchronize()
        totals: dict[str, float] = {}
        for _ in self._substeps(steps):
            for stage, (kernel, global_size, local_size) in self.launches:
                event = self._cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size)
                event.wait()
                totals[stage] = totals.get(stage, 0.0) + 1e-9 * (event.profile.end - event.profile.start)
        return {stage: 1e3 * seconds / max(steps, 1) for stage, seconds in totals.items()}

    def _buffers(self) -> tuple:
        contact = self._contact.buffers() if self._contact is not None else ()
        planes = (*self.planes, *self.planes_before, self.rest_order) if self.planes is not None else ()
        return (self.x, self.v, self.xs, self.y, *self.before, self.order, *planes, *contact, *self._body_buffers())


__all__ = ["OpenCLVbdBackend"]
