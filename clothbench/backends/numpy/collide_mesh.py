"""The NumPy reference of the mesh collider, moving colliders and attached pins:
docs/semantics.md, "Triangle mesh", "Moving colliders" and "Pins attached to a body".

Every operation is an element-wise, correctly rounded NumPy operation in the order the
semantics fix, so a kernel doing the same operations in the same order reproduces it bit for
bit. The closest triangle is found by the naive loop over every triangle (vectorised over
particles, chunked over triangles); `closest_triangle_bvh` is the host form of the BVH
traversal a kernel runs, and gives the same triangle and the same bits (tests/test_meshes.py).
"""

from __future__ import annotations

import numpy as np

from clothbench.colliders.mesh import MeshGeometry
from clothbench.backends.kernel_inputs import MeshConstants, pin_targets, pose_rows

TRIANGLE_CHUNK = 32  # triangles per vectorised pass of the naive loop (speed, not results)


def dot3(a, b):
    """(a.x*b.x + a.y*b.y) + a.z*b.z: the association every kernel uses (verlet.dot3's twin:
    verlet.py imports this module, so it cannot be imported from there)."""
    out = a[0] * b[0]
    out += a[1] * b[1]
    out += a[2] * b[2]
    return out


def closest_points(p, a, b, c):
    """Ericson's ClosestPtPointTriangle (Real-Time Collision Detection, 5.1.5) with the two
    guards and the clamp of docs/semantics.md: p (3, ...) against a, b, c (3, ...), broadcast.
    Returns (q, feature): the closest point and the index of the pseudo-normal of its region
    (colliders.mesh.FEATURES)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ab = b - a
        ac = c - a
        ap = p - a
        d1 = dot3(ab, ap)
        d2 = dot3(ac, ap)
        bp = p - b
        d3 = dot3(ab, bp)
        d4 = dot3(ac, bp)
        vc = d1 * d4 - d3 * d2
        cp = p - c
        d5 = dot3(ab, cp)
        d6 = dot3(ac, cp)
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        e43 = d4 - d3
        e56 = d5 - d6
        # the regions, tested in Ericson's order: the first that holds is taken
        in_a = (d1 <= 0) & (d2 <= 0)
        in_b = (d3 >= 0) & (d4 <= d3)
        in_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        in_c = (d6 >= 0) & (d5 <= d6)
        in_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        in_bc = (va <= 0) & (e43 >= 0) & (e56 >= 0)
        feature = np.select([in_a, in_b, in_ab, in_c, in_ac, in_bc], [1, 2, 4, 3, 5, 6], 0).astype(np.int8)
        # edge parameters: a zero denominator (an edge shorter than the rounding) gives 0
        den_ab = d1 - d3
        t_ab = np.where(den_ab > 0, d1 / den_ab, 0).astype(d1.dtype)
        den_ac = d2 - d6
        t_ac = np.where(den_ac > 0, d2 / den_ac, 0).astype(d1.dtype)
        den_bc = e43 + e56
        t_bc = np.where(den_bc > 0, e43 / den_bc, 0).astype(d1.dtype)
        s = (va + vb) + vc  # > 0 wherever the face region is taken: va, vb, vc > 0 there
        v = vb / s
        w = vc / s
        q_face = (a + ab * v) + ac * w
    q = q_face
    q = np.where(feature == 6, b + (c - b) * t_bc, q)
    q = np.where(feature == 5, a + ac * t_ac, q)
    q = np.where(feature == 4, a + ab * t_ab, q)
    q = np.where(feature == 3, c, q)
    q = np.where(feature == 2, b, q)
    q = np.where(feature == 1, a, q)
    # clamp into the triangle's box (exact): the BVH's pruning bound holds by construction
    lo = np.minimum(np.minimum(a, b), c)
    hi = np.maximum(np.maximum(a, b), c)
    q = np.minimum(np.maximum(q, lo), hi)
    return q, feature


def box_distance2(p, lo, hi):
    """Squared distance from p to the box lo..hi: g = max(max(lo - p, p - hi), 0), dot(g, g)."""
    g = np.maximum(np.maximum(lo - p, p - hi), 0)
    return dot3(g, g)


def closest_triangle_naive(p: np.ndarray, geometry: MeshGeometry, chunk: int = TRIANGLE_CHUNK, cull: bool = True):
    """For body-frame points p (3, P): (index, d2) of the closest triangle, ties to the
    lowest index: every triangle's d2, the smallest taken. index -1 where none is closer than
    +inf (a non-finite point). Without `cull`, the scan is in index order, chunk by chunk.
    With `cull` (the reference's default; the same bits, tests/test_meshes.py), the chunks are
    runs of the BVH's leaf order (each sorted by index), so that their boxes are tight; each
    point first takes the chunk whose box is nearest it, then every other chunk except those
    whose box is strictly farther than its best so far: every triangle in such a chunk is
    strictly farther (the BVH's argument, docs/semantics.md), so skipping it changes no bit."""
    P = p.shape[1]
    best = np.full(P, np.inf, dtype=p.dtype)
    index = np.full(P, -1, dtype=np.int64)
    corners = geometry.corners.astype(p.dtype)
    order = geometry.bvh.tris.astype(np.int64) if cull else np.arange(len(corners))
    # argmin's first minimum within a chunk is then its lowest index
    chunks = [np.sort(order[start : start + chunk]) for start in range(0, len(corners), chunk)]

    def scan(rows, ids):
        tri = corners[ids]  # (C, 3 corners, 3)
        pp = p[:, rows, None]
        a, b, c = (tri[:, k, :].T[:, None, :] for k in range(3))  # (3, 1, C)
        q, _ = closest_points(pp, a, b, c)
        d = pp - q
        d2 = dot3(d, d)  # (R, C)
        j = np.argmin(d2, axis=1)
        dj, ij = d2[np.arange(len(rows)), j], ids[j]
        # strictly closer, or as close with a lower index (chunks need not be in index order)
        better = (dj < best[rows]) | ((dj == best[rows]) & (ij < index[rows]))
        best[rows[better]] = dj[better]
        index[rows[better]] = ij[better]

    if not cull:
        for ids in chunks:
            scan(np.arange(P), ids)
        return index, best
    lo = np.stack([corners[ids].min(axis=(0, 1)) for ids in chunks], axis=1)  # (3, C)
    hi = np.stack([corners[ids].max(axis=(0, 1)) for ids in chunks], axis=1)
    bound = box_distance2(p[:, :, None], lo[:, None, :], hi[:, None, :])  # (P, C)
    nearest = np.argmin(bound, axis=1)
    for k, ids in enumerate(chunks):  # first pass: each point's nearest chunk, a tight best
        rows = np.flatnonzero(nearest == k)
        if len(rows):
            scan(rows, ids)
    for k, ids in enumerate(chunks):  # then every chunk that could still hold the closest
        rows = np.flatnonzero(~(bound[:, k] > best) & (nearest != k))
        if len(rows):
            scan(rows, ids)
    return index, best


def closest_triangle_bvh(p: np.ndarray, geometry: MeshGeometry):
    """The same as closest_triangle_naive, by the traversal a kernel runs (docs/semantics.md):
    a stack, nearer child first, a node skipped only when its box's squared distance is
    strictly greater than the best so far, ties to the lower index. One particle at a time."""
    bvh = geometry.bvh
    t = p.dtype.type
    corners = geometry.corners.astype(p.dtype)
    lo, hi = bvh.lo.astype(p.dtype), bvh.hi.astype(p.dtype)
    P = p.shape[1]
    index = np.full(P, -1, dtype=np.int64)
    best_out = np.full(P, np.inf, dtype=p.dtype)
    visited = 0
    for i in range(P):
        x = p[:, i]
        best, idx = t(np.inf), -1
        stack = [0]
        while stack:
            node = stack.pop()
            if box_distance2(x, lo[node], hi[node]) > best:
                continue  # every triangle in it is strictly farther
            child = bvh.child[node]
            if child >= 0:
                near, far = child, child + 1
                if box_distance2(x, lo[far], hi[far]) < box_distance2(x, lo[near], hi[near]):
                    near, far = far, near
                stack += [far, near]  # the nearer popped first: order changes speed, not results
                continue
            tris = bvh.tris[bvh.first[node] : bvh.first[node] + bvh.count[node]]
            visited += len(tris)
            tri = corners[tris]
            a, b, c = (tri[:, k, :].T for k in range(3))  # (3, L)
            q, _ = closest_points(x[:, None], a, b, c)
            d = x[:, None] - q
            for k, d2 in zip(tris, dot3(d, d)):
                if d2 < best or (d2 == best and k < idx):
                    best, idx = d2, int(k)
        index[i], best_out[i] = idx, best
    closest_triangle_bvh.visited = visited  # triangles tested, for the docs' counts
    return index, best_out


def to_body(x, rot, trans):
    """p = R^T (x - T): d = x - T per component, p_i = (R0i*d.x + R1i*d.y) + R2i*d.z."""
    d = x - trans
    return np.stack([(rot[0, i] * d[0] + rot[1, i] * d[1]) + rot[2, i] * d[2] for i in range(3)])


def to_world(y, rot, trans):
    """x = R y + T: x_i = ((Ri0*y.x + Ri1*y.y) + Ri2*y.z) + T_i."""
    return np.stack([((rot[i, 0] * y[0] + rot[i, 1] * y[1]) + rot[i, 2] * y[2]) + trans[i] for i in range(3)])


def collide_mesh(
    x: np.ndarray, free: np.ndarray, mesh: MeshConstants, rot, trans, closest=closest_triangle_naive
) -> None:
    """docs/semantics.md, "Triangle mesh": x (3, n, n) world positions, changed in place."""
    g = mesh.geometry
    flat = x.reshape(3, -1)
    cand = np.flatnonzero(free.reshape(-1))
    p = to_body(flat[:, cand], rot, trans[:, None])
    # early out: a particle farther than the margin from the mesh's box is not inside it
    near = box_distance2(p, mesh.lo[:, None], mesh.hi[:, None]) <= mesh.margin2
    cand, p = cand[near], p[:, near]
    if not len(cand):
        return
    index, d2 = closest(p, g)
    found = index >= 0
    cand, p, index, d2 = cand[found], p[:, found], index[found], d2[found]
    tri = mesh.corners[index]  # (P, 3, 3)
    a, b, c = (tri[:, k, :].T for k in range(3))
    q, feature = closest_points(p, a, b, c)  # the winner again: the same bits as in the scan
    nrm = mesh.normals[index, feature.astype(np.int64)].T  # (3, P)
    d = p - q
    side = dot3(d, nrm)
    push = (side < 0) | (d2 < mesh.margin2) if mesh.closed else (side < 0) & (d2 < mesh.margin2)
    if not push.any():
        return
    y = q[:, push] + nrm[:, push] * mesh.margin
    flat[:, cand[push]] = to_world(y, rot, trans[:, None])


class Bodies:
    """Per-step collider constants and attached-pin positions of a scene with meshes, moving
    colliders or pins attached to a body; `collide` applies every collider in the step's
    order (the analytic kinds of colliders/kinds.py, then the meshes). Steps are counted from
    the last upload."""

    def __init__(self, scene, dt: float, dtype, analytic_constants, collide_analytic):
        self.scene, self.dt, self.dtype = scene, dt, dtype
        self.analytic_constants = analytic_constants  # verlet.collider_constants
        self.collide_analytic = collide_analytic  # verlet.COLLIDE
        self.moving = any(c.motion is not None for c in scene.colliders)
        self.static = analytic_constants(scene, dtype)
        self.meshes = [MeshConstants.of(m, dtype) for m in scene.meshes]
        self.steps = 0

    @classmethod
    def needed(cls, scene) -> bool:
        return bool(scene.meshes) or scene.has_motion or scene.pin_attach is not None

    def collide(self, new: np.ndarray, free: np.ndarray, before_colliders=None) -> None:
        """`before_colliders(new)`: the self-collision pass, after the attached pins are placed."""
        self.steps += 1
        time = self.steps * self.dt  # the end of the step: x_new is the position at t + dt
        if self.scene.pin_attach is not None:
            pinned = self.scene.pinned()
            flat = new.reshape(3, -1)
            flat[:, pinned] = pin_targets(self.scene, time, self.dtype).T
        if before_colliders is not None:
            before_colliders(new)
        analytic = self.static
        if self.moving:
            analytic = self.analytic_constants(self.scene, self.dtype, time)
        for kind, constants in analytic:
            self.collide_analytic[kind](new, free, **constants)
        for mesh_scene, mesh in zip(self.scene.meshes, self.meshes):
            rot, trans = pose_rows(mesh_scene, time, self.dtype)
            collide_mesh(new, free, mesh, rot, trans)
