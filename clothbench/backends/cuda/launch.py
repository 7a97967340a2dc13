"""How the CUDA backend launches kernels/verlet_cloth.cu: its kernel shapes and the ping-pong.

Two kernels, one module (docs/cuda.md):

- `verlet_step`, one step a launch, one thread a particle, in blocks of 64..512 threads: the
  shapes "block=64" .. "block=512";
- `verlet_steps`, up to K steps a launch in one block that holds the grid in shared memory
  (24 bytes a particle), for grids that fit: the shapes "steps/launch=K".

`PingPong` holds the host side once, written against a small runtime (allocate, copy, launch),
so that the CuPy backend and the CPU build of the same kernels (cpu.py, for the tests) are
driven with the same argument list, launch geometry, shared memory and swap or copy.
"""

from __future__ import annotations

import math
import re

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.scene import Scene
from clothbench.solver import Solver
from clothbench.backends.kernel_inputs import ROWS_PER_COLLIDER, VerletConstants, collider_rows

TRANSFERS = ("swap", "copy")  # the first is the default
STEP_KERNEL = "verlet_step"
STEPS_KERNEL = "verlet_steps"
AUTO_BLOCK = 256  # threads per block of verlet_step when neither --local-size nor tuning says
BLOCK_SIZES = (AUTO_BLOCK, 64, 128, 512)  # verlet_step's candidates; the first is the default
STEPS_PER_LAUNCH = (16, 64)  # verlet_steps' candidates, where the grid fits one block
MULTISTEP_MAX_THREADS = 1024  # verlet_steps' __launch_bounds__ (kernels/verlet_cloth.cu)
SHARED_BYTES_PER_PARTICLE = 24  # x(t) and x(t - dt), three floats each
# The dynamic shared memory a block may opt into, where the device cannot be asked: the least
# of any sm_80 or newer device (sm_86, sm_89, sm_120: 99 KiB; sm_80, sm_87: 163 KiB; sm_90,
# sm_100: 227 KiB), so a 64 x 64 grid (96 KiB) fits everywhere.
SMALLEST_SHARED_OPTIN = 99 * 1024

_SHAPE = re.compile(r"block=(\d+)|steps/launch=(\d+)")


def multistep_shared_bytes(particles: int) -> int:
    """verlet_steps' dynamic shared memory for a grid of `particles`."""
    return SHARED_BYTES_PER_PARTICLE * particles


def multistep_threads(particles: int, local_size: int | None = None) -> int:
    """verlet_steps' one block: --local-size if given, else a thread a particle up to 1024
    (a whole number of warps), each thread taking every blockDim-th particle beyond that."""
    return local_size or min(MULTISTEP_MAX_THREADS, 32 * math.ceil(particles / 32))


def kernel_shapes(particles: int, local_size: int | None, shared_limit: int) -> tuple[str, ...]:
    """The shapes a grid of `particles` can run with: verlet_step in each block size (only
    --local-size's where given), then verlet_steps where its state fits `shared_limit` bytes."""
    names = [f"block={b}" for b in ((local_size,) if local_size else BLOCK_SIZES)]
    if multistep_shared_bytes(particles) <= shared_limit and (local_size or 0) <= MULTISTEP_MAX_THREADS:
        names += [f"steps/launch={k}" for k in STEPS_PER_LAUNCH]
    return tuple(names)


def parse_shape(name: str, particles: int, local_size: int | None = None) -> tuple[int | None, int]:
    """(steps per launch, threads per block) of a shape name; None steps: verlet_step."""
    match = _SHAPE.fullmatch(name)
    if not match:
        raise ClothbenchError(f"cuda kernel shape must be block=N or steps/launch=K, got {name!r}")
    if match[1]:
        return None, int(match[1])
    return int(match[2]), multistep_threads(particles, local_size)


def kernel_constants(scene: Scene, solver: Solver) -> dict[str, object]:
    """The step's constants (kernel_inputs.VerletConstants), in kernel parameter order."""
    c = VerletConstants.of(scene, solver)
    (gx, gy, gz), (structural, shear, bend) = c.g, c.rest
    return {
        "n": np.int32(scene.grid),
        "dt": c.dt, "dt2": c.dt2, "k": c.k, "b": c.b,
        "gx": gx, "gy": gy, "gz": gz,
        "rest_structural": structural, "rest_shear": shear, "rest_bend": bend,
    }  # fmt: skip


