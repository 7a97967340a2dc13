"""The VBD solver (docs/vbd.md) as GL 4.3 compute shaders: kernels/vbd_cloth.comp.

Host code only; the substep plan (pbd_device.VbdDeviceBackend: predict, per iteration one
sweep dispatch per vertex colour and with Chebyshev an extrapolation, collide, update), the
state conversion and the profiling are shared with the other device solvers, the context,
the (x, v) buffers, the moving bodies and the dispatch with glsl-compute's PBD solver
(compute_pbd.GLComputeSolver). One program per stage (the kernel file's STAGE), the scene's
constants (model/kernel_inputs.py VbdConstants) compiled in as exact float32 literals; the
sweep takes its colour's range of the particles sorted by colour as uniforms, the Chebyshev
stage its weight.

Kernel shapes (gl/shapes.py): a particle per invocation in every shape, "wg=L" the work-group
size of every dispatch of the substep; chosen per driver, grid, build and solver settings by
measurement (backends/tuning.py) unless --shape or --local-size fixes it.

Self-collision ([self_collision], docs/vbd.md), only where the scene has it: per substep after
the last sweep (and Chebyshev), in collide's place, the final iterate is keyed and sorted
(gl/self_contact.py, as the PBD solver's), then STAGE_SELF_COLLISION pushes it apart and
collides it into y, which update reads (pbd_device's plan).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from clothbench.kernel_source import glsl_float, kernel_hash
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import BackendOptions
from clothbench.backends.gl import shapes
from clothbench.backends.gl.compute_pbd import GLComputeSolver, GLSLComputePbdBackend
from clothbench.backends.gl.context import work_groups
from clothbench.backends.gl.self_contact import GLSelfContact
from clothbench.backends.pbd_device import VbdDeviceBackend
from clothbench.backends.tuning import sweeps_key

KERNEL_FILE = "vbd_cloth.comp"
STAGES = {"predict": 0, "sweep": 1, "chebyshev": 2, "collide": 3, "update": 4, "self collision": 5}  # as the kernel's
# colour sweeps per timed run of a shape: 4 steps at the default 10 iterations, a few ms at 64^2
TUNING_SWEEPS = 40


@dataclass(frozen=True)
class VbdPlan:
    """A shape's substep: its launches as (stage, launch), and the programs they run by stage."""

    shape: shapes.ComputeShape
    launches: list
    programs: dict


def tuning_key(backend: GLSLComputeVbdBackend) -> dict[str, str]:
    """Verlet's key (shapes.tuning_key) and what a VBD substep's dispatches depend on: the
    solver and its sweeps (tuning.sweeps_key) and the kernel, so that one solver's choice never
    answers the other's (both are kept in glsl-compute's tuning file)."""
    return {**shapes.tuning_key(backend), **sweeps_key(backend.solver), "kernel": kernel_hash(KERNEL_FILE)}


