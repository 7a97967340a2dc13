"""The OpenCL backend: kernels/verlet_cloth.cl through pyopencl (PoCL's CPU device here).

Host code only; the step is in the kernel file and docs/semantics.md. The state stays on the
device and is read back only by read(). The generic and split kernels ping-pong two pairs of
buffers (positions, previous positions) by swapping references, as in the chapter's Figure
22.4; the rows and multi-step kernels, the ones tuning picks on large grids, write x(t+dt) over
x(t-dt) in place and swap the pair's roles instead (_step_state), 40 bytes a particle a step
streamed instead of 52 (docs/bounds.md, "The count").

Transfer modes (options.transfer):
  resident  (default) the state never leaves the device between read() calls.
  per-step  the chapter's OpenCL variant (section 22.8): the host owns the state and uploads
            it at the start of every step; to upload the current state it must also read each
            step's result back, so a step costs one round trip. Done inside advance(), so the
            harness times it.

Which kernel runs (kernels/verlet_cloth.cl, whose header says what is a -D option and what
an argument):
  default    built for the scene: SoA planes (with PAD floats either side), V particles per
             work item, the grid side and the collider counts as -D constants, the code of a
             collider kind only when the scene has one. Which kernels and how the work is
             split is the kernel shape (verlet_shapes.py: interior + border kernels, whole
             rows, or several steps per launch), chosen per device and scene by measurement
             (backends/tuning.py; the backend times each candidate on itself) unless
             options.shape names one; it ends the mode. The multi-step kernel swaps the two
             buffers inside its launch: advance() swaps the references after an odd count.
             Programs are cached by their build options (`key`), so backends of the same
             shape (a dt or stiffness sweep too) build nothing. `--strict` runs them with
             the documented operation order and FP_CONTRACT OFF: bit-exact with the NumPy
             float32 reference, whatever the shape.
  --generic  `verlet_cloth`, the float4 kernel that reads beside Listing 22.1: one program
             for every scene, grid side, constants and collider counts all arguments.
             Bit-exact too in strict mode; the tests hold the two builds to each other.
Normals (docs/normals.md, options.normals): both builds compute them with -DCLOTH_NORMALS,
in the documented order (bit-exact with clothbench.harness.normals in strict mode), for the
state the step read: read_normals() belongs to read()[1]. Without the option the kernels
neither compute them nor take their buffer.

Meshes, moving colliders and pins attached to a body (docs/semantics.md; the kernel side
is kernels/collide_mesh.cl and the CLOTH_MESHES / CLOTH_PER_STEP / CLOTH_ATTACHED_PINS parts
of verlet_cloth.cl), both builds, each compiled only where the scene has it:
  meshes     the triangles, their pseudo-normals and (accelerated) the BVH go up once, in two
             buffers (collide_mesh.cl's header has the layout); the pose is six rows of the
             collider table. options.mesh_collision picks the search, a build option: naive
             (every triangle in index order) or accelerated (the host's BVH), the default.
  motion     a moving collider or attached pins: the table (and the pin targets) of every
             step, evaluated on the host in float64 at t = (k+1) dt (k counted from the last
             upload()) and rounded once, goes up before the launches that read it, up to
             bodies.STEPS_PER_UPLOAD steps at a time, inside advance() (so the harness times it);
             each launch takes the index of its first step. No rebuild, every shape (the
             multi-step kernel reads one table per step of its launch).
The generic build takes these parts as -D options too (one program per set of them).

Self-collision ([self_collision], docs/semantics.md), either build, only where the scene has
it (-DCLOTH_SELF_COLLISION, kernels/self_collision.cl): the step's kernels leave the colliders
out and write x_new; then per step the cells are keyed and sorted (self_contact.py) and one
launch reads x_new, pushes the pairs apart, collides, and writes a fifth state buffer, which
the references then rotate into the state. The specialised build runs only its default shape
there (verlet_shapes.candidates).

Timings of these variants, and where the specialisation gain comes from: docs/opencl.md.
"""

from __future__ import annotations

import os

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.variant_names import TRANSFERS
from clothbench.backends.base import Backend, BackendOptions, Capabilities
from clothbench.model.kernel_inputs import VerletConstants
from clothbench.backends.opencl import verlet_shapes as shapes
from clothbench.backends.opencl.bodies import OpenCLBodiesMixin, collider_counts
from clothbench.backends.opencl.self_contact import SelfContact, include_text
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    arithmetic_options,
    build_program,
    choose_device,
    program_source,
    shape_options,
)
from clothbench.backends.opencl.device import probe  # noqa: F401  (the registry asks this module)

