"""Triangle-mesh colliders on the host: loading (trimesh), the clean-up rules, the per-triangle
pseudo-normals and the BVH, all in the mesh's own (body) frame and in float32 as a kernel
reads them. docs/semantics.md, "Triangle mesh", is the response that uses them.

Rules, applied in this order to the file's (or built-in shape's) triangles:
1. body-frame vertices = scale * file vertices in float64, rounded once to float32;
2. vertices with identical float32 coordinates are one vertex (files repeat vertices per
   face for normals or texture coordinates);
3. a triangle is dropped when two of its corners are one vertex, or when twice its area
   |(b - a) x (c - a)| (float64, from the float32 corners) is <= 2^-23 times its longest
   edge squared: its height is below float32's resolution of that edge (degenerate);
4. the mesh is closed when every edge is shared by exactly two triangles that run it in
   opposite directions; a closed mesh with a negative signed volume is turned inside out
   (each triangle's b and c swapped) so that its normals point out;
5. an open (or non-manifold) mesh has no inside: it is a skin of thickness `margin` on the
   side its normals point away from, and needs margin > 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np

from clothbench.errors import SceneError
from clothbench.model.colliders.motion import Motion, euler_degrees, pose

SHAPES = ("box", "icosphere", "torus")
MESH_SUFFIXES = (".obj", ".stl", ".ply")
DEGENERATE = 2.0**-23  # rule 3: twice the area against the longest edge squared
LEAF_SIZE = 4  # triangles per BVH leaf
MAX_STACK = 32  # the traversal's fixed stack: the BVH is refused deeper than this
# the 7 pseudo-normals of a triangle, by the feature of Ericson's region the closest point is in
FEATURES = ("face", "a", "b", "c", "ab", "ac", "bc")


@dataclass(frozen=True)
class Mesh:
    """A rigid triangle mesh: from a file (OBJ, STL, PLY) or a built-in shape, scaled in its
    body frame, then rotated (degrees about x, then y, then z) and placed at `position`."""

    file: str | None = None
    shape: str | None = None
    subdivisions: int = 0
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    margin: float = 0.0
    name: str = ""
    motion: Motion | None = None

    kind = "mesh"

    def __post_init__(self):
        # scale: one number or three, as in the scene file
        if isinstance(self.scale, (int, float)) and not isinstance(self.scale, bool):
            object.__setattr__(self, "scale", (float(self.scale),) * 3)
        for what in ("position", "rotation", "scale"):
            v = getattr(self, what)
            if isinstance(v, (list, tuple)):
                object.__setattr__(self, what, tuple(v))

    @property
    def source(self) -> str:
        return self.file if self.file is not None else f"{self.shape} (subdivisions {self.subdivisions})"

    @property
    def geometry(self) -> "MeshGeometry":
        return mesh_geometry(self.file, self.shape, self.subdivisions, self.scale)

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) in float64: world = R body + T."""
        return pose(self.position, euler_degrees(self.rotation), self.motion, t)

    def check(self) -> None:
        """Refuse, in one line, what cannot be simulated: loads the geometry once."""
        if (self.file is None) == (self.shape is None):
            raise SceneError("a mesh needs exactly one of file or shape")
        if self.shape is not None and self.shape not in SHAPES:
            raise SceneError(f"unknown mesh shape {self.shape!r} (known: {', '.join(SHAPES)})")
        if (
            not isinstance(self.subdivisions, int)
            or isinstance(self.subdivisions, bool)
            or not 0 <= self.subdivisions <= 6
        ):
            raise SceneError(f"mesh subdivisions must be an integer 0 .. 6, got {self.subdivisions!r}")
        for what, v in (("position", self.position), ("rotation", self.rotation), ("scale", self.scale)):
            if len(v) != 3 or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
                raise SceneError(f"mesh {what} must be three finite numbers, got {v!r}")
        if any(s == 0 for s in self.scale):
            raise SceneError(f"mesh scale must not be zero, got {self.scale!r}")
        if not isinstance(self.margin, (int, float)) or not math.isfinite(self.margin) or self.margin < 0:
            raise SceneError(f"mesh margin must be a finite number >= 0, got {self.margin!r}")
        g = self.geometry
        if not g.closed and self.margin <= 0:
            raise SceneError(
                f"mesh {self.source} is open or not manifold, so it has no inside: give it a margin > 0 "
                "(the thickness of its skin on the side opposite its normals)"
            )


