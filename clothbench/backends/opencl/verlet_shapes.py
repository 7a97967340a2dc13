"""The kernel shapes of the specialised OpenCL Verlet build (kernels/verlet_cloth.cl): how one
step's work is split into launches, work items and work-groups. Every shape does the same
operations on every particle in the same order, so strict stays bit-exact whatever runs.

A shape's name, as the mode spells it:
  v<V>[/wg=<L>]        `verlet_cloth_interior` (V particles per work item, explicit vectors)
                       + `verlet_cloth_border` (one particle per work item): two launches a
                       step. wg=L fixes the work-group size; without it the runtime chooses.
  rows/v<V>[/wg=<L>]   `verlet_cloth_rows`: every row in vectors of V, the grid's edge masked
                       lane by lane: one launch a step, no scalar border.
  steps/launch=<K>/v<V>/wg=<L>
                       `verlet_cloth_steps`: the rows kernel's work, K steps per launch, the
                       whole grid in one work-group of L work items (so one core): for small
                       grids, where a launch costs as much as a step.
Which are candidates where, and why: candidates() and docs/opencl.md.
"""

from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass

from clothbench.errors import ClothbenchError
from clothbench.backends.tuning import turn_steps
from clothbench.backends.opencl.bodies import collider_counts

# Floats before and after the x, y, z planes of a state buffer (CLOTH_PAD in the kernel): the
# rows kernels' masked loads reach one float past either end. 16 keeps the planes 64-byte aligned.
PAD = 16
# Floats between the planes of a state buffer beyond n*n (CLOTH_STATE_GAP in the kernel):
# planes exactly n*n apart alias in the L1 and at 4 KiB at power-of-two grids (docs/opencl.md,
# "Planes apart"); 32 is the c kernel's pad, measured there (docs/c.md).
STATE_GAP = 32
# work items per work-group of rows/vN/wg=32: it and the runtime's choice won in turn, and 8, 32
# and 128 ran level (docs/opencl.md, "What was profiled")
WORK_GROUP = 32
STEPS_PER_LAUNCH = 32  # 8, 32 and 128 ran level (docs/opencl.md, "What was profiled")
STEPS_WORK_GROUP = 1  # its one work-group: 1, 16 and 64 work items ran level; 1 fits any device
# the multi-step kernel runs on one core: at 128^2 it already runs level with the two-core rows
# kernels (docs/opencl.md, "What was profiled"), so on larger grids it cannot win
STEPS_MAX_GRID = 128


@dataclass(frozen=True)
class KernelShape:
    layout: str  # "split" (interior + border), "rows", or "steps" (several steps per launch)
    width: int  # particles per work item, V
    work_group: int | None = None  # None: the runtime's choice (or options.local_size)
    steps_per_launch: int = 1

    @property
    def name(self) -> str:
        wg = f"/wg={self.work_group}" if self.work_group else ""
        if self.layout == "steps":
            return f"steps/launch={self.steps_per_launch}/v{self.width}{wg}"
        return f"{'rows/' if self.layout == 'rows' else ''}v{self.width}{wg}"

    @property
    def in_place(self) -> bool:
        """Whether its kernels write x(t+dt) over x(t-dt) (two state buffers) rather than to
        pos_out and pos_prev_out (four): the rows kernel and the multi-step kernel built on it."""
        return self.layout != "split"

    @property
    def kernels(self) -> tuple[str, ...]:
        return {
            "split": ("verlet_cloth_interior", "verlet_cloth_border"),
            "rows": ("verlet_cloth_rows",),
            "steps": ("verlet_cloth_steps",),
        }[self.layout]


_NAME = re.compile(r"^(?:(rows)/|steps/launch=(\d+)/)?v(\d+)(?:/wg=(\d+))?$")


