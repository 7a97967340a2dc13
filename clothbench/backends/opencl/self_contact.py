"""What the OpenCL solvers (verlet.py, pbd.py, vbd.py) do the same way for [self_collision]
(docs/semantics.md, "Self-collision"; the kernels are kernels/self_collision.cl): its numbers
as the kernels take them, its build options, and the sort's buffers and stages.

A pass is a launch of self_cell_keys, a bitonic sort over `slots` (the particle count rounded
up to a power of two: sort_launches), then the solver's pass kernel.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.colliders.self_contact import sort_slots
from clothbench.model.kernel_inputs import SelfCollisionConstants

KERNEL_FILE = "self_collision.cl"  # in a program's source only where the scene has the table
SORT_GROUP = 256  # self_sort_local's work-group size where the device and the slots allow it


class SelfContact:
    """The pass's numbers and sort buffers for one backend (`cl`, `context`: its pyopencl module
    and context); SelfContact.of(...) is None where the scene has no [self_collision]."""

    def __init__(self, scene, cl, context):
        c = SelfCollisionConstants.of(scene)  # rounded once on the host, never recomputed here
        self._cl, self._context = cl, context
        self.inv_cell = c.inv_cell
        # (thickness, thickness2, relax, inv_cell): one typed float4 argument
        self.numbers = cl.cltypes.make_float4(c.thickness, c.thickness2, c.relax, c.inv_cell)
        self.exclude2 = np.int32(min(c.exclude2, np.iinfo(np.int32).max))  # past 2 n^2 all alike
        self.count = np.int32(scene.particles)
        self.slots = sort_slots(scene.particles)
        # a power of two, so a group's block of 2 sort_group slots tiles the slots
        fits = min(SORT_GROUP, self.slots // 2, *(d.max_work_group_size for d in context.devices))
        self.sort_group = 1 << (fits.bit_length() - 1)
        mf = cl.mem_flags
        self.keys = cl.Buffer(context, mf.READ_WRITE, 8 * self.slots)  # a ulong cell id per slot
        self.order = cl.Buffer(context, mf.READ_WRITE, 4 * self.slots)  # the particle in the slot

    @classmethod
    def of(cls, scene, cl, context) -> "SelfContact | None":
        return None if scene.self_collision is None else cls(scene, cl, context)

    @property
    def build_options(self) -> tuple[str, ...]:
        slots, group = f"-DCLOTH_SELF_SLOTS={self.slots}", f"-DCLOTH_SELF_SORT_GROUP={self.sort_group}"
        return ("-DCLOTH_SELF_COLLISION", slots, group)

    @property
    def sort_passes(self) -> list[tuple[str, np.int32, np.int32]]:
        """The bitonic sort's launches in order: ("local", k_first, k_last), every stage of the
        blocks k_first..k_last whose distance stays within a block of 2 sort_group slots, in
        local memory; ("stage", j, k), one longer compare-and-exchange stage. At 64^2, 10
        launches for the 78 stages; at 256^2, 36 for 136."""
        block, i32 = 2 * self.sort_group, np.int32
        out, k = [("local", i32(2), i32(block))], 2 * block
        while k <= self.slots:
            j = k // 2
            while j >= block:
                out.append(("stage", i32(j), i32(k)))
                j //= 2
            out.append(("local", i32(k), i32(k)))
            k *= 2
        return out

    def sort_launches(self, kernel) -> list[tuple[object, tuple[int], tuple[int] | None]]:
        """The sort as (kernel, global size, local size) in launch order; `kernel(key, name,
        dtypes, args)`: the solver's kernel of its program with its arguments set once. The
        local launches take their own work-group size (their blocks' size), whatever the
        solver's; a stage's is the runtime's."""
        i32, sort, out = np.int32, (self.keys, self.order), []
        for kind, a, b in self.sort_passes:
            name = "self_sort_local" if kind == "local" else "self_sort_stage"
            k = kernel(("sort", kind, int(a), int(b)), name, [None, None, i32, i32], (*sort, a, b))
            if kind == "local":
                self._check_group(k)
            sizes = ((self.slots // 2,), (self.sort_group,)) if kind == "local" else ((self.slots,), None)
            out.append((k, *sizes))
        return out

    def _check_group(self, kernel) -> None:
        """self_sort_local runs in groups of sort_group work items, as built: refuse a device
        whose limit for that kernel is lower, in one line."""
        device = self._context.devices[0]
        limit = kernel.get_work_group_info(self._cl.kernel_work_group_info.WORK_GROUP_SIZE, device)
        if limit < self.sort_group:
            raise ClothbenchError(
                f"self-collision sort: {device.name} runs self_sort_local in groups of at most {limit} "
                f"work items, fewer than the {self.sort_group} it was sized for"
            )

    def buffers(self) -> tuple:
        return (self.keys, self.order)

    def row_launches(self, kernel, sizes, x_in, x_out, colliders, bodies: tuple) -> list[tuple]:
        """The pass of a solver that keeps float4 rows (pbd_cloth.cl, vbd_cloth.cl): x_in keyed,
        sorted, then pushed and collided into x_out by pbd_self_collision, as (kernel, global
        size, local size) in launch order. `kernel(key, name, dtypes, args, bodies)`: the
        solver's kernel with its arguments set once, shared by launches of one key; `sizes(items)`:
        the solver's (global, local) size of a launch of `items` work items, which the cell keys
        and the pass take (the sort takes its own, sort_launches); `bodies`: its _body_args() the
        pass takes after the colliders."""
        i32, f32 = np.int32, np.float32
        sort = (self.keys, self.order)
        cell_keys = kernel(
            ("cell keys", x_in), "self_cell_keys", [None] * 3 + [f32, i32], (x_in, *sort, self.inv_cell, self.count)
        )
        dtypes = [None] * 4 + [self.numbers.dtype, i32, None]
        args = (x_in, x_out, *sort, self.numbers, self.exclude2, colliders)
        push = kernel(("self collision", x_in), "pbd_self_collision", dtypes, args, bodies)
        return [(cell_keys, *sizes(self.slots)), *self.sort_launches(kernel), (push, *sizes(int(self.count)))]


def include_text(contact: SelfContact | None) -> str:
    """The text of `#include <self_collision>`: the pass where the scene has it, else nothing."""
    return f'#include "{KERNEL_FILE}"\n' if contact is not None else ""
