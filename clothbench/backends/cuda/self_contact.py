"""[self_collision] on the CUDA Verlet step (docs/semantics.md, "Self-collision"; the kernels are
kernels/self_collision.cuh, built into verlet_cloth.cu only with -DCLOTH_SELF_COLLISION): its
numbers as the kernels take them, the sort's buffers, and the launches of one pass.

After each verlet_step launch (which then leaves the colliders out), PingPong runs the pass on
the step's x_new: self_cell_keys over the sort's slots, one self_sort_stage per stage of the
bitonic sort (model/colliders/self_contact.py's bitonic_stages), then self_collision,
which pushes the pairs apart, collides, and writes a spare state buffer; that buffer becomes the
step's output and x_new's the next spare. The VBD step (cuda/vbd.py) runs the same launches
(`launches`) from its final iterate into y, in place of vbd_collide, with no spare.
"""

from __future__ import annotations

import math

import numpy as np

from clothbench.model.kernel_inputs import SelfCollisionConstants
from clothbench.model.colliders.self_contact import bitonic_stages, sort_slots

KERNELS = ("self_cell_keys", "self_sort_stage", "self_collision")  # in launch order


def self_collision_defines(scene) -> tuple[str, ...]:
    """The -D switch that builds the pass into either kernel file: only where the scene has the table."""
    return ("-DCLOTH_SELF_COLLISION",) if scene.self_collision is not None else ()


class SelfContact:
    """One backend's pass: `runtimes` are PingPong runtimes holding KERNELS' kernels, in order;
    `block` the threads a block of every launch (the shape's, as verlet_step's); `spare`: whether
    it keeps the spare state buffer push() needs."""

    def __init__(self, scene, runtimes, block: int, spare: bool = True):
        if len(runtimes) != len(KERNELS):
            raise ValueError(f"the self-collision pass needs a runtime for each of {KERNELS}")
        self.keys_kernel, self.sort_kernel, self.pass_kernel = runtimes
        c = SelfCollisionConstants.of(scene)  # rounded once on the host, never recomputed here
        self.inv_cell = c.inv_cell
        self.numbers = (c.thickness, c.thickness2, c.relax, c.inv_cell)
        self.exclude2 = np.int32(min(c.exclude2, np.iinfo(np.int32).max))  # past 2 n^2 all alike
        self.count = np.int32(scene.particles)
        self.slots = np.int32(sort_slots(scene.particles))
        self.stages = [(np.int32(j), np.int32(k)) for j, k in bitonic_stages(int(self.slots))]
        self.block = block
        alloc = self.keys_kernel.alloc
        self.keys = alloc(np.zeros(self.slots, np.uint64))  # a cell id per slot
        self.order = alloc(np.zeros(self.slots, np.int32))  # the particle in the slot
        self.spare = alloc(np.zeros((scene.particles, 4), np.float32)) if spare else None  # push()'s output

    def launches(self, x_in, x_out, tail: tuple) -> list:
        """The pass from x_in into x_out as (kernel, threads, arguments), kernel a name of
        KERNELS, in launch order. `tail`: the pass kernel's last arguments (the colliders' in the
        generic build, the mesh buffers, the rows where the caller has them)."""
        keys = (KERNELS[0], int(self.slots), (x_in, self.keys, self.order, self.inv_cell, self.count, self.slots))
        sorts = [(KERNELS[1], int(self.slots), (self.keys, self.order, j, k, self.slots)) for j, k in self.stages]
        args = (x_in, x_out, self.keys, self.order, self.slots, *self.numbers, self.exclude2, *tail)
        return [keys, *sorts, (KERNELS[2], int(self.count), args)]

    def push(self, x_new, tail: tuple):
        """Runs the pass on x_new (the step's output) and returns the buffer holding the result;
        x_new's buffer is the next pass's output. `tail`: the colliders' arguments (generic: n
        and the collider buffers and counts), the mesh buffers, the step's per-step rows."""
        out, self.spare = self.spare, x_new
        runtimes = dict(zip(KERNELS, (self.keys_kernel, self.sort_kernel, self.pass_kernel)))
        for kernel, threads, args in self.launches(x_new, out, tail):
            runtimes[kernel].launch(math.ceil(threads / self.block), self.block, args)
        return out