class PingPong:
    """The chapter's two pairs of buffers and the launches on them, for any runtime that has

        alloc(host array) -> buffer       upload(buffer, host array)   download(buffer) -> array
        copy(dst, src)  (device to device)       launch(grid, block, args, shared_bytes)

    The runtime holds one kernel: verlet_step where steps_per_launch is None (a launch a step,
    in blocks of `block` threads), else verlet_steps (one block of `block` threads, up to
    steps_per_launch steps a launch). CudaBackend's runtime is CuPy; cpu.py's is the CPU build
    of the same kernels, so both launch them with the argument list built here, in this order.
    `generic` and `normals` must be those the kernels were built with (kernel_defines).
    """

    def __init__(
        self,
        runtime,
        scene: Scene,
        solver: Solver,
        transfer: str = TRANSFERS[0],
        block: int = AUTO_BLOCK,
        generic: bool = False,
        normals: bool = False,
        steps_per_launch: int | None = None,
    ):
        if transfer not in TRANSFERS:
            raise ValueError(f"transfer must be swap or copy, got {transfer!r}")
        if steps_per_launch is not None and steps_per_launch < 1:
            raise ValueError(f"steps_per_launch must be >= 1, got {steps_per_launch}")
        self.runtime = runtime
        self.transfer = transfer
        self.block = block
        self.steps_per_launch = steps_per_launch
        if steps_per_launch is None:
            self.grid = math.ceil(scene.particles / block)  # blocks; the last may run past n*n
            self.shared_bytes = 0
        else:
            self.grid = 1  # the whole grid in one block, its state in shared memory
            self.shared_bytes = multistep_shared_bytes(scene.particles)
        self.scene_args: tuple = ()  # the specialised kernel has the scene compiled in
        if generic:
            colliders = []
            for kind, rows in collider_rows(scene).items():
                # never a zero-size buffer: its pointer is passed even when no collider is read
                buffer = runtime.alloc(rows if len(rows) else np.zeros((1, 4), np.float32))
                colliders += [buffer, np.int32(len(rows) // ROWS_PER_COLLIDER[kind])]
            self.scene_args = (*kernel_constants(scene, solver).values(), *colliders)
        empty = np.zeros((scene.particles, 4), dtype=np.float32)
        self.pos_in, self.prev_in = runtime.alloc(empty), runtime.alloc(empty)
        self.pos_out, self.prev_out = runtime.alloc(empty), runtime.alloc(empty)
        self.normals = runtime.alloc(empty) if normals else None  # written, never read back in
        self.has_normals = False  # whether the last launch since upload() wrote them

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.runtime.upload(self.pos_in, np.ascontiguousarray(pos, dtype=np.float32))
        self.runtime.upload(self.prev_in, np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False

    def args(self, steps: int = 1) -> tuple:
        """The kernel's arguments, in its parameter order; `steps` is verlet_steps' count."""
        buffers = (self.pos_in, self.prev_in, self.pos_out, self.prev_out)
        if self.normals is not None:
            buffers += (self.normals,)
        if self.steps_per_launch is not None:
            buffers += (np.int32(steps),)
        return (*buffers, *self.scene_args)

    def launches(self, steps: int) -> list[int]:
        """The steps of each launch that advance(steps) makes: all of steps_per_launch, then
        the remainder."""
        if self.steps_per_launch is None:
            return [1] * steps
        full, rest = divmod(steps, self.steps_per_launch)
        return [self.steps_per_launch] * full + [rest] * (rest > 0)

    def advance(self, steps: int) -> None:
        for count in self.launches(steps):
            self.runtime.launch(self.grid, self.block, self.args(count), self.shared_bytes)
            if self.transfer == "copy":  # the chapter: cudaMemcpy(in, out, DeviceToDevice), per launch
                self.runtime.copy(self.pos_in, self.pos_out)
                self.runtime.copy(self.prev_in, self.prev_out)
            else:  # the output becomes the next input: swap the pointers, move no data
                self.pos_in, self.pos_out = self.pos_out, self.pos_in
                self.prev_in, self.prev_out = self.prev_out, self.prev_in
            self.has_normals = self.normals is not None

    def step(self) -> None:
        self.advance(1)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) after the last step: always the input pair, whichever the transfer."""
        return self.runtime.download(self.pos_in), self.runtime.download(self.prev_in)

    def read_normals(self) -> np.ndarray | None:
        """The normals of read()[1], x(t) of the last step; None before a step or unasked."""
        return self.runtime.download(self.normals) if self.has_normals else None