def _shape_triangles(shape: str, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit built-in shapes: a box of side 1 (12 * 4^s triangles), an icosphere of radius 1
    (20 * 4^s), a torus around the y axis, radii 1 and 0.3 (256 * 4^s)."""
    import trimesh

    if shape == "torus":
        m = trimesh.creation.torus(1.0, 0.3, major_sections=16 * 2**s, minor_sections=8 * 2**s)
        v = np.asarray(m.vertices, dtype=np.float64)
        return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1), np.asarray(m.faces)  # axis z -> y
    if shape == "icosphere":
        m = trimesh.creation.icosphere(subdivisions=s, radius=1.0)
        return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces)
    m = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces)
    for _ in range(s):
        v, f = trimesh.remesh.subdivide(v, f)
    return np.asarray(v, dtype=np.float64), np.asarray(f)


def _file_triangles(file: str) -> tuple[np.ndarray, np.ndarray]:
    path = Path(file)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise SceneError(f"mesh file {file}: expected {', '.join(MESH_SUFFIXES)}")
    if not path.is_file():
        raise SceneError(f"mesh file {file} not found")
    try:
        import trimesh

        m = trimesh.load(str(path), force="mesh", process=False)
        v, f = np.asarray(m.vertices, dtype=np.float64), np.asarray(m.faces, dtype=np.int64)
    except SceneError:
        raise
    except ModuleNotFoundError as e:  # trimesh falls back to decoding junk as text with an optional package
        raise SceneError(
            f"cannot read mesh file {file} as a triangle mesh: not a {path.suffix[1:].upper()} file trimesh can parse "
            f"(its text fallback wanted the missing package {e.name})"
        ) from None
    except Exception as e:  # any parser's failure is the file's problem, said in one line
        raise SceneError(
            f"cannot read mesh file {file} as a triangle mesh: {type(e).__name__}: {e}".splitlines()[0]
        ) from None
    if f.ndim != 2 or len(f) == 0 or f.shape[1] != 3:
        raise SceneError(f"mesh file {file} has no triangles")
    if not np.isfinite(v).all():
        raise SceneError(f"mesh file {file} has a vertex that is not a finite number")
    if f.min() < 0 or f.max() >= len(v):
        raise SceneError(f"mesh file {file} has a triangle that names a vertex it does not have")
    return v, f


@lru_cache(maxsize=64)
def mesh_geometry(file, shape, subdivisions, scale) -> "MeshGeometry":
    v, f = _file_triangles(file) if file is not None else _shape_triangles(shape, subdivisions)
    with np.errstate(over="ignore"):
        body = (v * np.array(scale, dtype=np.float64)).astype(np.float32)  # rule 1
    if not np.isfinite(body).all():
        raise SceneError(f"mesh {file or shape} scaled by {scale} does not fit float32")
    return MeshGeometry.build(body, np.asarray(f, dtype=np.int64))


@dataclass(frozen=True, eq=False)
class MeshGeometry:
    """The cleaned triangles in the body frame (float32 corners, original order kept, which
    is the index that breaks ties) with their pseudo-normals."""

    corners: np.ndarray  # (T, 3, 3) float32: a, b, c of each triangle
    normals: np.ndarray  # (T, 7, 3) float32 unit pseudo-normals, in FEATURES order
    closed: bool
    dropped: int  # triangles removed by rule 3

    @property
    def triangles(self) -> int:
        return len(self.corners)

    @property
    def lo(self) -> np.ndarray:
        return self.corners.reshape(-1, 3).min(axis=0)

    @property
    def hi(self) -> np.ndarray:
        return self.corners.reshape(-1, 3).max(axis=0)

    @classmethod
    def build(cls, body: np.ndarray, faces: np.ndarray) -> "MeshGeometry":
        unique, inverse = np.unique(body, axis=0, return_inverse=True)  # rule 2
        faces = inverse.reshape(-1)[faces]
        a, b, c = (unique[faces[:, k]].astype(np.float64) for k in range(3))
        cross = np.cross(b - a, c - a)
        twice_area = np.linalg.norm(cross, axis=1)
        longest2 = np.max([((b - a) ** 2).sum(1), ((c - a) ** 2).sum(1), ((c - b) ** 2).sum(1)], axis=0)
        distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
        keep = distinct & (twice_area > DEGENERATE * longest2)  # rule 3
        faces = faces[keep]
        if len(faces) == 0:
            raise SceneError("mesh has no triangle left after dropping degenerate ones (docs/semantics.md)")
        closed = _is_closed(faces)
        if closed:
            a, b, c = (unique[faces[:, k]].astype(np.float64) for k in range(3))
            volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
            if volume < 0:  # rule 4: normals point out
                faces = faces[:, [0, 2, 1]]
            closed = volume != 0
        corners = unique[faces]  # (T, 3, 3) float32
        return cls(corners, _pseudo_normals(unique, faces), bool(closed), int((~keep).sum()))

    @cached_property
    def bvh(self) -> "Bvh":
        return Bvh.build(self.corners)


def _edges(faces: np.ndarray) -> np.ndarray:
    """(3T, 2) directed edges ab, bc, ca of each triangle."""
    return np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])


def _is_closed(faces: np.ndarray) -> bool:
    directed = _edges(faces)
    undirected = np.sort(directed, axis=1)
    _, counts = np.unique(undirected, axis=0, return_counts=True)
    if not (counts == 2).all():
        return False
    # consistent winding: no directed edge appears twice
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    return bool((dcounts == 1).all())


def _unit(v: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = v / norm
    return np.where(norm > 0, u, fallback)  # a sum that cancels (a two-sided sheet): the face normal


def _pseudo_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Angle-weighted pseudo-normals (Baerentzen and Aanaes 2005), float64, rounded once:
    face: the unit normal; edge: the sum of the unit normals of the triangles sharing it;
    vertex: the sum of the unit normals of its triangles weighted by their angle there;
    each normalised, falling back to the face's own normal where a sum is zero."""
    p = vertices.astype(np.float64)[faces]  # (T, 3, 3)
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    face /= np.linalg.norm(face, axis=1, keepdims=True)
    vertex_sum = np.zeros((len(vertices), 3))
    for k in range(3):
        e1, e2 = p[:, (k + 1) % 3] - p[:, k], p[:, (k + 2) % 3] - p[:, k]
        cosine = (e1 * e2).sum(1) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        np.add.at(vertex_sum, faces[:, k], np.arccos(np.clip(cosine, -1.0, 1.0))[:, None] * face)
    T = len(faces)
    und = np.sort(_edges(faces), axis=1)  # edge ab of every triangle, then bc, then ca
    _, edge_id = np.unique(und, axis=0, return_inverse=True)
    edge_id = edge_id.reshape(-1)
    edge_sum = np.zeros((edge_id.max() + 1, 3))
    np.add.at(edge_sum, edge_id, np.concatenate([face, face, face]))
    ab, bc, ca = edge_sum[edge_id[:T]], edge_sum[edge_id[T : 2 * T]], edge_sum[edge_id[2 * T :]]
    out = np.stack(
        [face, *(vertex_sum[faces[:, k]] for k in range(3)), ab, ca, bc], axis=1
    )  # FEATURES order: face, a, b, c, ab, ac, bc
    return _unit(out, face[:, None, :]).astype(np.float32)


@dataclass(frozen=True, eq=False)
class Bvh:
    """A binary BVH over the body-frame triangles, flattened for a kernel: node i has the box
    lo[i]..hi[i] (exact float32 min/max of its triangles' corners: no rounding, so the
    box-distance lower bound is provably <= the distance the step computes to any triangle in
    it, docs/semantics.md); an interior node's children are child[i] and child[i] + 1; a
    leaf (child[i] == -1) holds triangles tris[first[i] : first[i] + count[i]], by their
    original index. Built by median split of the centroids on the widest axis."""

    lo: np.ndarray  # (N, 3) float32
    hi: np.ndarray  # (N, 3) float32
    child: np.ndarray  # (N,) int32
    first: np.ndarray  # (N,) int32
    count: np.ndarray  # (N,) int32
    tris: np.ndarray  # (T,) int32
    depth: int

    @classmethod
    def build(cls, corners: np.ndarray) -> "Bvh":
        centroid = corners.astype(np.float64).mean(axis=1)
        tri_lo, tri_hi = corners.min(axis=1), corners.max(axis=1)
        order = []  # leaf triangle lists, appended as leaves are made
        nodes = [None]  # (lo, hi, child, first, count)
        queue = [(0, np.arange(len(corners)), 1)]
        depth = 1
        while queue:
            i, idx, level = queue.pop(0)
            depth = max(depth, level)
            lo, hi = tri_lo[idx].min(axis=0), tri_hi[idx].max(axis=0)
            if len(idx) <= LEAF_SIZE:
                nodes[i] = (lo, hi, -1, len(order), len(idx))
                order.extend(idx.tolist())
                continue
            c = centroid[idx]
            axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            idx = idx[np.lexsort((idx, c[:, axis]))]  # by centroid, ties by index: deterministic
            half = len(idx) // 2
            left = len(nodes)
            nodes += [None, None]
            nodes[i] = (lo, hi, left, 0, 0)
            queue += [(left, idx[:half], level + 1), (left + 1, idx[half:], level + 1)]
        if depth > MAX_STACK:
            raise SceneError(f"mesh BVH is {depth} levels deep, more than the kernels' stack of {MAX_STACK}")
        lo, hi, child, first, count = zip(*nodes)
        return cls(
            np.array(lo, dtype=np.float32),
            np.array(hi, dtype=np.float32),
            np.array(child, dtype=np.int32),
            np.array(first, dtype=np.int32),
            np.array(count, dtype=np.int32),
            np.array(order, dtype=np.int32),
            depth,
        )

    @property
    def nodes(self) -> int:
        return len(self.lo)
