"""The VBD solver (docs/vbd.md) on CUDA: kernels/vbd_cloth.cu through CuPy.

Host code only; the step is the kernel file's and docs/vbd.md's. A substep is a fixed list of
launches on one stream (each sees the one before): predict, then per iteration one launch per
vertex colour (and with Chebyshev one extrapolation), collide, update, each in blocks of the
kernel shape's threads (`block=N`, launch.BLOCK_SIZES, chosen per device and scene by
measurement as the Verlet class's block sizes are; --local-size fixes it); with [self_collision],
self_contact.py's pass (keys, sort stages, the pass and the colliders) from xs into y in place
of collide, and update reads y (docs/vbd.md, "Self-collision"). `VbdLaunches` holds that
list once, written against PingPong's small runtime (alloc, upload, download, launch), one
runtime per kernel: CudaVbdBackend's are CuPy's, cpu.py's ShimRuntime runs the CPU build of
the same kernels (the tests). The numbers are VbdConstants' (model/kernel_inputs.py).

The device, the compilation (NVRTC or nvcc, strict or fast: verlet.compile_options), the
stream and the events are CudaDevice's, shared with the Verlet class. The colliders, meshes
included, are kernels/collide.cuh's, the Verlet kernel's own code, built for the scene
(scene_defines); moving colliders and attached pins take one row set per substep, at its end,
from launch.py's per-step table and its window on the device.

Not tried yet: whole substeps in one block on a small grid (the colours separated by
__syncthreads(), as verlet_steps does it for Verlet steps).
"""

from __future__ import annotations

import math

import numpy as np

from clothbench.model.constraints import VERTEX_COLOURS, vertex_colours
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Vbd
from clothbench.backends.base import BackendOptions, Capabilities
from clothbench.model.kernel_inputs import VbdConstants
from clothbench.backends.pbd_device import position_state, velocity_state
from clothbench.backends.cuda.launch import (
    AUTO_BLOCK,
    BLOCK_SIZES,
    MotionWindow,
    attached_pins,
    mesh_buffers,
    motion_table,
    parse_shape,
    pin_slots,
)
from clothbench.backends.cuda.self_contact import KERNELS as SELF_KERNELS, SelfContact, self_collision_defines
from clothbench.backends.cuda.verlet import CudaBackend, CudaDevice, CupyRuntime, scene_defines
from clothbench.backends.tuning import sweeps_key

KERNEL_FILE = "vbd_cloth.cu"
PREDICT, SWEEP, CHEBYSHEV, COLLIDE, UPDATE = "vbd_predict", "vbd_sweep", "vbd_chebyshev", "vbd_collide", "vbd_update"
KERNELS = (PREDICT, SWEEP, CHEBYSHEV, COLLIDE, UPDATE)


def kernels_of(scene: Scene) -> tuple[str, ...]:
    """The kernels a build for this scene has: KERNELS, and with [self_collision] the pass's."""
    return (*KERNELS, *(SELF_KERNELS if scene.self_collision is not None else ()))


def vbd_defines(scene: Scene, mesh_collision: str | None = None) -> tuple[str, ...]:
    """The -D switches that build vbd_cloth.cu for this scene: the grid side and the scene's
    colliders, meshes and motion as collide.cuh takes them (the Verlet kernel's), and the
    self-collision pass where the scene has it."""
    return (f"-DCLOTH_N={scene.grid}", *self_collision_defines(scene), *scene_defines(scene, mesh_collision))