class GLSLComputeVbdBackend(GLComputeSolver, VbdDeviceBackend):
    # the PBD solver's options and scene features: its collide stage is the same colliders' code
    capabilities = replace(
        GLSLComputePbdBackend.capabilities,
        meshes=(*GLSLComputePbdBackend.capabilities.meshes, "vbd"),
        moving_colliders=(*GLSLComputePbdBackend.capabilities.moving_colliders, "vbd"),
        boxes=(*GLSLComputePbdBackend.capabilities.boxes, "vbd"),
        self_collision=(*GLSLComputePbdBackend.capabilities.self_collision, "vbd"),  # docs/vbd.md
        shapes=True,
    )
    kernel_file = KERNEL_FILE

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        shapes.refuse_shape_with_local_size(options)  # before the device's buffers exist
        super().__init__(scene, solver, options)
        self.max_invocations = shapes.limits(self.gl)[0]
        # [self_collision]: its defines, sort buffers and search programs; None: no pass, no code
        self.contact = GLSelfContact.of(self.gl, scene, self.local_size)
        with self.gl:
            self.xs, self.y = self._state_buffer(), self._state_buffer()  # the iterate, the inertial target
            # Chebyshev: the inputs of the last two sweeps, taking turns
            self.before = [self._state_buffer() for _ in range(2)] if self.chebyshev else []
            self.order = self.gl.ctx.buffer(self.colour_order.tobytes())
            # an imageBuffer view of the iterate (no copy), for the sweep's neighbour reads
            self.views = [self.gl.buffer_texture(self.xs)] if self.image_reads else []
        if options.local_size is not None:  # the shape of that size, not tuned (and not in the mode)
            self._use_plan(self.build_plan(f"wg={self.local_size}"))
        else:
            steps = max(1, TUNING_SWEEPS // (solver.iterations * solver.substeps))
            self.pick_shape(tuning_key(self), lambda name: shapes.time_shape(self, name, steps))
            self._use_plan(self.build_plan(self.shape))

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        return shapes.candidates(scene, options, "vbd")

    def build_plan(self, name: str) -> VbdPlan:
        """The substep's launches in shape `name`: every dispatch in work groups of its size
        (but the self-collision search's, made once: such a scene has one shape)."""
        shape = shapes.parse(name, self.scene, self.max_invocations)
        self.local_size, self.programs = shape.local, {}  # what _program and _launches_of build with
        with self.gl:
            return VbdPlan(shape, self._plan_launches(), self.programs)

    def run_plan(self, plan: VbdPlan, steps: int) -> None:
        """Enqueue `steps` steps with `plan` (the chosen one, or one being timed)."""
        self._use_plan(plan)
        self.advance(steps)

    def _use_plan(self, plan: VbdPlan) -> None:
        self.local_size = self.effective_local_size = plan.shape.local
        self.launches, self.programs = plan.launches, plan.programs
        self.motion_readers = None  # found again among this plan's programs (_use_substep)

    def _program(self, stage: str):
        if stage in self.programs:
            return self.programs[stage]
        c = self.constants
        defines = self._shared_defines()
        defines.update(
            H_VALUE=glsl_float(c.h),
            GH2_VALUE="vec3({})".format(", ".join(map(glsl_float, c.gh2))),
            MH2_VALUE=glsl_float(c.mh2),
            BH_VALUE=glsl_float(c.bh),
            K_VALUE=glsl_float(c.k),
            REST_VALUE="float[3]({})".format(", ".join(map(glsl_float, c.rest))),
            STAGE=STAGES[stage],
        )
        if stage == "sweep" and self.image_reads:
            defines["IMAGE_READS"] = ""
        if self.contact is not None:
            defines.update(self.contact.defines)
        return self._compile(stage, stage, defines, self_collision=self.contact is not None)

    def _launches_of(self, step) -> list:
        """[(program, work groups, SSBO bindings, image bindings, uniform values)] of one step
        of the plan."""
        kind = step[0]
        program, items = self._program(kind), self.n2
        images: tuple = ()
        uniforms: tuple = ()
        if kind == "predict":
            bindings = (self.x, self.v, self.xs, self.y)
        elif kind == "sweep":
            colour = step[2]
            items = int(self.colour_counts[colour])
            bindings = (self.xs, self.y, self.x, self.order)
            images = ((0, self.views[0]),) if self.image_reads else ()
            uniforms = (("first", int(self.colour_starts[colour])), ("count", items))
        elif kind == "chebyshev":  # extrapolate from sweep it - 1's input (none up to sweep 0), keep sweep it + 1's
            it = step[1]
            bindings = (self.xs, self.before[(it + 1) % 2])
            uniforms = (("omega", float(self.constants.omega[max(it, 0)])), ("apply", int(it > 0)))
        elif kind == "collide":
            bindings = (self.xs,)
        elif kind == "self collision":
            ssbos = ((0, self.xs), (1, self.y), *self.contact.bindings)
            push = (program, work_groups(items, self.local_size), ssbos, (), ())
            return [*self.contact.search(self.xs), push]
        else:  # update: from y where the self-collision pass wrote it
            bindings = (self.x, self.v, self.y if self.contact is not None else self.xs)
        uniforms = tuple((program[u], v) for u, v in uniforms)
        return [(program, work_groups(items, self.local_size), tuple(enumerate(bindings)), images, uniforms)]

    def close(self) -> None:
        self._release(self.views, (self.xs, self.y, *self.before, self.order), (self.contact,))
