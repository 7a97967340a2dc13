"""What the glsl-compute solvers (compute.py, compute_pbd.py, compute_vbd.py) do the same way for [self_collision]
(docs/semantics.md, "Self-collision"): the pass's defines, the search's buffers and programs
(kernels/self_collision.comp: the cell keys, then one dispatch per stage of a bitonic sort), and
the bindings the solver's pass program reads them at (kernels/self_collision.glsl, included by
verlet_cloth.comp, pbd_cloth.comp and vbd_cloth.comp only where the scene has the table).
"""

from __future__ import annotations

import numpy as np

from clothbench.kernel_source import glsl_float
from clothbench.model.colliders.self_contact import (
    KEY_LIMIT,
    STENCIL_REACH,
    bitonic_stages,
    neighbour_table,
    sort_slots,
)
from clothbench.model.kernel_inputs import SelfCollisionConstants
from clothbench.model.scene import OFFSETS, Scene
from clothbench.backends.gl.context import shader_source, work_groups

SEARCH_FILE = "self_collision.comp"
SEARCH_STAGES = {"keys": 0, "sort": 1}  # SELF_STAGE, as the kernel's
SELF_KEYS, SELF_ORDER = 11, 12  # storage-buffer bindings (kernels/self_collision.glsl)


def neighbour_mask() -> int:
    """The stencil (scene.OFFSETS) as bits: (dr + R) * (2R + 1) + (dc + R), R = STENCIL_REACH."""
    rows, cols = np.nonzero(neighbour_table(OFFSETS))
    return sum(1 << int(r * (2 * STENCIL_REACH + 1) + c) for r, c in zip(rows, cols))


class GLSelfContact:
    """The pass's defines and search for one backend on `device` (gl/context.py's GLDevice);
    GLSelfContact.of(...) is None where the scene has no [self_collision]."""

    def __init__(self, device, scene: Scene, local_size: int):
        c = SelfCollisionConstants.of(scene)  # rounded once on the host, never recomputed here
        self.device, self.local_size = device, local_size
        self.slots = sort_slots(scene.particles)
        self.stages = bitonic_stages(self.slots)
        numbers = ", ".join(map(glsl_float, (c.thickness, c.thickness2, c.relax, c.inv_cell)))
        self.defines = {
            "SELF_COLLISION": "",
            "SELF_C_VALUE": f"vec4({numbers})",
            "SELF_EXCLUDE2": min(c.exclude2, np.iinfo(np.int32).max),  # past 2 n^2 all alike
            "SELF_NEIGHBOURS": neighbour_mask(),
            "SELF_REACH": STENCIL_REACH,
            "SELF_KEY_LIMIT": KEY_LIMIT,
            "SELF_SLOTS": self.slots,
        }
        with device:
            self.keys = device.ctx.buffer(reserve=8 * self.slots)  # a cell id (two uints) per slot
            self.order = device.ctx.buffer(reserve=4 * self.slots)  # the particle in the slot
            self.programs = {stage: self._program(scene, value) for stage, value in SEARCH_STAGES.items()}
        self.bindings = ((SELF_KEYS, self.keys), (SELF_ORDER, self.order))

    @classmethod
    def of(cls, device, scene: Scene, local_size: int) -> "GLSelfContact | None":
        return None if scene.self_collision is None else cls(device, scene, local_size)

    def _program(self, scene: Scene, stage: int):
        defines = dict(LOCAL_SIZE=self.local_size, SELF_STAGE=stage, N_VALUE=scene.grid, **self.defines)
        source = shader_source(SEARCH_FILE, 430, defines, self_collision=True)
        return self.device.program(("self-comp", source), lambda: self.device.ctx.compute_shader(source))

    def search(self, positions) -> list:
        """The dispatches that key and sort `positions` (a buffer of vec4 rows), in order, as
        (program, work groups, storage-buffer bindings, image bindings, uniform values)."""
        groups = work_groups(self.slots, self.local_size)
        ssbos = ((0, positions), *self.bindings)
        keys, sort = self.programs["keys"], self.programs["sort"]
        launches = [(keys, groups, ssbos, (), ())]
        for j, k in self.stages:
            launches.append((sort, groups, ssbos, (), ((sort["sort_j"], j), (sort["sort_k"], k))))
        return launches

    def release(self) -> None:
        with self.device:
            self.keys.release()
            self.order.release()
