"""The scene's bodies in a GL program: the collide() source of its analytic colliders, and its
meshes, moving colliders and attached pins (their defines, per-step rows and storage buffers,
GLBodies)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from clothbench.model.colliders.kinds import KIND, KINDS, kinds_in
from clothbench.kernel_source import glsl_float
from clothbench.model.scene import Scene
from clothbench.model.kernel_inputs import MeshConstants, collider_rows, pin_targets, pose_rows


def collider_kinds(scene: Scene, generic: bool) -> tuple[str, ...]:
    """The collider kinds a program for `scene` handles, in the step's order (colliders/kinds.py,
    those with a kernels/collide_KIND.glsl): the ones it has, or all (generic)."""
    return tuple(k.name for k in kinds_in("glsl") if generic or getattr(scene, k.plural))


# how collide() reads one collider of each kind from the per-step rows (MOTION_ROW: the
# scene moves), at the offsets motion_offsets gives (MOTION_SPHERES, ...)
_MOVING_CALLS = {
    "sphere": "    for (int i = 0; i < SPHERE_COUNT; ++i)\n        x = collide_sphere(x, MOTION_ROW(MOTION_SPHERES + i));\n",
    "cylinder": "    for (int i = 0; i < CYLINDER_COUNT; ++i)\n"
    "        x = collide_cylinder(x, MOTION_ROW(MOTION_CYLINDERS + 3 * i), MOTION_ROW(MOTION_CYLINDERS + 3 * i + 1),\n"
    "                             MOTION_ROW(MOTION_CYLINDERS + 3 * i + 2).xyz);\n",
    "box": "    for (int i = 0; i < BOX_COUNT; ++i)\n"
    "        x = collide_box(x, MOTION_ROW(MOTION_BOXES + 4 * i), MOTION_ROW(MOTION_BOXES + 4 * i + 1),\n"
    "                        MOTION_ROW(MOTION_BOXES + 4 * i + 2), MOTION_ROW(MOTION_BOXES + 4 * i + 3));\n",
    "plane": "    for (int i = 0; i < PLANE_COUNT; ++i)\n"
    "        x = collide_plane(x, MOTION_ROW(MOTION_PLANES + 2 * i).xyz, MOTION_ROW(MOTION_PLANES + 2 * i + 1).xyz);\n",
}


def collider_source(kinds: tuple[str, ...], meshes: bool = False, moving: bool = False) -> str:
    """What `#include <colliders>` stands for: kernels/collide_KIND.glsl of each kind the
    program handles, and collide(), applying them in the fixed order, the meshes last
    (kernels/collide_mesh.glsl, only where the scene has meshes). A kind the program does not
    handle is not in its source at all. `moving`: the analytic colliders' rows are this
    step's (MOTION_ROW), not the file's constants (docs/semantics.md, "Moving colliders")."""
    calls = "".join(_MOVING_CALLS[kind] if moving else f"    x = collide_{KIND[kind].plural}(x);\n" for kind in kinds)
    parts = [f'#include "collide_{kind}.glsl"\n' for kind in kinds]
    if meshes:
        parts.append('#include "collide_mesh.glsl"\n')
        calls += "    x = collide_meshes(x);\n"
    parts.append(f"vec3 collide(vec3 x)\n{{\n{calls}    return x;\n}}\n")
    return "".join(parts)


# --- meshes, moving colliders, attached pins (docs/semantics.md) ----------------------------
# Only a scene that has them gets their switches and code: MESH_COUNT (kernels/collide_mesh.glsl),
# MOTION (per-step rows), PIN_ATTACH (pins that follow a body).


def motion_offsets(scene: Scene) -> dict[str, int]:
    """Where each part of one step's rows sits (MOTION_ROW, vec4s): the analytic colliders as
    collider_rows lays them out (MOTION_SPHERES from 0, then each kind of colliders/kinds.py in
    the step's order), three pose rows per mesh (row i of R, T.i in w), one row per attached
    pin (its target, 0)."""
    offsets, at = {}, 0
    for kind in KINDS:
        offsets[f"MOTION_{kind.plural.upper()}"] = at
        at += kind.rows * len(getattr(scene, kind.plural))
    pins = at + 3 * len(scene.meshes)
    attached = len(scene.pinned()) if scene.pin_attach is not None else 0
    return dict(offsets, MOTION_MESHES=at, MOTION_PINS=pins, MOTION_STRIDE=max(1, pins + attached))


def motion_rows(scene: Scene, time: float) -> np.ndarray:
    """One step's rows (motion_offsets' layout) at `time`, the end of the step: every pose in
    float64 rounded once to float32 (kernel_inputs, as the NumPy reference takes them)."""
    offsets = motion_offsets(scene)
    out = np.zeros((offsets["MOTION_STRIDE"], 4), dtype=np.float32)
    rows = collider_rows(scene, np.float32, time)
    analytic = np.concatenate([rows[kind.plural] for kind in KINDS])
    out[: len(analytic)] = analytic
    for m, mesh in enumerate(scene.meshes):
        out[offsets["MOTION_MESHES"] + 3 * m : offsets["MOTION_MESHES"] + 3 * m + 3] = pose_block(mesh, time)
    if scene.pin_attach is not None:
        targets = pin_targets(scene, time, np.float32)
        out[offsets["MOTION_PINS"] : offsets["MOTION_PINS"] + len(targets), :3] = targets
    return out


def pose_block(mesh, time: float) -> np.ndarray:
    """(3, 4) float32: row i of the mesh's R at `time`, and T.i in w (pose_rows' rounding)."""
    rot, trans = pose_rows(mesh, time, np.float32)
    return np.concatenate([rot, trans[:, None]], axis=1)


def pin_slots(scene: Scene) -> np.ndarray:
    """Per particle, its row among the attached pins' targets (scene.pinned() order), or -1."""
    slots = np.full(scene.particles, -1, dtype=np.int32)
    slots[scene.pinned()] = np.arange(len(scene.pinned()), dtype=np.int32)
    return slots


