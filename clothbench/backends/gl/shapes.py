"""The kernel shapes of glsl-compute (Verlet and VBD), how each is dispatched, and how they
are timed for backends/tuning.py.

A shape changes how the particles are split over invocations and dispatches, never the
operations done on one particle, so every shape of a strict build is bit-exact with NumPy.
Verlet's:
- "wg=L": work groups of L consecutive particles (row-major), the interior pass and the
  border pass (kernels/verlet_cloth.comp); "wg=64" is the default.
- "wg=WxH": the interior pass in 2-D work groups of W columns x H rows (TILE_W, TILE_H),
  the border pass as "wg=64".
- "steps/dispatch=K": one work group holds the whole grid and runs up to K steps per
  dispatch (kernels/verlet_cloth_steps.comp), on grids of up to MULTI_STEP_MAX_PARTICLES;
  the neighbours' positions go through shared memory where 6 floats per particle fit in the
  driver's GL_MAX_COMPUTE_SHARED_MEMORY_SIZE, else through a scratch storage buffer.
VBD's (gl/compute_vbd.py): "wg=L" only, every dispatch of a substep in work groups of L
(VBD_SIZES); a colour's sweep is one particle per invocation whatever L is.
An explicit --local-size fixes the shape to "wg=L" with no tuning (and no shape in the mode);
--shape and --local-size exclude each other.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass

from clothbench.model.colliders.kinds import KINDS
from clothbench.errors import ClothbenchError
from clothbench.kernel_source import kernel_hash
from clothbench.model.scene import Scene
from clothbench.backends.base import BackendOptions
from clothbench.backends.tuning import median_seconds, turn_steps

# the Verlet shapes' kernel files (gl/compute.py), whose text a choice was measured on
VERLET_KERNELS = ("verlet_cloth.comp", "verlet_cloth_steps.comp")
DEFAULT_SHAPE = "wg=64"
LINEAR_SIZES = (64, 256)  # work-group sizes of the 1-D shape (the first is the default)
# VBD's work-group sizes, the default first; none below 64, slower on llvmpipe (docs/vbd.md)
VBD_SIZES = (64, 128, 256)
TILES = ((8, 8), (16, 16), (32, 4))  # (columns, rows) of the 2-D interior shape
BORDER_LOCAL_SIZE = 64  # the border pass of the 2-D shapes
STEPS_PER_DISPATCH = (16, 64)
# One work group runs on one llvmpipe thread: past this many particles the second thread
# the other shapes use is worth more than the dispatches saved (docs/llvmpipe.md).
MULTI_STEP_MAX_PARTICLES = 64 * 64
SCRATCH_BYTES_PER_PARTICLE = 2 * 3 * 4  # two halves of x, y, z floats
TUNING_STEPS = 8  # the most steps of a timed run of a shape (tuning.turn_steps; at least K for steps/dispatch=K)
TUNING_REPEATS = 3
_GL_MAX_COMPUTE_SHARED_MEMORY_SIZE = 0x8262


@dataclass(frozen=True)
class ComputeShape:
    """A parsed shape name: `local` invocations per work group, `tile` (W, H) for the 2-D
    interior, `steps` per dispatch for the one-group shape (None for the others)."""

    name: str
    local: int
    tile: tuple[int, int] | None = None
    steps: int | None = None


@dataclass(frozen=True)
class StepsLayout:
    """How the one-group shape covers n*n particles: `local` invocations of `ppi` particles,
    the neighbours' positions in shared memory (`shared`) or a scratch buffer."""

    local: int
    ppi: int
    shared: bool


def limits(device) -> tuple[int, int]:
    """(GL_MAX_COMPUTE_WORK_GROUP_INVOCATIONS, GL_MAX_COMPUTE_SHARED_MEMORY_SIZE) of `device`
    (moderngl's info has the first only)."""
    value = ctypes.c_int(0)
    with device:
        get = device._fn("glGetIntegerv", ctypes.c_uint, ctypes.POINTER(ctypes.c_int))
        get(_GL_MAX_COMPUTE_SHARED_MEMORY_SIZE, ctypes.byref(value))
        return int(device.ctx.info["GL_MAX_COMPUTE_WORK_GROUP_INVOCATIONS"]), value.value


