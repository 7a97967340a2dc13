"""Triangle-mesh colliders (docs/semantics.md, "Triangle mesh"): the scene format and its
refusals, the response on hard cases (a vertex, an edge, an open skin, degenerate triangles, far
from the origin, a fast pass), the BVH traversal giving the naive loop's triangle and bits, and the
check of a state against the mesh itself (a winding number) that the contract applies to every
backend's mesh scenes (tests/contract/test_bodies_contract.py)."""

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh", reason="mesh colliders load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions, create_backend
from clothbench.model.kernel_inputs import MeshConstants, pose_rows
from clothbench.backends.numpy.collide_mesh import (
    closest_triangle_bvh,
    closest_triangle_naive,
    collide_mesh,
)
from clothbench.cli import main
from clothbench.model.colliders.mesh import Mesh
from clothbench.errors import SceneError
from clothbench.model.scene import Scene, Sphere, load_scene
from clothbench.model.solver import Verlet

F32 = BackendOptions(precision="f32")
VERLET = Verlet(dt=5e-4)
BOX_OBJ = """v -0.5 -0.5 -0.5
v 0.5 -0.5 -0.5
v 0.5 0.5 -0.5
v -0.5 0.5 -0.5
v -0.5 -0.5 0.5
v 0.5 -0.5 0.5
v 0.5 0.5 0.5
v -0.5 0.5 0.5
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 4 8 7
f 4 7 3
f 1 5 8
f 1 8 4
f 2 3 7
f 2 7 6
"""


def one_step(scene, points, dtype=np.float32):
    """Free particles placed at `points` at rest (no springs, no gravity), after one step."""
    pos, prev = scene.initial_state(np.float64)
    pos[: len(points), :3] = points
    prev[: len(points), :3] = points
    with create_backend("numpy", scene, VERLET, BackendOptions(precision="f32" if dtype == np.float32 else "f64")) as b:
        b.upload(pos.astype(dtype), prev.astype(dtype))
        b.advance(1)
        return b.read()[0][: len(points), :3].astype(np.float64)


def still(*meshes, **kw):
    # no springs, no gravity, no damping: only the collision moves a particle
    return Scene(grid=3, stiffness=0.0, damping=0.0, gravity=(0, 0, 0), height=50.0, meshes=meshes, **kw)


def winding_number(tm, points):
    """Generalised winding number (van Oosterom and Strackee's solid angles, float64): about
    1 inside a closed mesh, 0 outside. Independent of the reference's pseudo-normals."""
    tri = tm.triangles[None, :, :, :] - points[:, None, None, :]  # (P, T, 3, 3)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
    det = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
    den = la * lb * lc + (a * b).sum(-1) * lc + (a * c).sum(-1) * lb + (b * c).sum(-1) * la
    return (2 * np.arctan2(det, den)).sum(1) / (4 * np.pi)


def world_mesh(mesh, t=0.0):
    g = mesh.geometry
    rot, trans = mesh.pose_at(t)
    v = g.corners.reshape(-1, 3).astype(np.float64) @ rot.T + trans
    return trimesh.Trimesh(v, np.arange(len(v)).reshape(-1, 3), process=True)


# --- the scene format ----------------------------------------------------------------------


def test_mesh_table_reads_as_the_issue_writes_it(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "box.obj").write_text(BOX_OBJ)
    (tmp_path / "scene.toml").write_text(
        '[[mesh]]\nfile = "meshes/box.obj"\nposition = [0.5, 0.3, 0.5]\nrotation = [0.0, 30.0, 0.0]\n'
        'scale = 0.3\nmargin = 0.01\nname = "bowl"\n'
        '[[mesh]]\nshape = "icosphere"\nsubdivisions = 2\nscale = [0.1, 0.2, 0.1]\n'
    )
    s = load_scene(str(tmp_path / "scene.toml"))  # the file is read from the scene's folder
    box, ball = s.meshes
    assert box.scale == (0.3, 0.3, 0.3) and box.rotation == (0.0, 30.0, 0.0) and box.name == "bowl"
    assert box.geometry.triangles == 12 and box.geometry.closed
    assert ball.geometry.triangles == 20 * 4**2 and ball.margin == 0.0 and ball.position == (0, 0, 0)