KERNEL_FILE = "verlet_cloth.cl"


class OpenCLBackend(OpenCLBodiesMixin, OpenCLDeviceMixin, Backend):
    name = "opencl"
    capabilities = Capabilities(
        transfers=TRANSFERS["opencl"],
        local_size=True,
        generic=True,  # --generic: the float4 kernel, one program for every scene
        normals=True,
        device=True,
        shapes=True,  # verlet_shapes.py; the specialised build only
        meshes=("verlet",),  # not opencl/pbd.py, whose Capabilities are its own
        moving_colliders=("verlet",),
        boxes=("verlet",),
        self_collision=("verlet",),
        # the first is the default: faster from a few hundred triangles up (docs/opencl.md)
        mesh_collisions=("accelerated", "naive"),
        sweep_variants=({"strict": True}, {"strict": False}, {"strict": False, "transfer": "per-step"}),
    )

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.transfer = options.transfer or self.capabilities.transfers[0]
        self.strict, self.generic = options.strict, options.generic
        n = self.n = scene.grid
        self.n2 = n * n

        self._open_queue(options)
        cl, context = self._cl, self._context

        # The numbers, rounded once from float64 (docs/semantics.md, Constants), typed below.
        c, float4 = VerletConstants.of(scene, solver), cl.cltypes.make_float4
        self._constants = (c.k, c.b, c.dt, c.dt2, float4(*c.g, 0.0), float4(*c.rest, 0.0))
        self._constant_dtypes = [np.float32] * 4 + [cl.cltypes.float4] * 2
        # meshes, motion, attached pins (bodies.py): step k's poses are at (k + 1) dt
        self._open_bodies(solver.dt, shapes.STEPS_PER_LAUNCH)
        # [self_collision]: its numbers and sort buffers; None: no pass, no code
        self._contact = SelfContact.of(scene, cl, context)
        generated = {"mesh_colliders": self._mesh_source, "self_collision": lambda: include_text(self._contact)}
        self._source = program_source(KERNEL_FILE, generated)

        # State buffers, twice over: float4 per particle (generic) or x, y, z planes with
        # PAD floats before and after them (the rows kernels' masked loads reach past).
        mf = cl.mem_flags
        self._pad = 0 if self.generic else shapes.PAD
        # values from one plane to the next (the generic layout has none: float4 rows)
        self._pitch = self.n2 if self.generic else self.n2 + shapes.STATE_GAP
        state_bytes = 4 * (self.n2 * 4 if self.generic else self._pitch * 3 + 2 * self._pad)
        self._state = [cl.Buffer(context, mf.READ_WRITE, state_bytes) for _ in range(4)]
        self._host = [np.zeros(state_bytes // 4, np.float32) for _ in range(2)]  # per-step copy
        # the self-collision pass's output: it reads the step's x_new, so it cannot write there
        self._pushed = cl.Buffer(context, mf.READ_WRITE, state_bytes) if self._contact else None
        self._pass = None  # its kernels: (keys, sort stage, pass)
        self._w = np.zeros(self.n2, np.float32)  # inverse mass, as uploaded
        self._w_prev = self._w
        self._inv_mass = None if self.generic else cl.Buffer(context, mf.READ_ONLY, self.n2 * 4)
        self._border = None  # specialised: the particles of the border kernel
        # normals (docs/normals.md) of the state each step reads, only when asked for
        self.normals = options.normals
        normal_bytes = 4 * self.n2 * (4 if self.generic else 3)
        self._normals = cl.Buffer(context, mf.WRITE_ONLY, normal_bytes) if self.normals else None
        self._normals_of_prev = False  # is there a step whose normals belong to read()[1]?

        self.programs: list = []
        self.key: tuple[tuple[str, ...], ...] = ()
        if self.generic:  # one kernel for every scene: no shapes
            if options.shape is not None:
                raise ClothbenchError(f"opencl --generic has one kernel shape; drop --shape {options.shape}")
            self._use(self._generic_launches())
        else:
            self.pick_shape(
                shapes.tuning_key(self._device, scene, options, self._source, self.mesh_collision), self._time_shape
            )
            self._use_shape(self.shape)

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        if options.generic:
            return ()
        device = choose_device(options.device or os.environ.get("PYOPENCL_CTX"))
        return tuple(s.name for s in shapes.candidates(device, scene, options))

    def _use_shape(self, name: str) -> None:
        self._shape = shapes.parse(name)
        self.programs, self.key = [], ()  # those of this shape only (tuning builds several)
        self._use(self._specialised_launches(self._shape))

    def _use(self, launches) -> None:
        """Make `launches`, (kernel, work items, arguments after the state buffers), the step:
        the kernels, their launch sizes and the buffers of the normals appended."""
        self.kernels = [k for k, _, _ in launches]
        for k in self.kernels:
            self._check_local_size(k, k.function_name)
        normals = (self._normals,) if self.normals else ()
        self._launches = [(k, *self._launch_size(items), (*args, *normals)) for k, items, args in launches]
        self.effective_local_size = self._launches[0][2][0] if self._launches[0][2] else None
        if self._contact is not None:
            self._pass = self._self_collision_kernels(self._shape.width if not self.generic else 1)

    def _self_collision_kernels(self, vector_width: int):
        """The pass's kernels (cell keys, the sort's launches, the pass), from the program of
        the step's (its options: no build of its own), their arguments typed."""
        i32, f32, float4 = np.int32, np.float32, self._cl.cltypes.float4
        program = build_program(self._context, self._source, self.build_options(vector_width))

        def bound(_key, name, dtypes, args):
            k = self._cl.Kernel(program, name)
            k.set_scalar_arg_dtypes(dtypes)
            k.set_args(*args)
            return k

        kernels = [self._cl.Kernel(program, name) for name in ("self_cell_keys", "self_collision")]
        for k in kernels:
            self._check_local_size(k, k.function_name)
        keys, push = kernels
        keys.set_scalar_arg_dtypes([None, None, None, f32, i32])
        sort = [None, None, float4, i32, None]  # keys, order, the numbers, exclude2, colliders
        if self.generic:
            counts = [i32] * len(collider_counts(self.scene))
            push.set_scalar_arg_dtypes([None, None, i32, *sort, *counts, *self._body_dtypes()])
        else:
            push.set_scalar_arg_dtypes([None, None, None, *sort, *self._body_dtypes()])
        return keys, self._contact.sort_launches(bound), push

    def _enqueue_self_collision(self, x_new, out, bodies) -> None:
        """x_new (the step's output) -> out: keyed, sorted, pushed apart and collided."""
        (keys, sort_launches, push), c, queue, i32 = self._pass, self._contact, self.queue, np.int32
        slots, particles = self._launch_size(c.slots), self._launch_size(self.n2)
        self._events.append(keys(queue, *slots, x_new, c.keys, c.order, c.inv_cell, c.count))
        for kernel, global_size, local_size in sort_launches:
            self._events.append(self._cl.enqueue_nd_range_kernel(queue, kernel, global_size, local_size))
        sort = (c.keys, c.order, c.numbers, c.exclude2, self._colliders)
        if self.generic:
            counts = tuple(i32(count) for _, count in collider_counts(self.scene))
            self._events.append(push(queue, *particles, x_new, out, i32(self.n), *sort, *counts, *bodies))
        else:
            self._events.append(push(queue, *particles, x_new, self._inv_mass, out, *sort, *bodies))

    timing_repeats = 5

    def _timing_steps(self) -> int:
        return shapes.timing_steps(self.n, self._shape.steps_per_launch)

    @property
    def local_size(self) -> int | None:
        """options.local_size, else the shape's fixed work-group size (None: the runtime's)."""
        shape = getattr(self, "_shape", None)
        return self.options.local_size or (shape.work_group if shape else None)

    def build_options(self, vector_width: int = 1) -> tuple[str, ...]:
        """The specialisation key: what this scene's program is built with (the module's
        program cache is keyed by it). Generic: one key for every scene with the same
        meshes-and-motion options."""
        arithmetic = arithmetic_options(self.strict) + ("-DCLOTH_NORMALS",) * self.normals
        arithmetic += self._contact.build_options if self._contact is not None else ()
        if self.generic:
            return ("-DCLOTH_GENERIC", *self._body_options(), *arithmetic)
        shape = (*shape_options(self.scene, vector_width), *self._body_options())
        layout = (f"-DCLOTH_PAD={self._pad}", f"-DCLOTH_STATE_GAP={self._pitch - self.n2}")
        return (*shape, *layout, *arithmetic)

    def _kernel(self, name: str, dtypes, vector_width: int = 1):
        """Kernel `name` of this scene's program (built once per key, see build_program),
        created once, with every argument's type declared: a wrongly typed argument raises
        instead of being reinterpreted."""
        options = self.build_options(vector_width)
        program = build_program(self._context, self._source, options)
        self.programs.append(program)
        self.key += (options,)
        k = self._cl.Kernel(program, name)
        k.set_scalar_arg_dtypes([*dtypes, *([None] if self.normals else []), *self._body_dtypes()])
        return k

    def _generic_launches(self):
        """The float4 kernel, one work item per particle; n and the counts are arguments."""
        i32, counts = np.int32, collider_counts(self.scene)
        dtypes = [None] * 4 + [i32, *self._constant_dtypes, None] + [i32] * len(counts)
        args = (i32(self.n), *self._constants, self._colliders, *(i32(count) for _, count in counts))
        return [(self._kernel("verlet_cloth", dtypes), self.n2, args)]

    def _specialised_launches(self, shape: shapes.KernelShape):
        """split: the interior (rows and columns 2..n-3) in vectors of V particles, then
        every other particle through the border kernel. rows: every row in vectors of V, one
        kernel. steps: the rows kernel's work, several steps per launch (advance()). rows and
        steps take (pos, prev, inverse mass) and write in place; split takes pos_out and
        prev_out too."""
        n, v = self.n, shape.width
        dtypes = [None] * (3 if shape.in_place else 5) + self._constant_dtypes + [None]
        args = (*self._constants, self._colliders)
        if shape.layout == "rows":
            return [(self._kernel("verlet_cloth_rows", dtypes, v), -(-n // v) * n, args)]
        if shape.layout == "steps":  # one work-group; the step count is the last argument
            return [(self._kernel("verlet_cloth_steps", dtypes + [np.int32], v), shape.work_group, args)]
        vectors_per_row = -(-(n - 4) // v) if n - 4 >= v else 0
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : n - 2] = vectors_per_row > 0
        particles = np.flatnonzero(~covered).astype(np.int32)
        if self._border is not None:
            self._border.release()
        self._border = self._read_only_buffer(particles)
        launches = []
        if vectors_per_row:
            interior = self._kernel("verlet_cloth_interior", dtypes, v)
            launches.append((interior, vectors_per_row * (n - 4), args))
        border = self._kernel("verlet_cloth_border", dtypes + [None, np.int32])
        launches.append((border, particles.size, (*args, self._border, np.int32(particles.size))))
        return launches

    def _buffers(self) -> tuple:
        contact = self._contact.buffers() if self._contact is not None else ()
        return (
            *self._state,
            self._pushed,
            *contact,
            self._inv_mass,
            self._border,
            self._normals,
            *self._body_buffers(),
        )

    # --- Backend interface -------------------------------------------------------------
    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.queue.finish()  # pending per-step copies may still read the host copies
        self._clock = 0  # the uploaded state is at t = 0: moving bodies start over (as NumPy)
        self._w = np.ascontiguousarray(pos[:, 3], np.float32)
        self._w_prev = np.ascontiguousarray(prev[:, 3], np.float32)
        self._normals_of_prev = False
        for host, state in zip(self._host, (pos, prev)):
            host[:] = self._pack(np.asarray(state, np.float32))
        if self._inv_mass is not None:
            self._cl.enqueue_copy(self.queue, self._inv_mass, self._w)
        for buf, host in zip(self._state[:2], self._host):
            self._cl.enqueue_copy(self.queue, buf, host)
        self.queue.finish()

    def advance(self, steps: int) -> None:
        self._events = []
        multi = not self.generic and self._shape.layout == "steps"
        chunk = self._upload_steps if self._per_step else max(steps, 1)
        for done in range(0, steps, chunk):  # one chunk unless the scene moves
            count = min(chunk, steps - done)
            self._upload_step_constants(count)
            (self._advance_in_launches if multi else self._advance_per_step)(count)
            self._clock += count
        if steps > 0:
            self._w_prev = self._w  # prev_out carries pos's inverse mass
            self._normals_of_prev = self.normals

    def _step_state(self) -> tuple[tuple, list]:
        """The state buffers a step's kernels take, and the state after it: [the buffer holding
        x(t+dt), the one holding x(t), the two it leaves unused]. The chapter's four buffers
        (generic, split): x(t+dt) to pos_out, x(t) copied to prev_out, and the references swap.
        In place (rows, steps): x(t+dt) over x(t-dt) in prev, and pos and prev swap roles."""
        pos, prev, pos_out, prev_out = self._state
        if self.generic:
            return (pos, prev, pos_out, prev_out), [pos_out, prev_out, pos, prev]
        if self._shape.in_place:
            return (pos, prev, self._inv_mass), [prev, pos, pos_out, prev_out]
        return (pos, prev, self._inv_mass, pos_out, prev_out), [pos_out, prev_out, pos, prev]

    def _advance_per_step(self, steps: int) -> None:
        """One launch (or the split shape's two) per step; step j reads table j."""
        cl, queue = self._cl, self.queue
        per_step = self.transfer == "per-step"
        for j in range(steps):
            if per_step:  # the chapter's variant: the host's state goes up at every step
                cl.enqueue_copy(queue, self._state[0], self._host[0], is_blocking=False)
                cl.enqueue_copy(queue, self._state[1], self._host[1], is_blocking=False)
            state, after = self._step_state()
            bodies = self._body_args(j)
            for kernel, global_size, local_size, args in self._launches:
                self._events.append(kernel(queue, global_size, local_size, *state, *args, *bodies))
            if self._pass is not None:  # x_new -> pushed apart and collided, in the spare buffer
                self._enqueue_self_collision(after[0], self._pushed, bodies)
                after[0], self._pushed = self._pushed, after[0]
            self._state = after  # swap references, no copy
            if per_step:  # ... and both come back down, so the host owns the next step's input
                cl.enqueue_copy(queue, self._host[0], after[0], is_blocking=False)
                cl.enqueue_copy(queue, self._host[1], after[1], is_blocking=False)

    def _advance_in_launches(self, steps: int) -> None:
        """ceil(steps / K) launches of the multi-step kernel, the last with the remainder.
        It writes in place, the two state buffers swapping roles each step: the references
        swap after an odd count to match."""
        (kernel, global_size, local_size, args), k = self._launches[0], self._shape.steps_per_launch
        constants, normals = args[: len(self._constants) + 1], args[len(self._constants) + 1 :]
        for done in range(0, steps, k):
            count = min(k, steps - done)
            state, after = self._step_state()
            call = (*state, *constants, np.int32(count), *normals, *self._body_args(done))
            self._events.append(kernel(self.queue, global_size, local_size, *call))
            if count % 2:
                self._state = after

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        out = []
        for buf, w in zip(self._state[:2], (self._w, self._w_prev)):
            flat = np.empty(self._host[0].size, np.float32)
            self._cl.enqueue_copy(self.queue, flat, buf)  # blocking: waits for the steps
            out.append(self._unpack(flat, w))
        return out[0], out[1]

    def read_normals(self) -> np.ndarray | None:
        """(n*n, 4) normals of the positions the last step read, read()[1] (docs/normals.md);
        None unless options.normals, or before the first step."""
        if not self._normals_of_prev:
            return None
        flat = np.empty(self.n2 * (4 if self.generic else 3), np.float32)
        self._cl.enqueue_copy(self.queue, flat, self._normals)  # blocking: waits for the steps
        return self._unpack(flat, np.zeros(self.n2, np.float32), pad=0, pitch=self.n2)  # planes n*n apart

    # --- layouts -----------------------------------------------------------------------
    def _pack(self, state: np.ndarray) -> np.ndarray:
        """(n2, 4) -> the device layout: float4 rows (generic) or x, y, z planes, each
        STATE_GAP zeros after it, between PAD zeros."""
        if self.generic:
            return state.reshape(-1)
        flat = np.zeros(3 * self._pitch + 2 * self._pad, np.float32)
        self._planes(flat, self._pad, self._pitch)[:] = state[:, :3].T
        return flat

    def _unpack(self, flat: np.ndarray, w: np.ndarray, pad: int | None = None, pitch: int | None = None) -> np.ndarray:
        if self.generic:
            return flat.reshape(self.n2, 4)
        out = np.empty((self.n2, 4), np.float32)
        out[:, :3] = self._planes(flat, self._pad if pad is None else pad, pitch or self._pitch).T
        out[:, 3] = w
        return out

    def _planes(self, flat: np.ndarray, pad: int, pitch: int) -> np.ndarray:
        """The (3, n*n) x, y, z planes of a flat device layout: a view."""
        return flat[pad : pad + 3 * pitch].reshape(3, pitch)[:, : self.n2]
