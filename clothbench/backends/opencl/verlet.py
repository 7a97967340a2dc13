"""The OpenCL backend: kernels/verlet_cloth.cl through pyopencl (PoCL's CPU device here).

Host code only; the step is in the kernel file and docs/semantics.md. Two pairs of buffers
(positions, previous positions) are ping-ponged by swapping references, as in the chapter's
Figure 22.4: the state stays on the device and is read back only by read().

Transfer modes (options.transfer):
  resident  (default) the state never leaves the device between read() calls.
  per-step  the chapter's OpenCL variant (section 22.8): the host owns the state and uploads
            it at the start of every step; to upload the current state it must also read each
            step's result back, so a step costs one round trip. Done inside advance(), so the
            harness times it.

Which kernel runs (kernels/verlet_cloth.cl, whose header says what is a -D option and what
an argument):
  default    `verlet_cloth_interior` + `verlet_cloth_border`, built for the scene: SoA planes,
             V particles per work item (the device's preferred float width, 16 here), the
             grid side and the collider counts as -D constants, the code of a collider kind
             only when the scene has one. Programs are cached by their build options
             (`key`), so backends of the same shape (a dt or stiffness sweep too) build
             nothing. `--strict` runs them with the documented operation order and
             FP_CONTRACT OFF: bit-exact with the NumPy float32 reference.
  --generic  `verlet_cloth`, the float4 kernel that reads beside Listing 22.1: one program
             for every scene, grid side, constants and collider counts all arguments.
             Bit-exact too in strict mode; the tests hold the two builds to each other.
Normals (docs/normals.md, options.normals): both builds compute them with -DCLOTH_NORMALS,
in the documented order (bit-exact with clothbench.harness.normals in strict mode), for the
state the step read: read_normals() belongs to read()[1]. Without the option the kernels
neither compute them nor take their buffer.

Timings of these variants, and where the specialisation gain comes from: docs/opencl.md.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.scene import Scene
from clothbench.solver import Verlet
from clothbench.backends.base import Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import VerletConstants
from clothbench.backends.opencl.device import (
    OpenCLDeviceMixin,
    arithmetic_options,
    build_program,
    program_source,
    shape_options,
)
from clothbench.backends.opencl.device import probe  # noqa: F401  (the registry asks this module)

KERNEL_FILE = "verlet_cloth.cl"


class OpenCLBackend(OpenCLDeviceMixin, Backend):
    name = "opencl"
    capabilities = Capabilities(
        transfers=("resident", "per-step"),
        local_size=True,
        generic=True,  # --generic: the float4 kernel, one program for every scene
        normals=True,
        device=True,
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
        self._colliders = self._collider_buffer()

        # State buffers, twice over: float4 per particle (generic) or x, y, z planes.
        mf = cl.mem_flags
        state_bytes = self.n2 * 4 * (4 if self.generic else 3)
        self._state = [cl.Buffer(context, mf.READ_WRITE, state_bytes) for _ in range(4)]
        self._host = [np.zeros(state_bytes // 4, np.float32) for _ in range(2)]  # per-step copy
        self._w = np.zeros(self.n2, np.float32)  # inverse mass, as uploaded
        self._w_prev = self._w
        self._inv_mass = None if self.generic else cl.Buffer(context, mf.READ_ONLY, self.n2 * 4)
        self._border = None  # specialised: the particles of the border kernel
        # normals (docs/normals.md) of the state each step reads, only when asked for
        self.normals = options.normals
        self._normals = cl.Buffer(context, mf.WRITE_ONLY, state_bytes) if self.normals else None
        self._normals_of_prev = False  # is there a step whose normals belong to read()[1]?

        # One step's launches as (kernel, work items, arguments after the state buffers), and
        # the programs they come from with the options each was built with (the key).
        self.programs: list = []
        self.key: tuple[tuple[str, ...], ...] = ()
        launches = self._generic_launches() if self.generic else self._specialised_launches()
        self.kernels = [k for k, _, _ in launches]
        for k in self.kernels:
            self._check_local_size(k, k.function_name)
        normals = (self._normals,) if self.normals else ()
        self._launches = [(k, *self._launch_size(items), (*args, *normals)) for k, items, args in launches]

    def build_options(self, vector_width: int = 1) -> tuple[str, ...]:
        """The specialisation key: what this scene's program is built with (the module's
        program cache is keyed by it). Generic: one key for every scene."""
        arithmetic = arithmetic_options(self.strict) + ("-DCLOTH_NORMALS",) * self.normals
        if self.generic:
            return ("-DCLOTH_GENERIC", *arithmetic)
        return (*shape_options(self.scene, vector_width), *arithmetic)

    def _kernel(self, name: str, dtypes, vector_width: int = 1):
        """Kernel `name` of this scene's program (built once per key, see build_program),
        created once, with every argument's type declared: a wrongly typed argument raises
        instead of being reinterpreted."""
        options = self.build_options(vector_width)
        program = build_program(self._context, program_source(KERNEL_FILE), options)
        self.programs.append(program)
        self.key += (options,)
        k = self._cl.Kernel(program, name)
        k.set_scalar_arg_dtypes([*dtypes, *([None] if self.normals else [])])
        return k

    def _generic_launches(self):
        """The float4 kernel, one work item per particle; n and the counts are arguments."""
        i32, s = np.int32, self.scene
        dtypes = [None] * 4 + [i32, *self._constant_dtypes, None, i32, i32, i32]
        args = (i32(self.n), *self._constants, self._colliders)
        args += (i32(len(s.spheres)), i32(len(s.cylinders)), i32(len(s.planes)))
        return [(self._kernel("verlet_cloth", dtypes), self.n2, args)]

    def _specialised_launches(self):
        """The interior (rows and columns 2..n-3) in vectors of V particles, V the device's
        preferred float width, then every other particle through the border kernel."""
        n = self.n
        v = max(1, self._device.preferred_vector_width_float)
        vectors_per_row = -(-(n - 4) // v) if n - 4 >= v else 0
        covered = np.zeros((n, n), bool)
        covered[2 : n - 2, 2 : n - 2] = vectors_per_row > 0
        particles = np.flatnonzero(~covered).astype(np.int32)
        self._border = self._read_only_buffer(particles)
        dtypes = [None] * 5 + self._constant_dtypes + [None]
        args = (*self._constants, self._colliders)
        launches = []
        if vectors_per_row:
            interior = self._kernel("verlet_cloth_interior", dtypes, v)
            launches.append((interior, vectors_per_row * (n - 4), args))
        border = self._kernel("verlet_cloth_border", dtypes + [None, np.int32])
        launches.append((border, particles.size, (*args, self._border, np.int32(particles.size))))
        return launches

    def _buffers(self) -> tuple:
        return (*self._state, self._colliders, self._inv_mass, self._border, self._normals)

    # --- Backend interface -------------------------------------------------------------
    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.queue.finish()  # pending per-step copies may still read the host copies
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
        cl, queue = self._cl, self.queue
        per_step = self.transfer == "per-step"
        self._events = []
        for _ in range(steps):
            pos, prev, pos_out, prev_out = self._state
            if per_step:  # the chapter's variant: the host's state goes up at every step
                cl.enqueue_copy(queue, pos, self._host[0], is_blocking=False)
                cl.enqueue_copy(queue, prev, self._host[1], is_blocking=False)
            state = (pos, prev, pos_out, prev_out) if self.generic else (pos, prev, self._inv_mass, pos_out, prev_out)
            for kernel, global_size, local_size, args in self._launches:
                self._events.append(kernel(queue, global_size, local_size, *state, *args))
            self._state = [pos_out, prev_out, pos, prev]  # ping-pong: swap references, no copy
            if per_step:  # ... and comes back down, so the host owns the next step's input
                cl.enqueue_copy(queue, self._host[0], pos_out, is_blocking=False)
                cl.enqueue_copy(queue, self._host[1], prev_out, is_blocking=False)
        if steps > 0:
            self._w_prev = self._w  # prev_out carries pos's inverse mass
            self._normals_of_prev = self.normals

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
        flat = np.empty(self._host[0].size, np.float32)
        self._cl.enqueue_copy(self.queue, flat, self._normals)  # blocking: waits for the steps
        return self._unpack(flat, np.zeros(self.n2, np.float32))

    # --- layouts -----------------------------------------------------------------------
    def _pack(self, state: np.ndarray) -> np.ndarray:
        """(n2, 4) -> the device layout: float4 rows (generic) or x, y, z planes."""
        return state.reshape(-1) if self.generic else state[:, :3].T.reshape(-1)

    def _unpack(self, flat: np.ndarray, w: np.ndarray) -> np.ndarray:
        if self.generic:
            return flat.reshape(self.n2, 4)
        out = np.empty((self.n2, 4), np.float32)
        out[:, :3] = flat.reshape(3, self.n2).T
        out[:, 3] = w
        return out