@dataclass(frozen=True)
class MeshBuffers:
    """Every mesh of a scene as kernels/collide_mesh.glsl reads it, concatenated: `corners`
    (3 vec4 per triangle: a, b, c, with the triangle's index in its mesh in a.w; in index order
    for the naive loop, in the BVH's leaf order for the traversal), `normals` (7 vec4 per
    triangle by index: face, a, b, c, ab, ac, bc), `nodes` (two vec4 per BVH node: lo with the
    first child's index in w, hi with the leaf's first triangle in w, both as int bits; a leaf
    has child = -(its triangle count)) and `info` (first triangle, triangles, first node,
    closed) per mesh."""

    corners: np.ndarray
    normals: np.ndarray
    nodes: np.ndarray | None
    info: list[tuple[int, int, int, int]]
    stack: int  # the deepest BVH's depth: the traversal's stack

    @classmethod
    def of(cls, scene: Scene, accelerated: bool) -> "MeshBuffers":
        corners, normals, nodes, info = [], [], [], []
        tri0 = node0 = depth = 0
        for mesh in scene.meshes:
            c = MeshConstants.of(mesh, np.float32)
            g = c.geometry
            count = len(c.corners)
            order = g.bvh.tris.astype(np.int64) if accelerated else np.arange(count)
            block = np.zeros((count, 3, 4), dtype=np.float32)
            block[:, :, :3] = c.corners[order]
            block[:, 0, 3] = order  # exact in float32 below 2^24 triangles
            corners.append(block)
            n = np.zeros((count, 7, 4), dtype=np.float32)
            n[:, :, :3] = c.normals
            normals.append(n)
            if accelerated:
                bvh = g.bvh
                node = np.zeros((bvh.nodes, 2, 4), dtype=np.float32)
                node[:, 0, :3], node[:, 1, :3] = bvh.lo, bvh.hi
                ints = node.view(np.int32)
                ints[:, 0, 3] = np.where(bvh.child >= 0, bvh.child, -bvh.count)
                ints[:, 1, 3] = bvh.first
                nodes.append(node)
                depth = max(depth, bvh.depth)
                info.append((tri0, count, node0, int(c.closed)))
                node0 += bvh.nodes
            else:
                info.append((tri0, count, 0, int(c.closed)))
            tri0 += count
        return cls(
            np.concatenate(corners),
            np.concatenate(normals),
            np.concatenate(nodes) if accelerated else None,
            info,
            depth + 1,
        )


