"""What both OpenCL solvers (verlet.py, pbd.py) do the same way for meshes, moving colliders
and pins attached to a body (docs/semantics.md; the kernel side is kernels/collide_mesh.cl
and the CLOTH_MESHES / CLOTH_PER_STEP / CLOTH_ATTACHED_PINS parts of each solver's kernel):
the analytic collider kinds the kernels take (collider_counts), the collider table with its
mesh rows, the mesh buffers (uploaded once), the per-particle pin slots, and the per-step
constants (tables and pin targets) evaluated on the host in float64 and rounded once,
uploaded STEPS_PER_UPLOAD at a time.

A "step" here is one table: a Verlet step, or a PBD substep (docs/pbd.md, "Colliders, motion
and attached pins"); `period` is its length in seconds, so table j of the clock's count is at
(clock + j + 1) * period, the end of that step.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from clothbench.colliders.kinds import kinds_in
from clothbench.errors import ClothbenchError
from clothbench.backends.kernel_inputs import MeshConstants, collider_rows, pin_targets, pose_rows

MESH_FILE = "collide_mesh.cl"  # in the program's source only where the scene has meshes
# Steps whose per-step constants (moving scenes) go up in one copy: a multiple of the
# backend's steps per multi-step launch; the table buffer's size is this many tables
# (bounded by the device's constant-buffer size).
STEPS_PER_UPLOAD = 256


def collider_counts(scene) -> tuple[tuple[object, int], ...]:
    """(kind, count) of every analytic collider kind the OpenCL kernels take (collide.cl),
    in the table's and the step's order (colliders/kinds.py): the build's CLOTH_* counts, the
    generic kernel's count arguments, the table's parts and the tuning key all read it."""
    return tuple((kind, len(getattr(scene, kind.plural))) for kind in kinds_in("opencl"))


class OpenCLBodiesMixin:
    """For an OpenCLDeviceMixin backend: call _open_bodies(period, launch_steps) after _open_queue(); then
    self._colliders is the collider table buffer, _body_options() the build options,
    _mesh_source the `#include <mesh_colliders>` text, _body_args(j) the kernels' extra
    arguments for table j of the last upload, and _upload_step_constants(count) before the
    launches that read `count` tables (advance() adds them to self._clock; upload() zeroes it)."""

    def _open_bodies(self, period: float, launch_steps: int) -> None:
        scene, cl = self.scene, self._cl
        self._period = period  # seconds per table: the solver's step or substep
        self._launch_steps = launch_steps  # the most tables one launch reads: uploads hold a multiple
        self._meshes = [MeshConstants.of(m) for m in scene.meshes]
        self._per_step = scene.has_motion  # a table (and pin targets) per step
        self._attached = scene.pin_attach is not None
        self._clock = 0  # steps since the last upload(): step k's poses are at (k + 1) period
        self._copies: list = []  # the last per-step constants' copy events (kept alive)
        self._colliders = self._table_buffer()
        self._mesh_geometry, self._mesh_ints = self._mesh_buffers() if self._meshes else (None, None)
        self._pin_slot = self._pin_target = None
        if self._attached:  # per particle: its row of a step's pin targets, -1 for none
            slot = np.full(scene.particles, -1, np.int32)
            slot[scene.pinned()] = np.arange(len(scene.pinned()), dtype=np.int32)
            self._pin_slot = self._read_only_buffer(slot)
            target_bytes = 4 * 3 * len(scene.pinned()) * self._upload_steps
            self._pin_target = cl.Buffer(self._context, cl.mem_flags.READ_ONLY, target_bytes)

    def _body_options(self) -> tuple[str, ...]:
        """What of meshes, motion and attached pins the scene has (none: no option, no code)."""
        options = []
        if self._meshes:
            options.append(f"-DCLOTH_MESHES={len(self._meshes)}")
            if self.mesh_collision == "accelerated":
                options.append("-DCLOTH_MESH_BVH")
        if self._per_step:
            options.append("-DCLOTH_PER_STEP")
        if self._attached:
            options += ["-DCLOTH_ATTACHED_PINS", f"-DCLOTH_PINS={len(self.scene.pinned())}"]
        return tuple(options)

    def _mesh_source(self) -> str:
        """The text of `#include <mesh_colliders>`: collide_mesh.cl where the scene has meshes."""
        return f'#include "{MESH_FILE}"\n' if self._meshes else ""

    def _table(self, time: float) -> np.ndarray:
        """The collider table at `time` (collide.cl's rows, then collide_mesh.cl's MESH_ROWS
        per mesh: R's rows with the margin, its square and closedness, T, the box)."""
        rows = collider_rows(self.scene, np.float32, time)
        parts = [rows[kind.plural] for kind, _ in collider_counts(self.scene)]
        for mesh, c in zip(self.scene.meshes, self._meshes):
            rot, trans = pose_rows(mesh, time)
            extra = (c.margin, c.margin2, np.float32(c.closed), 0.0, 0.0, 0.0)
            vectors = (rot[0], rot[1], rot[2], trans, c.lo, c.hi)
            parts.append(np.array([[*v, e] for v, e in zip(vectors, extra)], np.float32))
        return np.concatenate(parts).astype(np.float32).reshape(-1, 4)

    @cached_property
    def _upload_steps(self) -> int:
        """Steps of per-step constants one upload holds (1 without motion: one fixed table)."""
        if not self._per_step:
            return 1
        table_bytes = max(1, len(self._table(0.0))) * 16
        fits = self._device.max_constant_buffer_size // table_bytes
        steps = min(STEPS_PER_UPLOAD, fits // self._launch_steps * self._launch_steps)
        if steps < 1:
            raise ClothbenchError(
                f"the scene's collider table takes {table_bytes} bytes a step, too many for "
                f"{self._launch_steps} steps in this device's constant buffer; use fewer colliders"
            )
        return steps

    def _table_buffer(self):
        """The fixed collider table (uploaded once), or room for _upload_steps tables."""
        if not self._per_step:
            table = self._table(0.0)
            limit = self._device.max_constant_buffer_size
            if table.nbytes > limit:
                raise ClothbenchError(
                    f"the scene's {len(self.scene.colliders) + len(self._meshes)} colliders take {table.nbytes} bytes, "
                    f"more than this device's {limit}-byte constant buffer; use fewer colliders"
                )
            return self._read_only_buffer(table if len(table) else np.zeros((1, 4), np.float32))
        table_bytes = 16 * max(1, len(self._table(0.0)))  # OpenCL has no empty buffers (pins only)
        return self._cl.Buffer(self._context, self._cl.mem_flags.READ_ONLY, table_bytes * self._upload_steps)

    def _mesh_buffers(self):
        """mesh_geometry (float4 rows) and mesh_ints, as collide_mesh.cl's header lays them out;
        the BVH only for the accelerated search."""
        geometries = [m.geometry for m in self._meshes]
        total = sum(g.triangles for g in geometries)
        rows = [g.corners.reshape(-1, 3) for g in geometries] + [g.normals.reshape(-1, 3) for g in geometries]
        ints, lists, tri0, node0 = [3 * total, 10 * total], [], 0, 0
        nodes = []
        header = 2 + 4 * len(geometries)
        for g in geometries:
            listed = header + sum(len(x) for x in lists)
            ints += [tri0, g.triangles, node0, listed]
            tri0 += g.triangles
            if self.mesh_collision == "accelerated":
                bvh = g.bvh
                node = np.zeros((bvh.nodes, 2, 4), np.float32)
                node[:, 0, :3], node[:, 1, :3] = bvh.lo, bvh.hi
                bits = node.view(np.int32)
                bits[:, 0, 3] = bvh.child
                bits[:, 1, 3] = bvh.first * 8 + bvh.count  # a leaf holds at most LEAF_SIZE (4) triangles
                nodes.append(node.reshape(-1, 4))
                lists.append(bvh.tris.astype(np.int32))
                node0 += bvh.nodes
        geometry = np.zeros((10 * total, 4), np.float32)
        geometry[:, :3] = np.concatenate(rows)
        geometry = np.concatenate([geometry, *nodes])
        ints = np.concatenate([np.array(ints, np.int32), *lists])
        return self._read_only_buffer(geometry), self._read_only_buffer(ints)

    def _upload_step_constants(self, count: int) -> None:
        """The tables and pin targets of the next `count` steps (from self._clock), evaluated in
        float64 and rounded once, copied in queue order before the launches that read them
        (non-blocking: pyopencl keeps the host arrays alive until the copy is done)."""
        if not self._per_step:
            return
        period, cl = self._period, self._cl
        times = [(self._clock + j + 1) * period for j in range(count)]  # the end of each step
        tables = np.concatenate([self._table(t) for t in times])
        # kept until the next upload: a copy's event, dropped, would wait for it to finish
        self._copies = [cl.enqueue_copy(self.queue, self._colliders, tables, is_blocking=False)]
        if self._attached:
            targets = np.concatenate([pin_targets(self.scene, t) for t in times]).astype(np.float32)
            self._copies.append(cl.enqueue_copy(self.queue, self._pin_target, targets, is_blocking=False))

    def _body_args(self, step: int) -> tuple:
        """The kernels' arguments after the solver's own: the index of the launch's first step
        in the uploaded tables, the mesh buffers, the attached pins'."""
        args = (np.int32(step),) if self._per_step else ()
        if self._meshes:
            args += (self._mesh_geometry, self._mesh_ints)
        if self._attached:
            args += (self._pin_slot, self._pin_target)
        return args

    def _body_dtypes(self) -> list:
        """set_scalar_arg_dtypes entries of _body_args()."""
        return [np.int32] * self._per_step + [None, None] * bool(self._meshes) + [None, None] * self._attached

    def _body_buffers(self) -> tuple:
        return (self._colliders, self._mesh_geometry, self._mesh_ints, self._pin_slot, self._pin_target)