class VbdLaunches:
    """The device state of docs/vbd.md's step and the launches of one substep.

    `runtimes[name]` runs kernel `name` (kernels_of(scene)) and allocates and moves buffers (any of them
    does), as PingPong's runtime: CuPy's on a device, the CPU build's in the tests. The
    kernels must be built with vbd_defines(scene, ...)."""

    def __init__(self, runtimes: dict, scene: Scene, solver: Vbd, block: int = AUTO_BLOCK):
        self.runtimes, self.block = runtimes, block
        self.substeps = solver.substeps
        rt = runtimes[PREDICT]
        self.n2 = scene.particles
        c = self.constants = VbdConstants.of(scene, solver)
        self.chebyshev = solver.chebyshev_rho > 0
        empty = np.zeros((self.n2, 4), np.float32)
        self.x, self.v, self.xs, self.y = (rt.alloc(empty) for _ in range(4))
        # Chebyshev: the inputs of the last two sweeps, taking turns
        self.before = (rt.alloc(empty), rt.alloc(empty)) if self.chebyshev else ()
        # every particle, by colour (the sweep's order); a launch per colour reads its range
        colour = vertex_colours(scene.grid)
        self.order = rt.alloc(np.argsort(colour, kind="stable").astype(np.int32))
        counts = np.bincount(colour, minlength=VERTEX_COLOURS)
        mesh = tuple(rt.alloc(b) for b in mesh_buffers(scene)) if scene.meshes else ()
        # moving scenes: substep j's rows, at its end ((j + 1) h counted from the upload), as the
        # per-step table gives step j's at (j + 1) dt: the table of h
        self.motion = (
            MotionWindow(rt, motion_table(scene, solver.dt / solver.substeps), 1) if scene.has_motion else None
        )
        pins = (rt.alloc(pin_slots(scene)),) if scene.has_motion and attached_pins(scene) else ()
        self.substeps_done = 0  # since the last upload(): the clock of moving bodies
        f32, i32 = np.float32, np.int32

        # one substep as (kernel, threads, arguments, whether the substep's rows follow them,
        # what follows those): predict reads the attached pins' targets, collide the colliders
        plan = [(PREDICT, self.n2, (self.x, self.v, self.xs, self.y, c.h, *c.gh2), bool(pins), pins)]
        sweeps, first = [], 0
        for count in counts:
            args = (self.xs, self.y, self.x, self.order, i32(first), i32(count), c.mh2, c.bh, c.k, *c.rest)
            sweeps.append((SWEEP, int(count), args, False, ()))
            first += count
        if self.chebyshev:  # the first sweep's input: the predicted iterate
            plan.append((CHEBYSHEV, self.n2, (self.xs, self.before[0], f32(1), i32(0)), False, ()))
        for it in range(solver.iterations):
            plan += sweeps
            if self.chebyshev:  # extrapolate from sweep it - 1's input (none after sweep 0), keep sweep it + 1's
                args = (self.xs, self.before[(it + 1) % 2], c.omega[it], i32(it > 0))
                plan.append((CHEBYSHEV, self.n2, args, False, ()))
        final = self.xs  # the positions the update reads
        if scene.self_collision is not None:  # the pass and then the colliders, from the iterate into y
            contact = SelfContact(scene, [runtimes[name] for name in SELF_KERNELS], block, spare=False)
            for kernel, threads, args in contact.launches(self.xs, self.y, mesh):
                plan.append((kernel, threads, args, kernel == SELF_KERNELS[-1] and self.motion is not None, ()))
            final = self.y
        elif scene.colliders or scene.meshes:
            plan.append((COLLIDE, self.n2, (self.xs, *mesh), self.motion is not None, ()))
        plan.append((UPDATE, self.n2, (self.x, self.v, final, c.h), False, ()))
        self.plan = plan

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if np.shape(pos) != expected or np.shape(prev) != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {np.shape(pos)} and {np.shape(prev)}")
        x, v = velocity_state(pos, prev, self.constants.dt)  # docs/vbd.md, as PBD's
        rt = self.runtimes[PREDICT]
        rt.upload(self.x, x)
        rt.upload(self.v, v)
        self.substeps_done = 0  # the uploaded state is at t = 0: moving bodies start over
        if self.motion is not None:  # the first window now, outside any timed advance()
            self.motion.load(0)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        rt = self.runtimes[PREDICT]
        return position_state(rt.download(self.x), rt.download(self.v), self.constants.dt)

    def advance(self, steps: int) -> None:
        for _ in range(steps * self.substeps):
            rows = (self.motion.rows(self.substeps_done, 1),) if self.motion is not None else ()
            for kernel, threads, args, with_rows, extra in self.plan:
                if threads:  # an empty colour (a 1 x 1 grid) launches nothing
                    launch_args = (*args, *(rows if with_rows else ()), *extra)
                    self.runtimes[kernel].launch(math.ceil(threads / self.block), self.block, launch_args)
            self.substeps_done += 1


class CudaVbdBackend(CudaDevice):
    """VBD on a CUDA device: the Verlet class's device, compiler, stream and events (CudaDevice),
    vbd_cloth.cu's kernels, in blocks of the tuned shape's threads."""

    name = "cuda"
    kernel_file = KERNEL_FILE
    capabilities = Capabilities(
        local_size=True,  # the threads a block of every launch
        device=True,
        shapes=True,  # block=N: the threads a block of every launch (kernel_shapes)
        # collide.cuh is the Verlet kernel's collider code, so every scene feature it takes
        meshes=("vbd",),
        moving_colliders=("vbd",),
        boxes=("vbd",),
        self_collision=("vbd",),  # self_contact.py's pass, after the sweeps, before the colliders
        mesh_collisions=CudaBackend.capabilities.mesh_collisions,
        sweep_variants=({"strict": True}, {"strict": False}),
    )

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        module = self._open_device(options, vbd_defines(scene, self.mesh_collision))
        kernels = {name: module.get_function(name) for name in kernels_of(scene)}
        for kernel in kernels.values():
            self._check_local_size(kernel)
        self._threads_limit = min(kernel.max_threads_per_block for kernel in kernels.values())
        self._runtimes = {name: CupyRuntime(kernel, self.stream) for name, kernel in kernels.items()}
        self.state = self._shape_state(self.pick_shape(self._tuning_key(), self._time_shape))

    # a VBD step is tens of launches (a sweep a colour): fewer steps than Verlet's time a shape
    tuning_steps = 16

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        """block=N for each of launch.BLOCK_SIZES (the first the default), or --local-size's only."""
        return tuple(f"block={b}" for b in ((options.local_size,) if options.local_size else BLOCK_SIZES))

    def _tuning_key(self) -> dict[str, str]:
        return {
            **self._device_key(),
            **sweeps_key(self.solver),
            **({"self_collision": "after the sweeps"} if self.scene.self_collision is not None else {}),
        }

    def _shape_state(self, shape: str) -> VbdLaunches:
        """The launches of one substep in blocks of `shape`'s threads (block=N)."""
        _, block = parse_shape(shape, self.scene.particles)
        if block > self._threads_limit:
            raise ClothbenchError(f"cuda {shape}: {block} threads a block, at most {self._threads_limit} here")
        self.effective_local_size = block
        return VbdLaunches(self._runtimes, self.scene, self.solver, block)


__all__ = ["CudaVbdBackend", "VbdLaunches", "vbd_defines"]
