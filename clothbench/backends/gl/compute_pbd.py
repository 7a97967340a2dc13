"""The PBD solver (docs/pbd.md) as GL 4.3 compute shaders: kernels/pbd_cloth.comp; and
GLComputeSolver, what it shares with the VBD solver's (gl/compute_vbd.py).

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
from clothbench.model.solver import Pbd, Solver
from clothbench.backends.gl import context as gl_context
from clothbench.backends.base import BackendOptions, Capabilities
from clothbench.backends.gl.context import dispatch, open_compute_device, work_groups
from clothbench.backends.gl.self_contact import GLSelfContact
from clothbench.backends.pbd_device import DeviceSolverBackend, PbdDeviceBackend

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


class GLComputeSolver(gl_context.GLDeviceMixin, DeviceSolverBackend):
    """What glsl-compute's PBD and VBD solvers share: the context and work-group size, the (x,
    v) SSBOs, the moving bodies, whether the iterate is read through imageBuffer views, one
    program per stage of `kernel_file` with the scene compiled in, and a launch as (program,
    work groups, SSBO bindings, image bindings, uniform values), enqueued with a memory
    barrier after it. A subclass makes its other buffers and plans its substep."""

    name = "glsl-compute"
    kernel_file: str  # the solver's kernels/*.comp

    def __init__(self, scene: Scene, solver: Solver, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.gl, self.local_size = open_compute_device(self.name, options)
        self.effective_local_size = self.local_size
        self.sources: dict[str, str] = {}
        self.programs: dict = {}
        # meshes, per-substep rows of moving bodies, attached-pin slots (none without them)
        self.bodies = gl_context.GLBodies(self.gl, scene, solver.dt / solver.substeps, self.mesh_collision)
        # the passes that read neighbours do it through imageBuffer views of their buffers
        # where the driver allows a view that large (PREFER_IMAGE_READS)
        self.image_reads = PREFER_IMAGE_READS and self.gl.max_texture_buffer_size >= self.n2
        self.mode_suffix = gl_context.mode_suffix(self.gl, ssbo_reads=not self.image_reads)
        self.motion_readers: list | None = None  # the programs that read motion_step, once planned
        with self.gl:
            self.x = self._state_buffer()
            self.v = self._state_buffer()

    def _state_buffer(self):
        """An SSBO of one vec4 per particle."""
        return self.gl.ctx.buffer(reserve=self.n2 * 16)

    def _shared_defines(self) -> dict[str, object]:
        """The switches and constants every stage of either solver takes: strict, the grid and
        colliders, the bodies, the work-group size."""
        defines: dict[str, object] = {"STRICT": ""} if self.strict else {}
        defines.update(gl_context.scene_defines(self.scene))  # n, colliders
        defines.update(gl_context.body_defines(self.scene, self.mesh_collision))  # meshes, motion, pins
        defines["LOCAL_SIZE"] = self.local_size
        return defines

    def _compile(self, key, name: str, defines: dict[str, object], self_collision: bool = False):
        """The program of `kernel_file` with `defines` (and, with `self_collision`, the pass's
        include), kept as self.programs[key] and its source as self.sources[name]."""
        kinds = gl_context.collider_kinds(self.scene, generic=False)
        parts = dict(  # what the includes put in: meshes, motion, the self-collision pass
            meshes=bool(self.scene.meshes), moving=self.scene.has_motion, self_collision=self_collision
        )
        source = gl_context.shader_source(self.kernel_file, 430, defines, kinds, **parts)
        self.sources[name] = source
        # the source is the specialisation key: the same scene and switches share a program
        program = self.gl.program((self.kernel_file, source), lambda: self.gl.ctx.compute_shader(source))
        self.programs[key] = program
        return program

    # --- DeviceSolverBackend ---------------------------------------------------------------
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
        if self.motion_readers is None:  # predict, collide: this substep's rows in the block
            self.motion_readers = [p for p in self.programs.values() if "motion_step" in p]
        for program in self.motion_readers:
            program["motion_step"].value = j

    def advance(self, steps: int) -> None:
        with self.gl:
            self.bodies.bind()
            super().advance(steps)

    def profile_stages(self, steps: int) -> dict[str, float]:
        with self.gl:
            self.bodies.bind()
            return super().profile_stages(steps)

    def _release(self, textures: list[int], buffers, parts=()) -> None:
        """Release this backend's views and buffers, x and v with them, its bodies' and the
        `parts` with a release() of their own, once (the context is shared: gl_context)."""
        if self.x is None:
            return
        with self.gl:
            self.gl.delete_textures(textures)
            for buf in (self.x, self.v, *buffers):
                if buf is not None:
                    buf.release()
        for part in (self.bodies, *parts):
            if part is not None:
                part.release()
        self.x = None


class GLSLComputePbdBackend(GLComputeSolver, PbdDeviceBackend):
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
    kernel_file = KERNEL_FILE

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        # [self_collision]: its defines, sort buffers and search programs; None: no pass, no code
        self.contact = GLSelfContact.of(self.gl, scene, self.local_size)
        with self.gl:
            ctx = self.gl.ctx
            self.xs = [self._state_buffer() for _ in range(2)]  # Jacobi ping-pong
            self.lam = ctx.buffer(reserve=4 * self.lambda_count)
            # Chebyshev: the lambdas ping-pong as the iterates do
            self.lams = [self.lam, ctx.buffer(reserve=4 * self.lambda_count)] if self.chebyshev else [self.lam]
            self.ij = None if self.jacobi else ctx.buffer(self.batch_pairs.tobytes())
            # imageBuffer views of the two predicted-position buffers (no copy), for the reads
            # of the constraint passes
            self.views = [self.gl.buffer_texture(buf) for buf in self.xs] if self.image_reads else []
            self.coloured_sweep = not self.jacobi and self.n2 <= COLOURED_SWEEP_MAX_PARTICLES
            self.mode_suffix += "/coloured-sweep" * self.coloured_sweep
            self.launches = self._plan_launches(self.coloured_sweep)
            if self.coloured_sweep:  # profile_stages() times each batch on its own
                self.stage_launches = self._plan_launches()

    def _defines(self) -> dict[str, object]:
        c = self.constants
        defines = self._shared_defines()
        defines.update(
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
        name = stage if part is None else f"{stage} {part}"
        return self._compile(key, name, defines, self_collision=self.contact is not None)

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

    def close(self) -> None:
        self._release(self.views, (*self.xs, *self.lams, self.ij), (self.contact,))
