"""How the CUDA backend launches kernels/verlet_cloth.cu: its kernel shapes and the ping-pong.

Two kernels, one module (docs/cuda.md):

- `verlet_step`, one step a launch, one thread a particle, in blocks of 64..512 threads: the
  shapes "block=64" .. "block=512";
- `verlet_steps`, up to K steps a launch in one block that holds the grid in shared memory
  (24 bytes a particle), for grids that fit: the shapes "steps/launch=K".

`PingPong` holds the host side once, written against a small runtime (allocate, copy, launch),
so that the CuPy backend and the CPU build of the same kernels (cpu.py, for the tests) are
driven with the same argument list, launch geometry, shared memory and swap or copy.

A scene with meshes adds two buffers, uploaded once (`mesh_buffers`); a scene with motion
(moving colliders, pins attached to a body) adds a table of per-step rows (`MotionTable`),
uploaded a window of steps at a time, and a pin-slot buffer (docs/cuda.md, "Meshes and motion").
A scene with [self_collision] adds the pass's launches after each verlet_step launch
(self_contact.py).
"""

from __future__ import annotations

import math
import re
from functools import lru_cache

import numpy as np

from clothbench.model.colliders.kinds import kinds_in
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver
from clothbench.backends.cuda.self_contact import SelfContact
from clothbench.variant_names import TRANSFERS as ALL_TRANSFERS
from clothbench.model.kernel_inputs import (
    MeshConstants,
    VerletConstants,
    collider_rows,
    pin_targets,
    pose_rows,
)

TRANSFERS = ALL_TRANSFERS["cuda"]  # the first is the default
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

# The mesh buffers' layout (kernels/collide_mesh.cuh): float4 rows and ints per mesh header,
# float4 rows per triangle (a, b, c and the 7 pseudo-normals)
MESH_HEADER_ROWS = 5
MESH_HEADER_INTS = 8
MESH_TRIANGLE_ROWS = 10
# Steps of per-step rows on the device at once, at most MOTION_WINDOW_BYTES of them: upload()
# loads the first window, a launch that would run past it loads the next (docs/cuda.md,
# "Meshes and motion")
MOTION_WINDOW = 4096
MOTION_WINDOW_BYTES = 16 * 2**20


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
        "dt": c.dt,
        "dt2": c.dt2,
        "k": c.k,
        "b": c.b,
        "gx": gx,
        "gy": gy,
        "gz": gz,
        "rest_structural": structural,
        "rest_shear": shear,
        "rest_bend": bend,
    }