def steps_layout(particles: int, max_invocations: int, shared_bytes: int) -> StepsLayout:
    """The fewest particles per invocation that fit one work group, the invocations a
    multiple of 8 (llvmpipe's SIMD width on AVX: a partial vector is wasted lanes)."""
    ppi = -(-particles // max_invocations)
    local = -(-particles // ppi)
    local = min(max_invocations, -(-local // 8) * 8)
    return StepsLayout(local, ppi, particles * SCRATCH_BYTES_PER_PARTICLE <= shared_bytes)


def candidates(scene: Scene, options: BackendOptions, solver: str = "verlet") -> tuple[str, ...]:
    """The shape names glsl-compute's `solver` (verlet or vbd) can run `scene` with, the
    default first; none where --local-size fixes the shape."""
    if options.local_size is not None:
        return ()
    if scene.self_collision is not None:
        # the default only: the pass (its own dispatches after the step's: keys, sort, push)
        # costs more than the step, so timing the shapes would mostly time the pass; and the
        # one-group shape has no dispatch between steps for it
        return (DEFAULT_SHAPE,)
    if solver == "vbd":
        return tuple(f"wg={size}" for size in VBD_SIZES)
    names = [f"wg={size}" for size in LINEAR_SIZES]
    if scene.grid >= 5:  # there is an interior to tile
        names += [f"wg={w}x{h}" for w, h in TILES]
    if scene.particles <= MULTI_STEP_MAX_PARTICLES:
        names += [f"steps/dispatch={k}" for k in STEPS_PER_DISPATCH]
    return tuple(names)


def parse(name: str, scene: Scene, max_invocations: int) -> ComputeShape:
    """The shape `name` (one of candidates()) for this scene on a driver allowing
    `max_invocations` per work group."""
    if name.startswith("steps/dispatch="):
        return ComputeShape(name, 0, steps=int(name.split("=")[1]))
    size = name.removeprefix("wg=")
    if "x" in size:
        w, h = (int(v) for v in size.split("x"))
        if w * h > max_invocations:
            raise ClothbenchError(
                f"glsl-compute: {name} is more invocations than the driver allows ({max_invocations})"
            )
        return ComputeShape(name, w * h, tile=(w, h))
    return ComputeShape(name, int(size))


def refuse_shape_with_local_size(options: BackendOptions) -> None:
    if options.shape is not None and options.local_size is not None:
        raise ClothbenchError(
            f"glsl-compute: --shape {options.shape} and --local-size {options.local_size} exclude "
            "each other (a shape fixes the work-group size); give one"
        )


def tuning_key(backend) -> dict[str, str]:
    """What a measured choice holds for: the driver, the grid, the colliders (meshes: their
    triangles and algorithm; motion), the build and the Verlet kernels' text (a solver with
    kernels of its own names them in place of those: gl/compute_vbd.py)."""
    scene, options = backend.scene, backend.options
    triangles = sum(m.geometry.triangles for m in scene.meshes)
    return {
        "driver": backend.driver,
        "grid": str(scene.grid),
        "colliders": collider_counts(scene),
        "arithmetic": "strict" if options.strict else "fast",
        "generic": str(options.generic),
        "normals": str(options.normals),
        "reads": "image" if backend.image_reads else "ssbo",
        # only where the scene has them, so that a scene without them keeps its key and its choice
        **({"meshes": f"{triangles}t/{backend.mesh_collision}"} if scene.meshes else {}),
        **({"motion": "moving"} if scene.has_motion else {}),
        "kernel": kernel_hash(*VERLET_KERNELS),  # an edit to the step measures again
    }


def collider_counts(scene) -> str:
    """'1s0c2p': the scene's colliders per kind (colliders/kinds.py), by the kind's initial; a
    kind not every backend takes (a box) only where the scene has one, so that the choices
    measured before that kind existed stay valid."""
    counts = ((kind, len(getattr(scene, kind.plural))) for kind in KINDS)
    return "".join(f"{count}{kind.name[0]}" for kind, count in counts if count or kind.capability is None)


def time_shape(backend, name: str, steps: int | None = None) -> float:
    """Seconds per step of shape `name` on `backend`'s own buffers (its build_plan(name), then
    run_plan(plan, steps) timed; by default tuning.turn_steps, at most TUNING_STEPS), from its
    initial state (the caller uploads the real state afterwards). A shape the driver cannot
    build is dropped by the tuner, with the compiler's first line (a ClothbenchError)."""
    import moderngl

    try:
        plan = backend.build_plan(name)
    except moderngl.Error as e:
        raise ClothbenchError(f"glsl-compute: {name} does not build: {str(e).strip().splitlines()[0]}") from None
    steps = max(steps or turn_steps(backend.scene.particles, most=TUNING_STEPS), plan.shape.steps or 0)
    backend.upload(*backend.initial_state())
    seconds = median_seconds(lambda: backend.run_plan(plan, steps), backend.synchronize, TUNING_REPEATS)
    return seconds / steps