def test_scenes_without_meshes_load_as_before():
    s = load_scene("sphere")
    assert s.meshes == () and s.frames == () and s.pin_attach is None and not s.has_motion
    assert s == Scene(name="sphere", description=s.description, height=0.85, spheres=(Sphere((0.5, 0.5, 0.5), 0.3),))


JUNK = bytes(range(256)) * 4


@pytest.mark.parametrize(
    "mesh, files, message",
    [
        ('shape = "box"\nscal = 2', {}, "unknown key 'scal' in \\[\\[mesh\\]\\]"),
        ('file = "nowhere.obj"', {}, "mesh file .*nowhere.obj not found"),
        ('file = "junk.stl"', {"junk.stl": JUNK}, "cannot read mesh file .*junk.stl|junk.stl has no triangles"),
        ('file = "empty.obj"', {"empty.obj": b""}, "cannot read mesh file .*empty.obj|empty.obj has no triangles"),
        ('file = "box.fbx"', {"box.fbx": b"x"}, "expected .obj, .stl, .ply"),
        ('shape = "cone"', {}, "unknown mesh shape 'cone'"),
        ('shape = "box"\nscale = [1.0, 0.0, 1.0]', {}, "mesh scale must not be zero"),
        ('shape = "box"\nscale = nan', {}, "mesh scale .*must be three finite numbers"),
        ('shape = "box"\nposition = [0.0, nan, 0.0]', {}, "mesh position must be three finite numbers"),
        ('shape = "box"\nmargin = -0.1', {}, "mesh margin must be a finite number >= 0"),
        ('file = "a.obj"\nshape = "box"', {"a.obj": BOX_OBJ.encode()}, "exactly one of file or shape"),
        (
            'file = "sheet.obj"',
            {"sheet.obj": b"v 0 0 0\nv 1 0 0\nv 0 0 1\nf 1 3 2\n"},
            "open or not manifold.*margin > 0",
        ),
        (
            'file = "line.obj"',
            {"line.obj": b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"},
            "no triangle left after dropping degenerate",
        ),
        ('shape = "box"\nmotion = { velocity = [1, 0] }', {}, "motion velocity must be three finite numbers"),
    ],
)
def test_bad_meshes_are_one_line_and_exit_2(tmp_path, capsys, mesh, files, message):
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    path = tmp_path / "scene.toml"
    path.write_text(f"[[mesh]]\n{mesh}\n")
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))
    assert main(["run", "--backend", "numpy", "--scene", str(path), "--grid", "4", "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


# --- the response --------------------------------------------------------------------------


def test_a_particle_inside_goes_to_the_closest_surface_point_plus_the_margin():
    scene = still(Mesh(shape="box", position=(0.0, 50.0, 0.0), margin=0.01))
    out = one_step(scene, [(0.4, 50.1, 0.0), (0.0, 50.0, -0.45), (0.0, 50.0, 0.505), (0.0, 50.0, 0.6)])
    np.testing.assert_allclose(out[0], (0.51, 50.1, 0.0), atol=1e-5)  # nearest face: +x
    np.testing.assert_allclose(out[1], (0.0, 50.0, -0.51), atol=1e-5)  # nearest face: -z
    np.testing.assert_allclose(out[2], (0.0, 50.0, 0.51), atol=1e-5)  # outside, within the margin
    assert out[3][2] == np.float32(0.6)  # outside the margin: untouched


def test_a_particle_exactly_on_a_vertex_or_an_edge_has_a_defined_result():
    # on the surface (distance 0): margin 0 leaves it; a margin pushes it along the vertex's
    # or edge's pseudo-normal (the corner's is (1, 1, 1)/sqrt 3, the edge's (1, 1, 0)/sqrt 2)
    points = [(0.5, 50.5, 0.5), (0.5, 50.5, 0.0)]
    on = one_step(still(Mesh(shape="box", position=(0.0, 50.0, 0.0))), points)
    np.testing.assert_array_equal(on, np.array(points, dtype=np.float32))
    out = one_step(still(Mesh(shape="box", position=(0.0, 50.0, 0.0), margin=0.1)), points)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[0], np.array(points[0]) + 0.1 / np.sqrt(3), atol=1e-5)
    np.testing.assert_allclose(out[1], np.array(points[1]) + (0.1 / np.sqrt(2), 0.1 / np.sqrt(2), 0), atol=1e-5)


def test_degenerate_triangles_are_dropped_and_the_box_stays_closed(tmp_path):
    # a zero-area sliver on the box's top face and a triangle naming one vertex twice
    extra = "v 0.0 0.5 0.0\nv 0.25 0.5 0.25\nf 7 9 10\nf 1 1 2\n"
    (tmp_path / "box.obj").write_text(BOX_OBJ + extra)
    mesh = Mesh(file=str(tmp_path / "box.obj"), position=(0.0, 50.0, 0.0))
    g = mesh.geometry
    assert g.dropped == 2 and g.triangles == 12 and g.closed
    out = one_step(still(mesh), [(0.0, 50.45, 0.0), (0.1, 50.5, 0.0)])
    np.testing.assert_allclose(out[0], (0.0, 50.5, 0.0), atol=1e-6)
    assert np.isfinite(out).all()


def test_an_open_mesh_is_a_skin_of_margin_thickness_on_its_inner_side(tmp_path):
    # one square, normals up (+y): the skin is the 5 cm below it
    (tmp_path / "square.obj").write_text("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n")
    mesh = Mesh(file=str(tmp_path / "square.obj"), position=(0.0, 50.0, 0.0), margin=0.05)
    assert not mesh.geometry.closed
    out = one_step(still(mesh), [(0.2, 49.98, 0.3), (0.2, 50.02, 0.3), (0.2, 49.9, 0.3), (1.5, 49.98, 0.0)])
    np.testing.assert_allclose(out[0], (0.2, 50.05, 0.3), atol=1e-5)  # in the skin: out above it
    assert out[1][1] == np.float32(50.02)  # above, within the margin: the outer side is free
    assert out[2][1] == np.float32(49.9)  # below the skin
    assert out[3][1] == np.float32(49.98)  # beside the square: the closest point is its edge, side > 0


def test_a_mesh_far_from_the_origin_still_pushes_out_to_float32_resolution():
    # at 1e4 m a float32 coordinate steps by 2^-10 m (about 1 mm): the push-out lands within
    # that of the surface, and nothing is NaN
    far = 1.0e4
    scene = Scene(
        grid=3,
        stiffness=0.0,
        damping=0.0,
        gravity=(0, 0, 0),
        height=far,
        meshes=(Mesh(shape="icosphere", subdivisions=3, position=(far, far, far), scale=0.5),),
    )
    out = one_step(scene, [(far + 0.3, far, far), (far, far - 0.2, far + 0.1)])
    ulp = float(np.spacing(np.float32(far)))
    assert ulp == 2.0**-10
    dist = np.linalg.norm(out - far, axis=1)
    assert np.isfinite(out).all() and (dist >= 0.5 * 0.995 - 2 * ulp).all()  # icosphere's flat faces: 0.5 % in


def test_a_fast_particle_passes_through_a_thin_mesh():
    # 1 cm thick slab, 5 cm per step: the particle is never inside at the end of a step, so
    # no collider catches it (docs/semantics.md: no continuous collision)
    slab = Mesh(shape="box", position=(0.0, 50.0, 0.0), scale=(1.0, 0.01, 1.0))
    scene = still(slab)
    pos, prev = scene.initial_state(np.float32)
    pos[0, :3], prev[0, :3] = (0.0, 50.03, 0.0), (0.0, 50.08, 0.0)  # moving down at 100 m/s
    with create_backend("numpy", scene, VERLET, F32) as b:
        b.upload(pos, prev)
        b.advance(2)
        assert b.read()[0][0, 1] == pytest.approx(49.93, abs=1e-4)


# --- BVH against the naive loop ------------------------------------------------------------


def probe_points(mesh, rng, count):
    """Body-frame points that stress ties: random ones around the mesh, every vertex, edge
    midpoints and face centres (exactly on the surface), slightly inside, the centre (a box's
    centre is equidistant to six faces) and far away."""
    corners = mesh.geometry.corners.astype(np.float64)
    lo, hi = corners.reshape(-1, 3).min(0), corners.reshape(-1, 3).max(0)
    around = rng.uniform(lo - 0.3 * (hi - lo), hi + 0.3 * (hi - lo), (count, 3))
    k = min(count, len(corners))
    pick = corners[rng.choice(len(corners), k, replace=False)]
    on = np.concatenate([pick[:, 0], (pick[:, 0] + pick[:, 1]) / 2, pick.mean(1), pick.mean(1) * 0.97])
    far = np.array(
        [[1e4, 0, 0], [0, -3e3, 2e3], [0, 0, 0], [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2]]
    )
    return np.concatenate([around, on, far]).astype(np.float32).T


@pytest.mark.parametrize(
    "mesh, count",
    [
        (Mesh(shape="box"), 300),  # 12 triangles
        (Mesh(shape="icosphere"), 300),  # 20
        (Mesh(shape="torus", subdivisions=1), 200),  # 1024
        (Mesh(shape="box", subdivisions=3, scale=(1.0, 0.2, 2.0)), 150),  # 768, thin, ties on faces
        pytest.param(Mesh(shape="icosphere", subdivisions=5), 60, marks=pytest.mark.full),  # 20480: slow
    ],
    ids=["box-12", "icosphere-20", "torus-1024", "slab-768", "icosphere-20480"],
)
def test_bvh_traversal_finds_the_naive_loops_triangle_and_bits(mesh, count):
    rng = np.random.default_rng(17)
    p = probe_points(mesh, rng, count)
    naive_index, naive_d2 = closest_triangle_naive(p, mesh.geometry, cull=False)
    bvh_index, bvh_d2 = closest_triangle_bvh(p, mesh.geometry)
    culled_index, culled_d2 = closest_triangle_naive(p, mesh.geometry)
    for index, d2, what in ((bvh_index, bvh_d2, "bvh"), (culled_index, culled_d2, "culled naive")):
        np.testing.assert_array_equal(index, naive_index, err_msg=what)
        np.testing.assert_array_equal(d2.view(np.uint32), naive_d2.view(np.uint32), err_msg=what)
    if mesh.geometry.triangles > 1000:  # the point of it: far fewer triangles tested
        assert closest_triangle_bvh.visited < 0.2 * p.shape[1] * mesh.geometry.triangles


def test_bvh_and_naive_collisions_move_particles_to_the_same_bits():
    mesh = Mesh(shape="torus", subdivisions=1, position=(0.1, 0.2, -0.3), rotation=(20.0, 40.0, 0.0), scale=0.4)
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.5, 0.6, (3, 20, 20)).astype(np.float32)
    free = np.ones((20, 20), dtype=bool)
    consts = MeshConstants.of(mesh)
    rot, trans = pose_rows(mesh, 0.0)
    naive, bvh = x.copy(), x.copy()
    collide_mesh(naive, free, consts, rot, trans, closest=lambda p, g: closest_triangle_naive(p, g, cull=False))
    collide_mesh(bvh, free, consts, rot, trans, closest=closest_triangle_bvh)
    assert (naive != x).any()  # some were inside
    np.testing.assert_array_equal(naive.view(np.uint32), bvh.view(np.uint32))


def test_bvh_fits_the_kernels_stack():
    bvh = Mesh(shape="icosphere", subdivisions=6).geometry.bvh  # 81,920 triangles
    assert bvh.depth <= 32 and sorted(bvh.tris.tolist()) == list(range(81920))
