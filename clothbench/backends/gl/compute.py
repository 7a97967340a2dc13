"""GLSL compute-shader backend: the same step as `glsl`, as a GL 4.3 compute shader on SSBOs.

Kernel: kernels/verlet_cloth.comp, with the step and colliders it shares with `glsl`
(kernels/verlet_cloth_step.glsl, kernels/collide_*.glsl). The state is two std430 vec4
storage buffers, x(t) and x(t - dt); a step writes x(t + dt) over x(t - dt), in place, and the
two swap roles: no copy, and 48 bytes a particle a step where the chapter's two (pos, prev)
pairs move 64. x(t), which the neighbours read, is read through an imageBuffer view of the
same buffer (no copy either): llvmpipe loads SSBOs one lane at a time, images with vector
gathers.
Each step is two dispatches, the interior (every neighbour present, no bounds tests) and
the border, then a memory barrier before the next step reads what this one wrote.

Meshes, moving colliders and attached pins (docs/semantics.md): kernels/collide_mesh.glsl
and the MOTION and PIN_ATTACH parts of the step, compiled only for a scene that has them;
their storage buffers are gl_context.GLBodies, the per-step rows written for a block of steps
before the dispatches that read them (uniform motion_step: a step's place in the block).

Self-collision ([self_collision], docs/semantics.md), only where the scene has it: the step
leaves the colliders out and writes x_new to a buffer of its own; then per step its cells are
keyed and sorted (gl/self_contact.py, kernels/self_collision.comp) and the PASS_SELF_COLLISION
program reads x_new, pushes the pairs apart, collides, and writes x(t + dt) over x(t - dt).
Only the default shape runs it (shapes.candidates).

Kernel shapes (gl/shapes.py): the work-group size or 2-D tile of those dispatches, or, on
small grids, one work group running K steps per dispatch (kernels/verlet_cloth_steps.comp);
chosen per driver, grid and build by measurement (backends/tuning.py) unless --shape or
--local-size fixes it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.backends.gl import context as gl_context
from clothbench.backends.gl import shapes
from clothbench.backends.gl.self_contact import GLSelfContact
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities

PASS_ALL, PASS_INTERIOR, PASS_BORDER, PASS_SELF_COLLISION = 0, 1, 2, 3  # as in the kernel
# Read x(t) through imageBuffer views where the driver allows a view that large:
# half the step time of SSBO loads on llvmpipe. Tests turn it off to check the SSBO path.
PREFER_IMAGE_READS = True


def probe() -> Availability:
    return gl_context.probe(430)  # compute shaders


class GLSLComputeBackend(gl_context.GLDeviceMixin, Backend):
    name = "glsl-compute"
    capabilities = Capabilities(
        local_size=True,
        generic=True,
        normals=True,
        gl=True,
        shapes=True,
        sweep_variants=({"strict": True}, {"strict": False}),
        meshes=("verlet",),
        moving_colliders=("verlet",),
        boxes=("verlet",),  # compute_pbd.py declares its own
        mesh_collisions=("accelerated", "naive"),  # the same bits (kernels/collide_mesh.glsl)
        self_collision=("verlet",),
    )

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        shapes.refuse_shape_with_local_size(options)
        self.gl, self.local_size = gl_context.open_compute_device(self.name, options)
        self.max_invocations, self.shared_bytes = shapes.limits(self.gl)
        self.image_reads = PREFER_IMAGE_READS and self.gl.max_texture_buffer_size >= scene.particles
        self.mode_suffix = gl_context.mode_suffix(self.gl, ssbo_reads=not self.image_reads)
        self.sources: dict[object, str] = {}  # the compiled source of each (pass, shape)
        self._scratch = None  # the one-group shape's scratch buffer, where shared memory is too small
        self.steps_done = 0  # steps since the last upload: step k's poses are at (k + 1) dt
        size = scene.particles * 16  # one vec4 per particle
        with self.gl:
            ctx = self.gl.ctx
            # x(t) and x(t - dt), in either order: self.current is the index of x(t)
            self.state = [ctx.buffer(reserve=size), ctx.buffer(reserve=size)]
            self.normals = ctx.buffer(reserve=size) if options.normals else None
            # imageBuffer views of each, for the reads of x(t) (IMAGE_READS), sharing its storage
            self.views = [self.gl.buffer_texture(buf) for buf in self.state] if self.image_reads else []
        # meshes, per-step rows of moving bodies, attached-pin slots (none without them)
        self.bodies = gl_context.GLBodies(self.gl, scene, solver.dt, self.mesh_collision)
        # [self_collision]: its defines, sort buffers and search programs, and x_new's buffer
        # (with its view for the pass's reads); None: no pass, no code
        self.contact = GLSelfContact.of(self.gl, scene, self.local_size)
        self.x_new = self.x_new_view = None
        if self.contact is not None:
            with self.gl:
                self.x_new = self.gl.ctx.buffer(reserve=size)
                self.x_new_view = self.gl.buffer_texture(self.x_new) if self.image_reads else None
        self.current = 0  # index of the buffer holding x(t), the latest state
        self.has_normals = False
        if options.local_size is not None:  # the 1-D shape of that size, not tuned
            self.plan = self.build_plan(f"wg={self.local_size}")
        else:
            self.pick_shape(shapes.tuning_key(self), lambda name: shapes.time_shape(self, name))
            self.plan = self.build_plan(self.shape)
        self.effective_local_size = self.plan.shape.local

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        return shapes.candidates(scene, options)

    def build_plan(self, name: str) -> "Plan":
        """The programs and dispatches of shape `name` (shapes.py)."""
        shape = shapes.parse(name, self.scene, self.max_invocations)
        n = self.scene.grid
        with self.gl:
            if shape.steps is not None:
                layout = shapes.steps_layout(self.scene.particles, self.max_invocations, self.shared_bytes)
                shape = replace(shape, local=layout.local)
                if not layout.shared and self._scratch is None:
                    floats = 2 * 3 * self.scene.particles
                    self._scratch = self.gl.ctx.buffer(reserve=4 * floats)
                defines = dict(LOCAL_SIZE=layout.local, PPI=layout.ppi, CAPACITY=self.scene.particles)
                if layout.shared:
                    defines["SCRATCH_SHARED"] = ""
                program = self._program("verlet_cloth_steps.comp", ("steps", name), defines)
                return Plan(shape, [(program, (1, 1))], layout)
            if n < 5:  # no interior: one pass with bounds tests
                counts = {PASS_ALL: n * n}
            else:
                counts = {PASS_INTERIOR: (n - 4) ** 2, PASS_BORDER: 8 * n - 16}
            passes = []
            for pass_id, count in counts.items():
                defines = dict(LOCAL_SIZE=shape.local, PASS=pass_id)
                groups = gl_context.work_groups(count, shape.local)
                if pass_id == PASS_BORDER and shape.tile is not None:
                    defines["LOCAL_SIZE"] = shapes.BORDER_LOCAL_SIZE
                    groups = gl_context.work_groups(count, shapes.BORDER_LOCAL_SIZE)
                if pass_id == PASS_INTERIOR and shape.tile is not None:
                    w, h = shape.tile
                    defines.update(TILE_W=w, TILE_H=h)
                    groups = (-(-(n - 4) // w), -(-(n - 4) // h))
                passes.append((self._program("verlet_cloth.comp", (pass_id, name), defines), groups))
            contact = None
            if self.contact is not None:
                defines = dict(LOCAL_SIZE=shape.local, PASS=PASS_SELF_COLLISION)
                program = self._program("verlet_cloth.comp", (PASS_SELF_COLLISION, name), defines)
                contact = (program, gl_context.work_groups(n * n, shape.local))
            return Plan(shape, passes, self_collision=contact)

    def _program(self, filename: str, what, extra: dict):
        defines = gl_context.kernel_defines(self.scene, self.solver, self.options)
        defines.update(extra)
        if self.image_reads and filename == "verlet_cloth.comp":
            defines["IMAGE_READS"] = ""
        defines.update(gl_context.body_defines(self.scene, self.mesh_collision))
        if self.contact is not None:
            defines.update(self.contact.defines)
        kinds = gl_context.collider_kinds(self.scene, self.options.generic)
        parts = dict(  # what the includes put in: meshes, motion, the self-collision pass
            meshes=bool(self.scene.meshes), moving=self.scene.has_motion, self_collision=self.contact is not None
        )
        source = gl_context.shader_source(filename, 430, defines, kinds, **parts)
        # the source is the specialisation key (see fragment.GLSLBackend._program)
        program = self.gl.program(("comp", source), lambda: self.gl.ctx.compute_shader(source))
        self.sources[what] = source
        if self.options.generic:
            gl_context.set_constant_uniforms(program, self.scene, self.solver)
        return program

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        with self.gl:
            self.state[self.current].write(np.ascontiguousarray(pos, dtype=np.float32))
            self.state[1 - self.current].write(np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False
        self.steps_done = 0  # the uploaded state is at t = 0: moving bodies start over

    def advance(self, steps: int) -> None:
        if steps > 0:
            with self.timed_steps():  # device_elapsed_ms: GL timestamps around the dispatches
                self.run_plan(self.plan, steps)

    def run_plan(self, plan: "Plan", steps: int) -> None:
        """Enqueue `steps` steps with `plan`'s dispatches (the chosen one, or one being timed)."""
        with self.gl:
            if self.options.generic:
                contact = [plan.self_collision] if plan.self_collision is not None else []
                for program, _ in plan.passes + contact:  # programs are shared between backends
                    gl_context.set_constant_uniforms(program, self.scene, self.solver)
            if self.normals is not None:
                self.normals.bind_to_storage_buffer(4)
            self.bodies.bind()
            moving = self.bodies.moving
            done = 0
            while done < steps:  # a scene that moves: blocks of MOTION_BLOCK steps' rows
                block = min(gl_context.MOTION_BLOCK, steps - done) if moving else steps - done
                if moving:
                    self.bodies.upload_rows(self.steps_done, block)
                if plan.shape.steps is not None:
                    self._run_steps(plan, block)
                else:
                    for step in range(block):
                        self._bind_state(image_reads=self.image_reads)
                        if plan.self_collision is not None:  # the step writes x_new for the pass
                            self.x_new.bind_to_storage_buffer(2)
                        for program, groups in plan.passes:
                            if moving and "motion_step" in program:
                                program["motion_step"].value = step  # this step's rows in the block
                            program.run(*groups)
                        self.gl.ctx.memory_barrier()  # the next step reads what this one wrote
                        if plan.self_collision is not None:
                            self._self_collision(plan, step)
                        self.current = 1 - self.current  # x(t + dt) is x(t) now: swap the roles
                done += block
                self.steps_done += block
        self.has_normals = self.options.normals

    def _self_collision(self, plan: "Plan", step: int) -> None:
        """x_new -> x(t + dt) over x(t - dt): keyed, sorted, pushed apart and collided."""
        for launch in self.contact.search(self.x_new):
            gl_context.dispatch(self.gl, launch)
        program, groups = plan.self_collision
        reads = ((), ((0, self.x_new_view),)) if self.image_reads else (((0, self.x_new),), ())
        ssbos = (*reads[0], (2, self.state[1 - self.current]), *self.contact.bindings)
        uniforms = ((program["motion_step"], step),) if "motion_step" in program else ()
        gl_context.dispatch(self.gl, (program, groups, ssbos, reads[1], uniforms))

    def _bind_state(self, image_reads: bool) -> None:
        """x(t) as binding 0 (image unit or SSBO), x(t - dt), written over, as SSBO 1."""
        if image_reads:
            self.gl.bind_image_read(0, self.views[self.current])
        else:
            self.state[self.current].bind_to_storage_buffer(0)
        self.state[1 - self.current].bind_to_storage_buffer(1)

    def _run_steps(self, plan: "Plan", steps: int) -> None:
        """steps/dispatch=K: dispatches of K steps each and one of the remainder."""
        program = plan.passes[0][0]
        if self._scratch is not None and not plan.layout.shared:
            self._scratch.bind_to_storage_buffer(5)
        done = 0
        while done < steps:
            chunk = min(plan.shape.steps, steps - done)
            self._bind_state(image_reads=False)
            program["steps"].value = chunk
            if "motion_step" in program:
                program["motion_step"].value = done  # this dispatch's first step in the block
            program.run(1)
            self.gl.ctx.memory_barrier()
            self.current = 1 - self.current
            done += chunk

    def _read_buffer(self, buf) -> np.ndarray:
        return np.frombuffer(buf.read(), dtype=np.float32).reshape(self.scene.particles, 4).copy()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        with self.gl:
            return self._read_buffer(self.state[self.current]), self._read_buffer(self.state[1 - self.current])

    def read_normals(self) -> np.ndarray | None:
        """Normals of the positions the last step read (read()[1]), see docs/normals.md."""
        if not self.has_normals:
            return None
        with self.gl:
            return self._read_buffer(self.normals)

    def drawable_state(self) -> gl_context.DrawableState:
        """x(t) (read()[1]) and its normals as this backend's own storage buffers, for drawing."""
        if not self.has_normals:
            raise ClothbenchError("glsl-compute: no normals to draw; create the backend with normals=True and step")
        return gl_context.DrawableState(self.gl, self.state[1 - self.current], self.normals)

    def close(self) -> None:
        with self.gl:  # the context is shared (gl_context), so only our objects go
            self.gl.delete_textures(self.views)
            for buf in self.state + [self.normals]:
                if buf is not None:
                    buf.release()
            if self._scratch is not None:
                self._scratch.release()
            if self.contact is not None:
                self.gl.delete_textures([self.x_new_view] if self.x_new_view is not None else [])
                self.x_new.release()
                self.contact.release()
        self.bodies.release()
        self.views, self.state, self.normals, self._scratch = [], [], None, None


@dataclass(frozen=True)
class Plan:
    """A shape's dispatches: (program, work groups) per pass of a step, or the one program of
    the one-group shape and its layout (shapes.StepsLayout); with [self_collision], the pass's
    (program, work groups), run after the step's passes."""

    shape: shapes.ComputeShape
    passes: list
    layout: shapes.StepsLayout | None = None
    self_collision: tuple | None = None
