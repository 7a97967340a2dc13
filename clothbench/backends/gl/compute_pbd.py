"""The PBD solver (docs/pbd.md) as GL 4.3 compute shaders: kernels/pbd_cloth.comp.

Host code only; the stages, the substep plan, the state conversion and the profiling are
shared with the OpenCL solver (pbd_device.PbdDeviceBackend). One program per stage (the
kernel file's STAGE), the scene's constants compiled in as exact float32 literals; every
dispatch is followed by a memory barrier, since the next one reads what it wrote. The state
(x, v, two predicted-position buffers, lambda) stays in SSBOs; the coloured batches' (i, j)
pairs are uploaded once. The context, its program cache, the work-group size and the
dispatch geometry are gl/context.py's.

Meshes, moving colliders and pins attached to a body (docs/pbd.md, "Colliders, motion and
attached pins"): gl/context.py's GLBodies and body_defines, as the Verlet kernels take them,
with one block of rows per substep (the poses and pin targets at its end), written inside
advance() (so the harness times it) MOTION_BLOCK substeps at a time; the predict and collide
programs read block `motion_step`, set before each substep's dispatches.

Self-collision ([self_collision], docs/semantics.md), only where the scene has it: per substep,
in collide's place, the last iterate is keyed and sorted (gl/self_contact.py,
kernels/self_collision.comp), then STAGE_SELF_COLLISION pushes it apart and collides it into
the other buffer, which update reads (pbd_device's plan).
"""

from __future__ import annotations

import time

import numpy as np

from clothbench.kernel_source import glsl_float
from clothbench.model.scene import Scene
from clothbench.model.solver import Pbd
from clothbench.backends.gl import context as gl_context
from clothbench.backends.base import BackendOptions, Capabilities
from clothbench.backends.gl.context import dispatch, open_compute_device, work_groups
from clothbench.backends.gl.self_contact import GLSelfContact
from clothbench.backends.pbd_device import PbdDeviceBackend

KERNEL_FILE = "pbd_cloth.comp"
STAGES = {
    "predict": 0,
    "jacobi": 1,
    "coloured": 2,
    "collide": 3,
    "update": 4,
    "coloured sweep": 5,
    "self collision": 6,
}  # as the kernel's
PARTS = {"all": 0, "interior": 1, "border": 2}  # of a Jacobi pass, as the kernel's
# The constraint passes read positions through imageBuffer views of their buffers where the
# driver allows a view that large: llvmpipe gathers image loads and loads SSBOs lane by lane
# (docs/pbd.md, "Launches"). Tests turn it off to check the SSBO path.
PREFER_IMAGE_READS = True
# The coloured method can run an iteration's 12 batches in one dispatch of one work-group of
# SWEEP_LOCAL_SIZE invocations (barriers between batches), up to this many particles, instead
# of a dispatch per batch (docs/pbd.md, "Launches"). Off (0): on llvmpipe one work-group is
# one thread, so the sweep loses to 12 dispatches there (the same section). Tests set it to
# check that the sweep is exact; the mode says /coloured-sweep when it runs.
COLOURED_SWEEP_MAX_PARTICLES = 0
SWEEP_LOCAL_SIZE = 256  # llvmpipe's better of 256 and 1024 (docs/pbd.md); GL 4.3 guarantees up to 1024


def jacobi_parts(n: int) -> list[tuple[str, int]]:
    """The launches of one Jacobi pass and their work items: the interior (2 or more from
    every edge: all 12 neighbours exist, no bounds tests) and the border, or, below n = 5,
    the border kernel over every particle."""
    if n < 5:
        return [("border", n * n)]
    return [("interior", (n - 4) ** 2), ("border", 8 * n - 16)]