def mesh_buffers(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(rows, ints): every mesh of the scene in the layout kernels/collide_mesh.cuh reads, float32
    rows of four and int32, from kernel_inputs.MeshConstants (rounded once) and the BVH."""
    meshes = [MeshConstants.of(m) for m in scene.meshes]
    row, count = MESH_HEADER_ROWS * len(meshes), MESH_HEADER_INTS * len(meshes)
    headers, header_ints, triangles, boxes, links = [], [], [], [], []
    for mesh, constants in zip(scene.meshes, meshes):
        bvh = constants.geometry.bvh
        rot, trans = pose_rows(mesh, 0.0)  # the fixed pose; a moving mesh's is per step
        headers += [
            (*constants.lo, constants.margin),
            (*constants.hi, constants.margin2),
            *np.concatenate([rot, trans[:, None]], axis=1),
        ]
        tris = len(constants.corners)
        node_row = row + MESH_TRIANGLE_ROWS * tris
        link, leaves = count, count + 3 * bvh.nodes
        header_ints += [row, tris, node_row, link, leaves, int(constants.closed), 0, 0]
        rows = np.zeros((tris, MESH_TRIANGLE_ROWS, 4), np.float32)
        rows[:, :3, :3] = constants.corners
        rows[:, 3:, :3] = constants.normals
        triangles.append(rows.reshape(-1, 4))
        node = np.zeros((bvh.nodes, 2, 4), np.float32)
        node[:, 0, :3], node[:, 1, :3] = bvh.lo, bvh.hi
        boxes.append(node.reshape(-1, 4))
        links.append(np.concatenate([np.stack([bvh.child, bvh.first, bvh.count], axis=1).reshape(-1), bvh.tris]))
        row, count = node_row + 2 * bvh.nodes, leaves + len(bvh.tris)
    # mesh_rows: the headers, then each mesh's triangles and then its node boxes
    body = [part for pair in zip(triangles, boxes) for part in pair]
    rows = np.concatenate([np.array(headers, np.float32).reshape(-1, 4), *body])
    ints = np.concatenate([np.array(header_ints, np.int32), *(a.astype(np.int32) for a in links)])
    assert len(rows) == row and len(ints) == count
    return np.ascontiguousarray(rows), np.ascontiguousarray(ints)


def pin_slots(scene: Scene) -> np.ndarray:
    """Per particle, its row among the step's pin targets, or -1 (int32): the pinned particles
    in scene.pinned() order where the pins follow a body, else none."""
    slots = np.full(scene.particles, -1, np.int32)
    if scene.pin_attach is not None:
        pinned = scene.pinned()
        slots[pinned] = np.arange(len(pinned), dtype=np.int32)
    return slots


def attached_pins(scene: Scene) -> int:
    """How many pinned particles follow a body: all of them where [pins] attach, else none."""
    return len(scene.pinned()) if scene.pin_attach is not None else 0


def motion_rows(scene: Scene) -> int:
    """Rows of the per-step table: every collider's rows, 3 per mesh, one per attached pin."""
    return sum(len(r) for r in collider_rows(scene).values()) + 3 * len(scene.meshes) + attached_pins(scene)


def motion_window(rows: int, steps_per_launch: int | None) -> int:
    """Steps of per-step rows the device holds at once: MOTION_WINDOW, fewer where they would
    pass MOTION_WINDOW_BYTES, never fewer than a launch takes."""
    fits = MOTION_WINDOW_BYTES // (16 * rows)
    return max(steps_per_launch or 1, min(MOTION_WINDOW, fits))


@lru_cache(maxsize=8)
def motion_table(scene: Scene, dt: float) -> "MotionTable":
    """One table per scene and dt: every PingPong of it (a backend's, each shape the tuning
    times) shares the steps already evaluated."""
    return MotionTable(scene, dt)


class MotionTable:
    """The per-step rows of a moving scene (docs/semantics.md, "Moving colliders", "Pins
    attached to a body"): for step k since the last upload, the poses at t = (k + 1) dt, evaluated
    in float64 on the host and rounded once (kernel_inputs), in the layout verlet_cloth.cu reads
    (`step_rows`): collider rows, then each mesh's (R row i, T_i), then the pins' targets.

    Each step index is evaluated once and kept (an upload starts the clock again at step 0, so
    a second run reuses them)."""

    def __init__(self, scene: Scene, dt: float):
        self.scene, self.dt = scene, dt
        self.rows = max(1, motion_rows(scene))  # never a zero-size buffer
        self.host = np.zeros((0, self.rows, 4), np.float32)

    def step_rows(self, step: int) -> np.ndarray:
        time = (step + 1) * self.dt  # the end of the step, t as an integer times dt
        s = self.scene
        parts = list(collider_rows(s, np.float32, time).values())
        for mesh in s.meshes:
            rot, trans = pose_rows(mesh, time)
            parts.append(np.concatenate([rot, trans[:, None]], axis=1))
        if s.pin_attach is not None:
            targets = pin_targets(s, time)
            parts.append(np.concatenate([targets, np.zeros((len(targets), 1), np.float32)], axis=1))
        out = np.zeros((self.rows, 4), np.float32)
        rows = np.concatenate([p.reshape(-1, 4) for p in parts])
        out[: len(rows)] = rows
        return out

    def window(self, first: int, steps: int) -> np.ndarray:
        """The rows of steps first .. first + steps - 1, (steps * rows, 4)."""
        end = first + steps
        if len(self.host) < end:
            more = [self.step_rows(k) for k in range(len(self.host), end)]
            self.host = np.concatenate([self.host, np.stack(more)])
        return self.host[first:end].reshape(-1, 4)


class MotionWindow:
    """A moving scene's per-step rows on the device, a window of `steps` steps at a time
    (docs/cuda.md, "Meshes and motion"): load(0) at upload, outside any timed region; rows()
    loads the next window when a launch would run past this one."""

    def __init__(self, runtime, table: MotionTable, steps_per_launch: int | None):
        self.runtime, self.table = runtime, table
        self.steps = motion_window(table.rows, steps_per_launch)
        self.buffer = runtime.alloc(np.zeros((self.steps * table.rows, 4), np.float32))
        self.first = 0  # the first step the device window holds

    def load(self, first: int) -> None:
        self.runtime.upload(self.buffer, self.table.window(first, self.steps))
        self.first = first

    def rows(self, step: int, steps: int):
        """The device rows of steps step .. step + steps - 1 on (a view into the window)."""
        offset = step - self.first
        if offset < 0 or offset + steps > self.steps:
            # inside advance(), so inside a timed chunk: one upload of a window of steps (and
            # their host evaluation, the first time a step index is reached), every `steps`
            # steps; upload() loaded the first one outside it
            self.load(step)
            offset = 0
        return self.buffer[offset * self.table.rows :]


class PingPong:
    """The state buffers and the launches on them, for any runtime that has

        alloc(host array) -> buffer       upload(buffer, host array)   download(buffer) -> array
        copy(dst, src)  (device to device)       launch(grid, block, args, shared_bytes)

    The runtime holds one kernel: verlet_step where steps_per_launch is None (a launch a step,
    in blocks of `block` threads), else verlet_steps (one block of `block` threads, up to
    steps_per_launch steps a launch). CudaBackend's runtime is CuPy; cpu.py's is the CPU build
    of the same kernels, so both launch them with the argument list built here, in this order.
    `generic` and `normals` must be those the kernels were built with (kernel_defines), and
    the transfer too: `swap` (the default) holds two buffers, x(t) and x(t - dt), a launch writes
    its latest state over the second and the host swaps their roles; `copy` (CLOTH_TWO_PAIRS)
    the chapter's two pairs (in, out), copied out to in after each launch.
    A scene with [self_collision] needs verlet_step and `self_collision`: a runtime for each of
    the pass's kernels (self_contact.KERNELS).
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
        self_collision: tuple | None = None,
    ):
        if transfer not in TRANSFERS:
            raise ValueError(f"transfer must be swap or copy, got {transfer!r}")
        if steps_per_launch is not None and steps_per_launch < 1:
            raise ValueError(f"steps_per_launch must be >= 1, got {steps_per_launch}")
        if scene.self_collision is not None and (steps_per_launch is not None or self_collision is None):
            raise ValueError("a self-colliding scene runs verlet_step with the pass's kernels (self_collision=...)")
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
        moving = scene.has_motion
        if generic:
            colliders = []
            table = collider_rows(scene)
            for kind in kinds_in("cuda"):  # the kinds verlet_cloth.cu takes, each a buffer and a count
                rows = table[kind.plural]
                if not moving:  # a moving scene's rows are in the per-step table
                    # never a zero-size buffer: its pointer is passed even when no collider is read
                    colliders.append(runtime.alloc(rows if len(rows) else np.zeros((1, 4), np.float32)))
                colliders.append(np.int32(len(rows) // kind.rows))
            self.scene_args = (*kernel_constants(scene, solver).values(), *colliders)
        # what the pass's colliders take (generic: n and the collider arguments)
        self.pass_args: tuple = (np.int32(scene.grid), *colliders) if generic else ()
        self.mesh_args: tuple = ()
        if scene.meshes:  # uploaded once: the body frame does not change when a mesh moves
            rows, ints = mesh_buffers(scene)
            self.mesh_args = (runtime.alloc(rows), runtime.alloc(ints))
            if generic:
                self.mesh_args += (np.int32(len(scene.meshes)),)
        # moving scenes: the window of the per-step table on the device, the pin slots
        self.motion = MotionWindow(runtime, motion_table(scene, solver.dt), steps_per_launch) if moving else None
        self.steps_done = 0  # steps since the last upload: the clock of the motion
        if self.motion is not None:
            with_pins = generic or attached_pins(scene) > 0  # as the kernel's HAS_PIN_TARGETS
            self.pin_args = (runtime.alloc(pin_slots(scene)),) if with_pins else ()
            self.generic = generic
        empty = np.zeros((scene.particles, 4), dtype=np.float32)
        self.pos_in, self.prev_in = runtime.alloc(empty), runtime.alloc(empty)  # x(t), x(t - dt)
        self.pos_out = self.prev_out = None  # in place: the launch writes over the input pair
        if transfer == "copy":
            self.pos_out, self.prev_out = runtime.alloc(empty), runtime.alloc(empty)
        self.normals = runtime.alloc(empty) if normals else None  # written, never read back in
        self.contact = SelfContact(scene, self_collision, block) if scene.self_collision is not None else None
        self.has_normals = False  # whether the last launch since upload() wrote them

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        self.runtime.upload(self.pos_in, np.ascontiguousarray(pos, dtype=np.float32))
        self.runtime.upload(self.prev_in, np.ascontiguousarray(prev, dtype=np.float32))
        self.has_normals = False
        self.steps_done = 0  # the uploaded state is at t = 0: the bodies start over
        if self.motion is not None:  # the first window now, outside any timed advance()
            self.motion.load(0)

    def motion_args(self, steps: int) -> tuple:
        """The per-step rows of the next `steps` steps (a view into the device window, reloaded
        when they would run past it) and the pin slots; () without motion."""
        if self.motion is None:
            return ()
        view = self.motion.rows(self.steps_done, steps)
        rows = (np.int32(self.motion.table.rows),) if self.generic else ()
        return (view, *rows, *self.pin_args)

    def args(self, steps: int = 1, motion: tuple | None = None) -> tuple:
        """The kernel's arguments, in its parameter order; `steps` is verlet_steps' count (and,
        in a moving scene, how many steps of rows the launch reads from the step count on);
        `motion`, motion_args(steps) where the caller has them already."""
        buffers = (self.pos_in, self.prev_in)
        if self.transfer == "copy":
            buffers += (self.pos_out, self.prev_out)
        if self.normals is not None:
            buffers += (self.normals,)
        if self.steps_per_launch is not None:
            buffers += (np.int32(steps),)
        motion = self.motion_args(steps) if motion is None else motion
        return (*buffers, *self.scene_args, *self.mesh_args, *motion)

    def launches(self, steps: int) -> list[int]:
        """The steps of each launch that advance(steps) makes: all of steps_per_launch, then
        the remainder."""
        if self.steps_per_launch is None:
            return [1] * steps
        full, rest = divmod(steps, self.steps_per_launch)
        return [self.steps_per_launch] * full + [rest] * (rest > 0)

    def advance(self, steps: int) -> None:
        for count in self.launches(steps):
            motion = self.motion_args(count)
            self.runtime.launch(self.grid, self.block, self.args(count, motion), self.shared_bytes)
            if self.contact is not None:  # x_new pushed apart and collided, at the step's rows
                tail = (*self.pass_args, *self.mesh_args, *motion[:1])
                if self.transfer == "copy":
                    self.pos_out = self.contact.push(self.pos_out, tail)
                else:  # in place: x_new is over x(t - dt)
                    self.prev_in = self.contact.push(self.prev_in, tail)
            if self.transfer == "copy":  # the chapter: cudaMemcpy(in, out, DeviceToDevice), per launch
                self.runtime.copy(self.pos_in, self.pos_out)
                self.runtime.copy(self.prev_in, self.prev_out)
            else:  # the latest state is over x(t - dt): swap the two's roles, move no data
                self.pos_in, self.prev_in = self.prev_in, self.pos_in
            self.steps_done += count
            self.has_normals = self.normals is not None

    def step(self) -> None:
        self.advance(1)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(pos, prev) after the last step: always the input pair, whichever the transfer."""
        return self.runtime.download(self.pos_in), self.runtime.download(self.prev_in)

    def read_normals(self) -> np.ndarray | None:
        """The normals of read()[1], x(t) of the last step; None before a step or unasked."""
        return self.runtime.download(self.normals) if self.has_normals else None
