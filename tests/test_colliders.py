"""Colliders in the reference: spheres, capped cylinders, planes (docs/semantics.md)."""

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.errors import SceneError
from clothbench.harness import max_penetration, simulate
from clothbench.model.scene import Cylinder, Plane, Scene, Sphere, load_scene

from conftest import VERLET, setup

F64 = BackendOptions(precision="f64")
F32 = BackendOptions(precision="f32")


def one_step(scene, points):
    """Place free particles at `points` (at rest, no forces) and take one step."""
    pos, prev = scene.initial_state(np.float64)
    pos[: len(points), :3] = points
    prev[: len(points), :3] = points
    with create_backend("numpy", scene, VERLET, F64) as b:
        b.upload(pos, prev)
        b.advance(1)
        return b.read()[0][: len(points), :3]


def still(**colliders):
    # no springs, no gravity, no damping: only the collision moves a particle
    return Scene(grid=3, stiffness=0.0, damping=0.0, gravity=(0, 0, 0), height=5.0, **colliders)


def test_capped_cylinder_pushes_out_the_shortest_way():
    cyl = Cylinder(start=(0, 0, 0), end=(1, 0, 0), radius=0.2)
    out = one_step(
        still(cylinders=(cyl,)),
        [
            (0.5, 0.15, 0.0),  # near the side: out through the side
            (0.05, 0.0, 0.1),  # near the start cap: out through it
            (0.97, -0.05, 0.0),  # near the end cap
            (0.5, 0.0, 0.0),  # on the axis: out along the fixed radial direction
            (0.5, 0.5, 0.0),  # outside: untouched
        ],
    )
    np.testing.assert_allclose(out[0], (0.5, 0.2, 0.0), atol=1e-15)
    np.testing.assert_allclose(out[1], (0.0, 0.0, 0.1), atol=1e-15)
    np.testing.assert_allclose(out[2], (1.0, -0.05, 0.0), atol=1e-15)
    assert np.linalg.norm(out[3][1:]) == pytest.approx(0.2) and out[3][0] == 0.5
    np.testing.assert_array_equal(out[4], (0.5, 0.5, 0.0))


def test_plane_is_one_sided():
    floor = Plane(point=(0, 1, 0), normal=(0, 2, 0))  # normal need not be unit in the file
    out = one_step(still(planes=(floor,)), [(0.3, 0.9, 0.2), (0.3, 1.1, 0.2)])
    np.testing.assert_array_equal(out[0], (0.3, 1.0, 0.2))
    np.testing.assert_array_equal(out[1], (0.3, 1.1, 0.2))


@pytest.mark.parametrize("name", ["sphere", "cylinder", "curtain"])
def test_builtin_scenes_end_with_no_particle_inside_a_collider(name):
    run = setup(name, 24)
    s = run.scene
    pos, _ = simulate("numpy", s, run.solver, 1500, F32)
    assert np.isfinite(pos).all()
    # the cloth must actually reach a collider for this to mean anything
    assert _closest_approach(pos, s) < 0.02
    # projections round: allow a few float32 ulps of the collider's size
    assert max_penetration(pos, s) <= 1e-6


def _closest_approach(pos, s):
    xyz = pos[:, :3].astype(np.float64)
    gaps = [np.linalg.norm(xyz - sp.center, axis=1).min() - sp.radius for sp in s.spheres]
    for c in s.cylinders:
        d = xyz - c.start
        t = d @ np.array(c.axis)
        rho = np.linalg.norm(d - np.outer(t, c.axis), axis=1)
        gaps.append((rho - c.radius)[(t > 0) & (t < c.length)].min())
    return min(gaps)


def test_cylinder_scene_reaches_the_floor():
    run = setup("cylinder", 16)
    pos, _ = simulate("numpy", run.scene, run.solver, 6000, F32)
    assert pos[:, 1].min() == pytest.approx(0.0, abs=0.01)
    assert pos[:, 1].min() >= 0.0


@pytest.mark.parametrize(
    "text, message",
    [
        ("[[cone]]\napex = [0, 0, 0]\n", "unknown table or key 'cone'"),
        ("[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.0\n", "sphere radius must be > 0"),
        ("[[cylinder]]\nstart = [0, 0, 0]\nend = [0, 0, 0]\nradius = 0.1\n", "zero-length cylinder"),
        ("[[cylinder]]\nstart = [0, 0, 0]\nend = [1, 0, 0]\nradius = -1\n", "cylinder radius must be > 0"),
        ("[[plane]]\npoint = [0, 0, 0]\nnormal = [0, 0, 0]\n", "plane normal must not be zero"),
        ("[[plane]]\npoint = [0, 0, 0]\n", "missing: 'normal'"),
    ],
)
def test_bad_colliders_are_refused(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))


def test_colliders_apply_spheres_then_cylinders_then_planes():
    s = Scene(
        planes=(Plane((0, 0, 0), (0, 1, 0)),),
        cylinders=(Cylinder((0, 0, 0), (1, 0, 0), 0.1),),
        spheres=(Sphere((0, 0, 0), 0.5),),
    )
    assert [c.kind for c in s.colliders] == ["sphere", "cylinder", "plane"]
