"""GLSL fragment-shader backend: the chapter's section 22.6 in modern OpenGL (moderngl).

Kernel: kernels/verlet_cloth.vert + kernels/verlet_cloth.frag, which includes the step
(kernels/verlet_cloth_step.glsl, shared with glsl-compute) and the collider files of the
kinds the scene has (kernels/collide_*.glsl). The state lives in two
framebuffers, each with RGBA32F colour attachments (position, previous position, and the
normal when asked for); a step draws one full-viewport triangle from one into the other,
then the two swap roles. Nothing leaves the device until read().
"""

from __future__ import annotations

import numpy as np

from ..errors import BackendUnavailable, ClothbenchError
from ..scene import Scene
from . import gl_context
from .base import Availability, Backend, BackendOptions


# Read the input textures with imageLoad where the context has it (GL 4.2): the same bits
# as texelFetch in about half the step time on llvmpipe. Tests turn it off to check the other path.
PREFER_IMAGE_READS = True


def probe() -> Availability:
    return gl_context.probe(330)


def open_device(backend: str, options: BackendOptions, min_version: int) -> gl_context.GLDevice:
    """The GL context for `options.gl`, checked for f32 and the GL version `backend` needs."""
    if options.precision != "f32":
        raise ClothbenchError(f"{backend} runs in f32 only, got precision {options.precision!r}")
    try:
        device = gl_context.get_device(options.gl)
    except gl_context.GLUnavailable as e:
        raise BackendUnavailable(backend, str(e)) from None
    if device.version_code < min_version:
        need = f"{min_version // 100}.{min_version % 100 // 10}"
        have = f"{device.version_code // 100}.{device.version_code % 100 // 10}"
        raise BackendUnavailable(backend, f"needs OpenGL {need}, {device.renderer} offers {have}")
    return device


def base_mode(options: BackendOptions, device: gl_context.GLDevice) -> str:
    parts = ["strict" if options.strict else "fast"]
    if options.normals:
        parts.append("normals")
    if options.generic:
        parts.append("generic")
    if device.provider != "egl":
        parts.append(device.provider)
    return "/".join(parts)


def kernel_defines(scene: Scene, options: BackendOptions) -> dict[str, object]:
    defines: dict[str, object] = {}
    if options.strict:
        defines["STRICT"] = ""
    if options.normals:
        defines["NORMALS"] = ""
    defines.update(gl_context.constant_defines(scene, options.generic))
    return defines


class GLSLBackend(gl_context.GLDeviceMixin, Backend):
    name = "glsl"
    sweep_variants = ({"strict": True}, {"strict": False})
    has_generic = True  # --generic: one program for every scene

    def __init__(self, scene: Scene, options: BackendOptions):
        super().__init__(scene, options)
        # `precise` (GLSL 4.00) is what makes strict exact; fast runs on any GL 3.3 context
        self.gl = open_device(self.name, options, 400 if options.strict else 330)
        self.image_reads = PREFER_IMAGE_READS and self.gl.version_code >= 420
        n = scene.grid
        # Without normals there is no third target: writing zeros to one cost 16% at n = 256.
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
        self.current = 0  # index of the framebuffer holding the latest state
        self.has_normals = False

    def _program(self):
        version = self.gl.version_code  # GLSL's version numbers follow GL's from 3.3 on
        defines = kernel_defines(self.scene, self.options)
        if self.image_reads:
            defines["IMAGE_READS"] = ""
        vertex = gl_context.shader_source("verlet_cloth.vert", version, {})
        fragment = gl_context.shader_source(
            "verlet_cloth.frag", version, defines, gl_context.collider_kinds(self.scene, self.options.generic)
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
            gl_context.set_constant_uniforms(program, self.scene)
        return program

    @property
    def mode(self) -> str:
        return base_mode(self.options, self.gl)

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        with self.gl:
            pos_tex, prev_tex = self.textures[self.current][:2]
            pos_tex.write(np.ascontiguousarray(pos, dtype=np.float32))
            prev_tex.write(np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False

    def advance(self, steps: int) -> None:
        if steps <= 0:
            return
        with self.gl:
            ctx = self.gl.ctx
            ctx.disable(ctx.BLEND | ctx.DEPTH_TEST | ctx.CULL_FACE)
            if self.options.generic:
                gl_context.set_constant_uniforms(self.program, self.scene)  # shared program
            for _ in range(steps):
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
        self.fbos, self.textures, self.vao = [], [], None