def body_defines(scene: Scene, mesh_collision: str | None) -> dict[str, object]:
    """The switches and exact literals of a scene's meshes, motion and attached pins, in
    specialised and generic programs alike (their code is compiled only for scenes that have
    them, so a generic program of such a scene is that scene's): MESH_COUNT, the meshes'
    boxes, margins, layout and (fixed) poses; MESH_BVH and MESH_STACK for the traversal;
    MOTION and the per-step row offsets; PIN_ATTACH."""
    defines: dict[str, object] = {}
    if scene.meshes:
        buffers = mesh_layout(scene, mesh_collision == "accelerated")
        consts = [MeshConstants.of(m, np.float32) for m in scene.meshes]

        def vec4(v, w) -> str:
            return "vec4({})".format(", ".join(map(glsl_float, (*v, w))))

        box = [row for c in consts for row in (vec4(c.lo, c.margin), vec4(c.hi, c.margin2))]
        defines["MESH_COUNT"] = len(consts)
        defines["MESH_BOX_VALUE"] = f"vec4[{len(box)}]({', '.join(box)})"
        info = ", ".join("ivec4({}, {}, {}, {})".format(*i) for i in buffers.info)
        defines["MESH_INFO_VALUE"] = f"ivec4[{len(consts)}]({info})"
        if not scene.has_motion:
            pose = [vec4(row[:3], row[3]) for m in scene.meshes for row in pose_block(m, 0.0)]
            defines["MESH_POSE_VALUE"] = f"vec4[{len(pose)}]({', '.join(pose)})"
        if mesh_collision == "accelerated":
            defines["MESH_BVH"] = ""
            defines["MESH_STACK"] = buffers.stack
    if scene.has_motion:
        defines["MOTION"] = ""
        defines.update(motion_offsets(scene))
    if scene.pin_attach is not None:
        defines["PIN_ATTACH"] = ""
    return defines


# storage-buffer bindings of a scene's bodies (kernels/verlet_cloth_step.glsl, collide_mesh.glsl)
MOTION_ROWS, MESH_CORNERS, MESH_NORMALS, MESH_NODES, PIN_SLOTS = 6, 7, 8, 9, 10
MOTION_BLOCK = 256  # steps whose rows go up in one write (a multiple of every steps/dispatch=K)


class GLBodies:
    """The storage buffers of a scene's meshes (MESH_*, uploaded once), its per-step rows
    (MOTION_ROWS, a block of MOTION_BLOCK steps at a time) and attached-pin slots (PIN_SLOTS);
    none for a scene without meshes or motion. Step k's rows (counted from the last upload of
    a state) are the poses at (k + 1) dt, the end of the step, as the NumPy reference's.
    `device` is the GLDevice (gl/context.py) whose context holds the buffers."""

    def __init__(self, device, scene: Scene, dt: float, mesh_collision: str | None):
        self.device, self.scene, self.dt = device, scene, dt
        self.buffers: dict[int, object] = {}
        self._table: list[np.ndarray] = []  # rows of step k, computed once per k
        ctx = device.ctx
        with device:
            if scene.meshes:
                mesh = mesh_layout(scene, mesh_collision == "accelerated")
                self.buffers[MESH_CORNERS] = ctx.buffer(mesh.corners.tobytes())
                self.buffers[MESH_NORMALS] = ctx.buffer(mesh.normals.tobytes())
                if mesh.nodes is not None:
                    self.buffers[MESH_NODES] = ctx.buffer(mesh.nodes.tobytes())
            if scene.has_motion:
                stride = motion_offsets(scene)["MOTION_STRIDE"]
                self.buffers[MOTION_ROWS] = ctx.buffer(reserve=MOTION_BLOCK * stride * 16)
            if scene.pin_attach is not None:
                self.buffers[PIN_SLOTS] = ctx.buffer(pin_slots(scene).tobytes())

    @property
    def moving(self) -> bool:
        return MOTION_ROWS in self.buffers

    def bind(self) -> None:
        for binding, buf in self.buffers.items():
            buf.bind_to_storage_buffer(binding)

    def upload_rows(self, first: int, count: int) -> None:
        """The rows of steps first .. first + count - 1 since the upload, into MOTION_ROWS.
        Evaluated on the host once per step index (float64, rounded once: the same function of
        k in every run) and written before the commands that read them, by the backend's
        advance(): inside the timed region, as a program moving its bodies pays for it."""
        while len(self._table) < first + count:
            k = len(self._table)
            self._table.append(motion_rows(self.scene, (k + 1) * self.dt))  # the end of step k
        self.buffers[MOTION_ROWS].write(np.concatenate(self._table[first : first + count]).tobytes())

    def release(self) -> None:
        with self.device:
            for buf in self.buffers.values():
                buf.release()
        self.buffers = {}


@lru_cache(maxsize=16)
def mesh_layout(scene: Scene, accelerated: bool) -> MeshBuffers:
    """MeshBuffers of `scene`, built once per scene and algorithm (scenes are immutable)."""
    return MeshBuffers.of(scene, accelerated)
