"""GLSL compute-shader backend: the same step as `glsl`, as a GL 4.3 compute shader on SSBOs.

Kernel: kernels/verlet_cloth.comp, with the step and colliders it shares with `glsl`
(kernels/verlet_cloth_step.glsl, kernels/collide_*.glsl). The state is two (pos, prev)
pairs of std430 vec4 storage buffers; a step reads one pair and writes the other
(bindings 2-3), then the pairs swap roles: no copy. The input pair is read through
imageBuffer views of the same buffers (no copy either): llvmpipe loads SSBOs one lane at a
time, images with vector gathers.
Each step is two dispatches, the interior (every neighbour present, no bounds tests) and
the border, then a memory barrier before the next step reads what this one wrote.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.scene import Scene
from clothbench.solver import Verlet
from clothbench.backends.gl import context as gl_context
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities

PASS_ALL, PASS_INTERIOR, PASS_BORDER = 0, 1, 2  # as in the kernel
# Read the input pair through imageBuffer views where the driver allows a view that large:
# half the step time of SSBO loads on llvmpipe. Tests turn it off to check the SSBO path.
PREFER_IMAGE_READS = True


def probe() -> Availability:
    return gl_context.probe(430)  # compute shaders


class GLSLComputeBackend(gl_context.GLDeviceMixin, Backend):
    name = "glsl-compute"
    capabilities = Capabilities(
        local_size=True, generic=True, normals=True, gl=True,
        sweep_variants=({"strict": True}, {"strict": False}),
    )  # fmt: skip

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.gl, self.local_size = gl_context.open_compute_device(self.name, options)
        self.effective_local_size = self.local_size
        n = scene.grid
        self.image_reads = PREFER_IMAGE_READS and self.gl.max_texture_buffer_size >= scene.particles
        self.mode_suffix = gl_context.mode_suffix(self.gl, ssbo_reads=not self.image_reads)
        self.sources: dict[int, str] = {}  # the compiled source of each pass
        # interior and border when there is an interior (n >= 5); else one pass with tests
        if n >= 5:
            counts = {PASS_INTERIOR: (n - 4) ** 2, PASS_BORDER: 8 * n - 16}
        else:
            counts = {PASS_ALL: n * n}
        size = scene.particles * 16  # one vec4 per particle
        with self.gl:
            ctx = self.gl.ctx
            # (program, work groups) for each dispatch of a step
            self.passes = [
                (self._program(p), gl_context.work_groups(count, self.local_size))
                for p, count in counts.items()
            ]
            self.pairs = [(ctx.buffer(reserve=size), ctx.buffer(reserve=size)) for _ in range(2)]
            self.normals = ctx.buffer(reserve=size) if options.normals else None
            # imageBuffer views of each pair, for the reads (IMAGE_READS), sharing its storage
            self.views = []
            if self.image_reads:
                self.views = [tuple(map(self.gl.buffer_texture, pair)) for pair in self.pairs]
        self.current = 0  # index of the pair holding the latest state
        self.has_normals = False

    def _program(self, pass_id: int):
        defines = gl_context.kernel_defines(self.scene, self.solver, self.options)
        defines.update(LOCAL_SIZE=self.local_size, PASS=pass_id)
        if self.image_reads:
            defines["IMAGE_READS"] = ""
        kinds = gl_context.collider_kinds(self.scene, self.options.generic)
        source = gl_context.shader_source("verlet_cloth.comp", 430, defines, kinds)
        # the source is the specialisation key (see fragment.GLSLBackend._program)
        program = self.gl.program(("comp", source), lambda: self.gl.ctx.compute_shader(source))
        self.sources[pass_id] = source
        if self.options.generic:
            gl_context.set_constant_uniforms(program, self.scene, self.solver)
        return program

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        with self.gl:
            pos_buf, prev_buf = self.pairs[self.current]
            pos_buf.write(np.ascontiguousarray(pos, dtype=np.float32))
            prev_buf.write(np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False

    def advance(self, steps: int) -> None:
        if steps <= 0:
            return
        with self.gl:
            if self.options.generic:
                for program, _ in self.passes:  # programs are shared between backends
                    gl_context.set_constant_uniforms(program, self.scene, self.solver)
            if self.normals is not None:
                self.normals.bind_to_storage_buffer(4)
            for _ in range(steps):
                source, target = self.current, 1 - self.current
                if self.image_reads:
                    for unit, view in enumerate(self.views[source]):
                        self.gl.bind_image_read(unit, view)
                else:
                    for binding, buf in enumerate(self.pairs[source]):
                        buf.bind_to_storage_buffer(binding)
                for binding, buf in enumerate(self.pairs[target], start=2):
                    buf.bind_to_storage_buffer(binding)
                for program, groups in self.passes:
                    program.run(*groups)
                self.gl.ctx.memory_barrier()  # the next step reads what this one wrote
                self.current = target  # ping-pong: swap the pairs' roles
        self.has_normals = self.options.normals

    def _read_buffer(self, buf) -> np.ndarray:
        return np.frombuffer(buf.read(), dtype=np.float32).reshape(self.scene.particles, 4).copy()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        with self.gl:
            pos_buf, prev_buf = self.pairs[self.current]
            return self._read_buffer(pos_buf), self._read_buffer(prev_buf)

    def read_normals(self) -> np.ndarray | None:
        """Normals of the positions the last step read (read()[1]), see docs/normals.md."""
        if not self.has_normals:
            return None
        with self.gl:
            return self._read_buffer(self.normals)

    def drawable_state(self) -> gl_context.DrawableState:
        """x(t) (read()[1]) and its normals as this backend's own storage buffers, for drawing."""
        if not self.has_normals:
            raise ClothbenchError(
                "glsl-compute: no normals to draw; create the backend with normals=True and step"
            )
        return gl_context.DrawableState(self.gl, self.pairs[self.current][1], self.normals)

    def close(self) -> None:
        with self.gl:  # the context is shared (gl_context), so only our objects go
            self.gl.delete_textures([view for pair in self.views for view in pair])
            for buf in [b for pair in self.pairs for b in pair] + [self.normals]:
                if buf is not None:
                    buf.release()
        self.views, self.pairs, self.normals = [], [], None
