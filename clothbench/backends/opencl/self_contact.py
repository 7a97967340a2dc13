"""What the OpenCL solvers (verlet.py, pbd.py, vbd.py) do the same way for [self_collision]
(docs/semantics.md, "Self-collision"; the kernels are kernels/self_collision.cl): its numbers
as the kernels take them, its build options, and the sort's buffers and stages.

A pass is a launch of self_cell_keys, one of self_sort_stage per stage of a bitonic sort over
`slots` (the particle count rounded up to a power of two), then the solver's pass kernel.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.kernel_inputs import SelfCollisionConstants

KERNEL_FILE = "self_collision.cl"  # in a program's source only where the scene has the table


class SelfContact:
    """The pass's numbers and sort buffers for one backend (`cl`, `context`: its pyopencl module
    and context); SelfContact.of(...) is None where the scene has no [self_collision]."""

    def __init__(self, scene, cl, context):
        c = SelfCollisionConstants.of(scene)  # rounded once on the host, never recomputed here
        self.inv_cell = c.inv_cell
        # (thickness, thickness2, relax, inv_cell): one typed float4 argument
        self.numbers = cl.cltypes.make_float4(c.thickness, c.thickness2, c.relax, c.inv_cell)
        self.exclude2 = np.int32(min(c.exclude2, np.iinfo(np.int32).max))  # past 2 n^2 all alike
        self.count = np.int32(scene.particles)
        self.slots = sort_slots(scene.particles)
        mf = cl.mem_flags
        self.keys = cl.Buffer(context, mf.READ_WRITE, 8 * self.slots)  # a ulong cell id per slot
        self.order = cl.Buffer(context, mf.READ_WRITE, 4 * self.slots)  # the particle in the slot

    @classmethod
    def of(cls, scene, cl, context) -> "SelfContact | None":
        return None if scene.self_collision is None else cls(scene, cl, context)

    @property
    def build_options(self) -> tuple[str, ...]:
        return ("-DCLOTH_SELF_COLLISION", f"-DCLOTH_SELF_SLOTS={self.slots}")

    @property
    def stages(self) -> list[tuple[np.int32, np.int32]]:
        return sort_stages(self.slots)

    def buffers(self) -> tuple:
        return (self.keys, self.order)

    def row_launches(self, kernel, x_in, x_out, colliders, bodies: tuple) -> list[tuple[object, int]]:
        """The pass of a solver that keeps float4 rows (pbd_cloth.cl, vbd_cloth.cl): x_in keyed,
        sorted, then pushed and collided into x_out by pbd_self_collision, as (kernel, work
        items) in launch order. `kernel(key, name, dtypes, args, bodies)`: the solver's kernel
        with its arguments set once, shared by launches of one key; `bodies`: its _body_args()
        the pass takes after the colliders."""
        i32, f32 = np.int32, np.float32
        sort = (self.keys, self.order)
        cell_keys = kernel(
            ("cell keys", x_in), "self_cell_keys", [None] * 3 + [f32, i32], (x_in, *sort, self.inv_cell, self.count)
        )
        out = [(cell_keys, self.slots)]
        for j, k in self.stages:
            out.append((kernel(("sort", j, k), "self_sort_stage", [None, None, i32, i32], (*sort, j, k)), self.slots))
        dtypes = [None] * 4 + [self.numbers.dtype, i32, None]
        args = (x_in, x_out, *sort, self.numbers, self.exclude2, colliders)
        out.append((kernel(("self collision", x_in), "pbd_self_collision", dtypes, args, bodies), int(self.count)))
        return out


def sort_slots(particles: int) -> int:
    """The bitonic sort's length: the particle count rounded up to a power of two (the CUDA
    pass's too, kernels/self_collision.cuh)."""
    return 1 << max(0, (particles - 1).bit_length())


def sort_stages(slots: int) -> list[tuple[np.int32, np.int32]]:
    """(j, k) of each compare-and-exchange stage of the bitonic sort over `slots`, in launch order."""
    out, k = [], 2
    while k <= slots:
        j = k // 2
        while j > 0:
            out.append((np.int32(j), np.int32(k)))
            j //= 2
        k *= 2
    return out


def include_text(contact: SelfContact | None) -> str:
    """The text of `#include <self_collision>`: the pass where the scene has it, else nothing."""
    return f'#include "{KERNEL_FILE}"\n' if contact is not None else ""
