"""GLSL fragment-shader backend: the chapter's section 22.6 in modern OpenGL (moderngl).

Kernel: kernels/verlet_cloth.vert + kernels/verlet_cloth.frag, which includes the step
(kernels/verlet_cloth_step.glsl, shared with glsl-compute) and the collider files of the
kinds the scene has (kernels/collide_*.glsl, and collide_mesh.glsl where it has meshes:
storage buffers, so such a scene, or one that moves, needs GL 4.3). The state lives in two
framebuffers, each with RGBA32F colour attachments (position, previous position, and the
normal when asked for); a step draws one full-viewport triangle from one into the other,
then the two swap roles. Nothing leaves the device until read().
Where the driver flushes subnormal floats in fragment shaders (llvmpipe does), --strict holds
until a value falls below float32's smallest normal (docs/semantics.md, "Subnormal floats").
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.backends.gl import context as gl_context
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities


# Read the input textures with imageLoad where the context has it (GL 4.2): the same bits
# as texelFetch in about half the step time on llvmpipe. Tests turn it off to check the other path.
PREFER_IMAGE_READS = True


def probe() -> Availability:
    return gl_context.probe(330)


class GLSLBackend(gl_context.GLDeviceMixin, Backend):
    name = "glsl"
    capabilities = Capabilities(
        generic=True,
        normals=True,
        gl=True,
        sweep_variants=({"strict": True}, {"strict": False}),
        meshes=("verlet",),
        moving_colliders=("verlet",),  # on GL 4.3: storage buffers in the shader
        boxes=("verlet",),  # kernels/collide_box.glsl
        mesh_collisions=("accelerated", "naive"),  # kernels/collide_mesh.glsl, as glsl-compute's
    )
    shader_stage = "fragment"

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        # `precise` (GLSL 4.00) is what makes strict exact; fast runs on any GL 3.3 context; the
        # meshes and per-step rows of moving bodies are storage buffers (GL 4.3)
        bodies = bool(scene.meshes) or scene.has_motion
        self.gl = gl_context.open_device(self.name, options, 430 if bodies else 400 if options.strict else 330)
        self.mode_suffix = gl_context.mode_suffix(self.gl)
        self.image_reads = PREFER_IMAGE_READS and self.gl.version_code >= 420
        n = scene.grid
        # Without normals there is no third target: even writing zeros to one costs (docs/llvmpipe.md).
        targets = 3 if options.normals else 2
        with self.gl:
            ctx = self.gl.ctx
            self.program = self._program()
            self.vao = ctx.vertex_array(self.program, [])  # no vertex data: gl_VertexID
            self.fbos, self.textures = [], []
            for _ in range(2):
                textures = [ctx.texture((n, n), 4, dtype="f4") for _ in range(targets)]
                for t in textures:
                    t.filter = (ctx.NEAREST, ctx.NEAREST)
                self.textures.append(textures)
                self.fbos.append(ctx.framebuffer(color_attachments=textures))
        # meshes, per-step rows of moving bodies, attached-pin slots (none without them)
        self.bodies = gl_context.GLBodies(self.gl, scene, solver.dt, self.mesh_collision)
        self.steps_done = 0  # steps since the last upload: step k's poses are at (k + 1) dt
        self.current = 0  # index of the framebuffer holding the latest state
        self.has_normals = False

    def _program(self):
        version = self.gl.version_code  # GLSL's version numbers follow GL's from 3.3 on
        defines = gl_context.kernel_defines(self.scene, self.solver, self.options)
        if self.image_reads:
            defines["IMAGE_READS"] = ""
        defines.update(gl_context.body_defines(self.scene, self.mesh_collision))
        vertex = gl_context.shader_source("verlet_cloth.vert", version, {})
        fragment = gl_context.shader_source(
            "verlet_cloth.frag",
            version,
            defines,
            gl_context.collider_kinds(self.scene, self.options.generic),
            meshes=bool(self.scene.meshes),
            moving=self.scene.has_motion,
        )

        def build():
            program = self.gl.ctx.program(vertex_shader=vertex, fragment_shader=fragment)
            if not self.image_reads:
                program["pos_tex"].value = 0  # texture units, as bound in advance()
                program["prev_tex"].value = 1
            return program

        # the source is the specialisation key: the same scene constants, switches and
        # collider kinds share one program (a sweep's repeats, every --generic scene)
        program = self.gl.program(("frag", vertex, fragment), build)
        self.source = fragment
        if self.options.generic:
            gl_context.set_constant_uniforms(program, self.scene, self.solver)
        return program

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        with self.gl:
            pos_tex, prev_tex = self.textures[self.current][:2]
            pos_tex.write(np.ascontiguousarray(pos, dtype=np.float32))
            prev_tex.write(np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False
        self.steps_done = 0  # the uploaded state is at t = 0: moving bodies start over

    def advance(self, steps: int) -> None:
        if steps <= 0:
            return
        with self.gl, self.timed_steps():  # device_elapsed_ms: GL timestamps around the draws
            ctx = self.gl.ctx
            ctx.disable(ctx.BLEND | ctx.DEPTH_TEST | ctx.CULL_FACE)
            if self.options.generic:
                gl_context.set_constant_uniforms(self.program, self.scene, self.solver)  # shared program
            self.bodies.bind()
            for step in range(steps):
                if self.bodies.moving:  # a block of steps' rows at a time, then this step's place in it
                    block = step % gl_context.MOTION_BLOCK
                    if block == 0:
                        self.bodies.upload_rows(self.steps_done + step, min(gl_context.MOTION_BLOCK, steps - step))
                    self.program["motion_step"].value = block
                source, target = self.current, 1 - self.current
                pos_tex, prev_tex = self.textures[source][:2]
                if self.image_reads:
                    pos_tex.bind_to_image(0, read=True, write=False)
                    prev_tex.bind_to_image(1, read=True, write=False)
                else:
                    pos_tex.use(location=0)
                    prev_tex.use(location=1)
                self.fbos[target].use()
                self.vao.render(mode=ctx.TRIANGLES, vertices=3)
                self.current = target  # ping-pong: the output is the next step's input
        self.steps_done += steps
        self.has_normals = self.options.normals

    def _read_attachment(self, i: int) -> np.ndarray:
        n2 = self.scene.particles
        data = self.fbos[self.current].read(components=4, attachment=i, dtype="f4")
        return np.frombuffer(data, dtype=np.float32).reshape(n2, 4).copy()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        with self.gl:
            return self._read_attachment(0), self._read_attachment(1)

    def read_normals(self) -> np.ndarray | None:
        """Normals of the positions the last step read (read()[1]), see docs/normals.md."""
        if not self.has_normals:
            return None
        with self.gl:
            return self._read_attachment(2)

    def drawable_state(self) -> gl_context.DrawableState:
        """x(t) (read()[1]) and its normals as this backend's own textures, for drawing."""
        if not self.has_normals:
            raise ClothbenchError("glsl: no normals to draw; create the backend with normals=True and step")
        _, prev_tex, normal_tex = self.textures[self.current]
        return gl_context.DrawableState(self.gl, prev_tex, normal_tex)

    def close(self) -> None:
        with self.gl:  # the context is shared (gl_context), so only our objects go
            for obj in [*self.fbos, *(t for ts in self.textures for t in ts), self.vao]:
                if obj is not None:
                    obj.release()
        self.bodies.release()
        self.fbos, self.textures, self.vao = [], [], None