class GLSLComputePbdBackend(gl_context.GLDeviceMixin, PbdDeviceBackend):
    name = "glsl-compute"
    capabilities = Capabilities(
        local_size=True,
        gl=True,
        sweep_variants=({"strict": True}, {"strict": False}),
        meshes=("pbd",),
        moving_colliders=("pbd",),
        boxes=("pbd",),
        mesh_collisions=("accelerated", "naive"),  # compute.py's default, the same bits
        self_collision=("pbd",),
    )

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.gl, self.local_size = open_compute_device(self.name, options)
        self.effective_local_size = self.local_size
        size = self.n2 * 16  # one vec4 per particle
        self.sources: dict[str, str] = {}
        # meshes, per-substep rows of moving bodies, attached-pin slots (none without them)
        self.bodies = gl_context.GLBodies(self.gl, scene, solver.dt / solver.substeps, self.mesh_collision)
        # [self_collision]: its defines, sort buffers and search programs; None: no pass, no code
        self.contact = GLSelfContact.of(self.gl, scene, self.local_size)
        with self.gl:
            ctx = self.gl.ctx
            self.x = ctx.buffer(reserve=size)
            self.v = ctx.buffer(reserve=size)
            self.xs = [ctx.buffer(reserve=size) for _ in range(2)]  # Jacobi ping-pong
            self.lam = ctx.buffer(reserve=4 * self.lambda_count)
            # Chebyshev: the lambdas ping-pong as the iterates do
            self.lams = [self.lam, ctx.buffer(reserve=4 * self.lambda_count)] if self.chebyshev else [self.lam]
            self.ij = None if self.jacobi else ctx.buffer(self.batch_pairs.tobytes())
            # imageBuffer views of the two predicted-position buffers (no copy), for the reads
            # of the constraint passes (PREFER_IMAGE_READS)
            self.image_reads = PREFER_IMAGE_READS and self.gl.max_texture_buffer_size >= self.n2
            self.views = [self.gl.buffer_texture(buf) for buf in self.xs] if self.image_reads else []
            self.mode_suffix = gl_context.mode_suffix(self.gl, ssbo_reads=not self.image_reads)
            self.programs = {}
            self.coloured_sweep = not self.jacobi and self.n2 <= COLOURED_SWEEP_MAX_PARTICLES
            self.mode_suffix += "/coloured-sweep" * self.coloured_sweep
            self.launches = self._plan_launches(self.coloured_sweep)
            if self.coloured_sweep:  # profile_stages() times each batch on its own
                self.stage_launches = self._plan_launches()
            # the programs that read a moving scene's per-substep rows: predict, collide
            self.motion_readers = [p for p in self.programs.values() if "motion_step" in p]

    def _defines(self) -> dict[str, object]:
        c = self.constants
        defines: dict[str, object] = {"STRICT": ""} if self.strict else {}
        defines.update(gl_context.scene_defines(self.scene))  # n, colliders
        defines.update(gl_context.body_defines(self.scene, self.mesh_collision))  # meshes, motion, pins
        defines.update(
            LOCAL_SIZE=self.local_size,
            H_VALUE=glsl_float(c.h),
            GH_VALUE="vec3({})".format(", ".join(map(glsl_float, c.gh))),
            AT_VALUE="float[3]({})".format(", ".join(map(glsl_float, c.at))),
            REST_VALUE="float[3]({})".format(", ".join(map(glsl_float, c.rest))),
            DAMP_VALUE=glsl_float(c.damp),
            RELAX_VALUE=glsl_float(c.relax),
        )
        if self.contact is not None:
            defines.update(self.contact.defines)
        return defines

    def _program(self, stage: str, part: str | None = None):
        key = (stage, part)
        if key in self.programs:
            return self.programs[key]
        defines = self._defines()
        defines["STAGE"] = STAGES[stage]
        if stage == "jacobi":
            defines["PART"] = PARTS[part]
        if stage in ("jacobi", "coloured") and self.image_reads:
            defines["IMAGE_READS"] = ""
        if stage == "coloured sweep":
            starts = [*map(int, self.batch_offsets), len(self.batch_pairs)]
            defines.update(LOCAL_SIZE=SWEEP_LOCAL_SIZE, BATCH_OFFSETS_VALUE=f"int[13]({', '.join(map(str, starts))})")
        if stage == "jacobi" and self.chebyshev:
            defines["CHEBYSHEV"] = ""
        kinds = gl_context.collider_kinds(self.scene, generic=False)
        parts = dict(  # what the includes put in: meshes, motion, the self-collision pass
            meshes=bool(self.scene.meshes), moving=self.scene.has_motion, self_collision=self.contact is not None
        )
        source = gl_context.shader_source(KERNEL_FILE, 430, defines, kinds, **parts)
        self.sources[stage if part is None else f"{stage} {part}"] = source
        # the source is the specialisation key: the same scene and switches share a program
        program = self.gl.program(("pbd-comp", source), lambda: self.gl.ctx.compute_shader(source))
        self.programs[key] = program
        return program

    def _launches_of(self, step) -> list:
        """[(program, work groups, SSBO bindings, image bindings, uniform values)] of one step
        of the plan."""
        kind = step[0]
        if kind == "jacobi":
            _, it, src, dst = step
            images = ((0, self.views[src]),) if self.image_reads else ()
            ssbos = ((1, self.xs[dst]), (2, self.lam)) + (() if self.image_reads else ((0, self.xs[src]),))
            if self.chebyshev:
                ssbos = ((1, self.xs[dst]), (2, self.lams[it % 2]), (3, self.lams[1 - it % 2]))
                ssbos += () if self.image_reads else ((0, self.xs[src]),)
            launches = []
            for part, items in jacobi_parts(self.n):
                program = self._program(kind, "all" if self.n < 5 else part)
                uniforms = ((program["iteration"], it),)
                if self.chebyshev and it > 0:
                    uniforms += ((program["omega"], float(self.constants.omega[it])),)
                launches.append((program, work_groups(items, self.local_size), ssbos, images, uniforms))
            return launches
        program, items = self._program(kind), self.n2
        uniforms: tuple = ()
        images: tuple = ()
        if kind == "predict":
            bindings = (self.x, self.v, self.xs[0])
        elif kind == "coloured":
            _, it, b = step
            batch = self.batches[b]
            items = len(batch.i)
            if items == 0:  # a batch a small grid has no constraint in (n < 5): nothing to run
                return []
            bindings = (self.xs[0], self.ij, self.lam)
            images = ((0, self.views[0]),) if self.image_reads else ()
            uniforms = (
                ("batch_offset", int(self.batch_offsets[b])),
                ("batch_count", items),
                ("batch_kind", batch.kind),
                ("first_pass", int(it == 0)),
            )
        elif kind == "coloured sweep":
            bindings = (self.xs[0], self.ij, self.lam)
            uniforms = (("first_pass", int(step[1] == 0)),)
            uniforms = tuple((program[u], v) for u, v in uniforms)
            return [(program, (1, 1), tuple(enumerate(bindings)), (), uniforms)]
        elif kind == "collide":
            bindings = (self.xs[step[1]],)
        elif kind == "self collision":
            _, src, dst = step
            ssbos = ((0, self.xs[src]), (1, self.xs[dst]), *self.contact.bindings)
            push = (program, work_groups(items, self.local_size), ssbos, (), ())
            return [*self.contact.search(self.xs[src]), push]
        else:
            bindings = (self.x, self.v, self.xs[step[1]])
        uniforms = tuple((program[u], v) for u, v in uniforms)
        return [(program, work_groups(items, self.local_size), tuple(enumerate(bindings)), images, uniforms)]

    # --- PbdDeviceBackend ----------------------------------------------------------------
    def _enqueue(self, launch) -> None:
        dispatch(self.gl, launch)

    def _timed(self, launch) -> float:
        # wall clock around finish(): llvmpipe's timer queries are not to be trusted
        t0 = time.perf_counter()
        self._enqueue(launch)
        self.gl.ctx.finish()
        return time.perf_counter() - t0

    def _write_state(self, x: np.ndarray, v: np.ndarray) -> None:
        with self.gl:
            self.x.write(np.ascontiguousarray(x, dtype=np.float32))
            self.v.write(np.ascontiguousarray(v, dtype=np.float32))

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        with self.gl:
            return tuple(
                np.frombuffer(buf.read(), dtype=np.float32).reshape(self.n2, 4).copy() for buf in (self.x, self.v)
            )

    # --- Backend interface -----------------------------------------------------------------
    def _motion_block(self) -> int:
        return gl_context.MOTION_BLOCK if self.bodies.moving else 0

    def _upload_motion(self, first: int, count: int) -> None:
        self.bodies.upload_rows(first, count)

    def _use_substep(self, j: int) -> None:
        for program in self.motion_readers:  # predict, collide: this substep's rows in the block
            program["motion_step"].value = j

    def advance(self, steps: int) -> None:
        with self.gl:
            self.bodies.bind()
            super().advance(steps)

    def profile_stages(self, steps: int) -> dict[str, float]:
        with self.gl:
            self.bodies.bind()
            return super().profile_stages(steps)

    def close(self) -> None:
        if self.x is None:
            return
        with self.gl:  # the context is shared (gl_context), so only our objects go
            self.gl.delete_textures(self.views)
            for buf in (self.x, self.v, *self.xs, *self.lams, self.ij):
                if buf is not None:
                    buf.release()
        self.bodies.release()
        if self.contact is not None:
            self.contact.release()
        self.x = None