def parse(name: str) -> KernelShape:
    """The shape a name spells (the inverse of KernelShape.name)."""
    m = _NAME.match(name)
    if not m:
        raise ClothbenchError(f"not an OpenCL kernel shape name: {name!r}")
    rows, k, v, wg = m.groups()
    layout = "steps" if k else ("rows" if rows else "split")
    return KernelShape(layout, int(v), int(wg) if wg else None, int(k) if k else 1)


def candidates(device, scene, options) -> tuple[KernelShape, ...]:
    """The shapes worth measuring for this device and scene, the default first (what an
    untuned run, CLOTHBENCH_TUNING=off, runs): rows/vN where the grid is at least N wide,
    since it was the fastest untuned shape on every runtime measured; the split kernels at
    the device's preferred float width P (two launches a step: interior and border) as a
    candidate, and the only shape on narrower grids.

    The others at the native float width N (16 with AVX-512), which won on all three
    runtimes measured here (docs/opencl.md); N/2, 4 and 1 (scalar code, the runtime's own
    work-group vectoriser) never won. rows/vN with the runtime's work-group size and with
    WORK_GROUP work items, which won in turn (options.local_size replaces both); the rows
    kernels need n >= N. The multi-step shape for n <= STEPS_MAX_GRID, resident state (the
    per-step transfer uploads every step) and where its work-group fits the device."""
    n = scene.grid
    p = max(1, int(device.preferred_vector_width_float))
    native = max(1, int(device.native_vector_width_float))
    shapes = []
    if native <= n:
        shapes.append(KernelShape("rows", native))  # the default: fastest untuned everywhere measured
        shapes.append(KernelShape("split", p))
        if not options.local_size:
            shapes.append(KernelShape("rows", native, WORK_GROUP))
        group = options.local_size or STEPS_WORK_GROUP
        resident = (options.transfer or "resident") == "resident"
        if n <= STEPS_MAX_GRID and resident and group <= device.max_work_group_size:
            shapes.append(KernelShape("steps", native, group, STEPS_PER_LAUNCH))
    else:
        shapes.append(KernelShape("split", p))
    if scene.self_collision is not None:
        # the default only: the pass (its own launches after the step's: keys, sort, push) costs
        # more than the step, so timing the shapes would mostly time the pass; and the
        # multi-step kernel has no launch between steps for it
        return tuple(shapes[:1])
    return tuple(dict.fromkeys(shapes))


def tuning_key(device, scene, options, source: str, mesh_collision: str | None = None) -> dict[str, str]:
    """What a shape's speed depends on: the device and its driver, the scene's shape (its
    meshes, their search and whether anything moves included), the arithmetic, what else the
    step does, and the kernel source (an edit measures again)."""
    bodies, counts = {}, collider_counts(scene)
    if scene.meshes:
        bodies["meshes"] = f"{'/'.join(str(m.geometry.triangles) for m in scene.meshes)} {mesh_collision}"
    if scene.has_motion:
        bodies["motion"] = "pins attached" if scene.pin_attach is not None else "moving colliders"
    return {
        "device": device.name,
        "platform": device.platform.version,
        "driver": device.driver_version,
        "grid": str(scene.grid),
        # the kinds every backend takes by count; a kind not every backend takes (a box) its
        # own key, only where the scene has it: the keys measured before stay valid
        "colliders": "/".join(str(count) for kind, count in counts if kind.capability is None),
        **{kind.plural: str(count) for kind, count in counts if kind.capability and count},
        "arithmetic": "strict" if options.strict else "fast",
        "normals": str(bool(options.normals)),
        "transfer": options.transfer or "resident",
        "local_size": str(options.local_size or "auto"),
        "source": hashlib.sha256(source.encode()).hexdigest()[:16],
        **bodies,  # absent without meshes or motion: a scene without them keeps its key
    }


def timing_steps(n: int, steps_per_launch: int) -> int:
    """Steps per timed call while tuning (tuning.turn_steps: a few milliseconds of work at every
    grid), at least two, at most 256, a whole number of multi-step launches."""
    return turn_steps(n * n, least=2, most=256, multiple=steps_per_launch)
