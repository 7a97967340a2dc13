"""The VBD solver (docs/vbd.md) on OpenCL: kernels/vbd_cloth.cl through pyopencl.

Host code only; the step is the kernel file's and docs/vbd.md's. One kernel shape: a substep
is a fixed list of launches on an in-order queue (each sees the one before): predict, then
per iteration one launch per vertex colour (and with Chebyshev one extrapolation), collide,
update. Every launch is a kernel object whose arguments are set once at construction, so
advance() only enqueues; the numbers are VbdConstants' (model/kernel_inputs.py).

Meshes, moving colliders and pins attached to a body: bodies.py's host side, as the PBD
solver uses it, one collider table (and set of pin targets) per substep, at its end; predict
and collide take the substep's index in the upload, set before each substep is enqueued.

What a later change may tune: the sweep is one particle per work item, gathered through an
index list of the colour's particles (half of them would be one vector lane apart in a
planar layout); a small grid would gain from whole substeps in one launch, as PBD's
one-launch shape does.

Self-collision ([self_collision], docs/vbd.md), only where the scene has it
(-DCLOTH_SELF_COLLISION, kernels/self_collision.cl): per substep after the last sweep (and
Chebyshev), the iterate's cells are keyed and sorted and pbd_self_collision pushes the pairs
apart and collides into y (which the sweeps no longer read), in place of vbd_collide; the
update reads y. self_contact.py's row_launches, as the PBD solver's.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.constraints import VERTEX_COLOURS, vertex_colours
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import Backend, BackendOptions, Capabilities
from clothbench.model.kernel_inputs import VbdConstants
from clothbench.backends.opencl.bodies import OpenCLBodiesMixin
from clothbench.backends.opencl.self_contact import SelfContact, include_text
from clothbench.backends.pbd_device import position_state, velocity_state
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    arithmetic_options,
    build_program,
    program_source,
    shape_options,
)

KERNEL_FILE = "vbd_cloth.cl"
# the sweep kernel reads no vectors; shape_options wants a width, and the program ignores it
SCALAR = 1


class OpenCLVbdBackend(OpenCLBodiesMixin, OpenCLDeviceMixin, Backend):
    name = "opencl"
    capabilities = Capabilities(
        local_size=True,
        device=True,
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
        self._step_kernels: list = []  # (kernel, argument index) of each launch's substep index
        self.launches = self._plan_launches()
        self.substeps_done = 0  # since the last upload(): the clock of moving bodies

    def build_options(self) -> tuple[str, ...]:
        contact = self._contact.build_options if self._contact is not None else ()
        return (*shape_options(self.scene, SCALAR), *self._body_options(), *arithmetic_options(self.strict), *contact)

    def _kernel(self, name: str, dtypes: list, args: tuple, bodies: tuple = ()):
        """Kernel `name` with its typed arguments set once; `bodies`: the _body_args() it takes
        after `args` (the substep index first, where the scene moves, set per substep). Every
        launch has its own: the plan sets each kernel's arguments once."""
        k = self._cl.Kernel(self.program, name)
        k.set_scalar_arg_dtypes(list(dtypes) + [np.int32 if isinstance(a, np.int32) else None for a in bodies])
        k.set_args(*args, *bodies)
        self._check_local_size(k, name)
        if bodies and self._per_step:
            self._step_kernels.append((k, len(args)))
        return k

    def _plan_launches(self) -> list:
        """One substep as [(stage, (kernel, global size, local size))] in launch order."""
        c, f32, i32 = self.constants, np.float32, np.int32
        make4, float4 = self._cl.cltypes.make_float4, self._cl.cltypes.float4
        plan = []

        def launch(stage: str, kernel, items: int) -> None:
            plan.append((stage, (kernel, *self._launch_size(items))))

        pins = self._body_args(0)[: self._per_step] + ((self._pin_slot, self._pin_target) if self._attached else ())
        predict = self._kernel(
            "vbd_predict", [None] * 4 + [f32, float4], (self.x, self.v, self.xs, self.y, c.h, make4(*c.gh2, 0.0)), pins
        )
        launch("predict", predict, self.n2)
        rest = make4(*c.rest, 0.0)
        sweeps, first = [], 0
        for count in self.colour_counts:
            args = (self.xs, self.y, self.x, self.order, i32(first), i32(count), c.mh2, c.bh, c.k, rest)
            sweeps.append((self._kernel("vbd_sweep", [None] * 4 + [i32, i32, f32, f32, f32, float4], args), count))
            first += count
        chebyshev = [None] * 2 + [f32, i32]
        if self.chebyshev:  # the first sweep's input: the predicted iterate
            launch(
                "chebyshev",
                self._kernel("vbd_chebyshev", chebyshev, (self.xs, self.before[0], f32(1), i32(0))),
                self.n2,
            )
        for it in range(self.solver.iterations):
            for kernel, count in sweeps:
                launch("sweep", kernel, count)
            if self.chebyshev:  # extrapolate from sweep it - 1's input (none after sweep 0), keep sweep it + 1's
                before = self.before[(it + 1) % 2]
                args = (self.xs, before, c.omega[it], i32(it > 0))
                launch("chebyshev", self._kernel("vbd_chebyshev", chebyshev, args), self.n2)
        meshes = self._body_args(0)[: self._per_step + 2 * bool(self._meshes)]  # no pins: predict's
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
        return (self.x, self.v, self.xs, self.y, *self.before, self.order, *contact, *self._body_buffers())


__all__ = ["OpenCLVbdBackend"]
