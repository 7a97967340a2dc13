"""Moving colliders and pins attached to a body (docs/semantics.md, "Moving colliders" and
"Pins attached to a body"): poses per step in float64 rounded once, the motion carrying the
cloth, pins following a body exactly, keyframes, refusals, and the built-in scenes that move."""

import numpy as np
import pytest

pytest.importorskip("trimesh", reason="the built-in mesh scenes load with trimesh (pip install trimesh)")

from clothbench.backends import BACKENDS, BackendOptions, backend_class
from clothbench.backends.kernel_inputs import collider_rows
from clothbench.colliders.motion import Frame, Motion
from clothbench.errors import SceneError
from clothbench.harness import simulate
from clothbench.scene import Plane, Scene, Sphere, load_scene, load_setup
from clothbench.solver import Verlet

F32 = BackendOptions(precision="f32")
DT = 5e-4
VERLET = Verlet(dt=DT)


def run(scene, steps, dtype="f32"):
    return simulate("numpy", scene, VERLET, steps, BackendOptions(precision=dtype))


def test_a_moving_colliders_rows_are_its_pose_at_the_end_of_the_step_rounded_once():
    s = Scene(grid=4, spheres=(Sphere((0.1, 0.2, 0.3), 0.2, motion=Motion(velocity=(0.3, 0.0, -0.7))),))
    t = 7 * DT
    expected = np.array([0.1 + 0.3 * t, 0.2, 0.3 - 0.7 * t, 0.2], dtype=np.float64).astype(np.float32)
    np.testing.assert_array_equal(collider_rows(s, np.float32, t)["spheres"][0], expected)


def test_a_motion_that_does_not_move_changes_no_bit():
    base = load_scene("sphere").replace(grid=16)
    still = base.replace(spheres=(Sphere((0.5, 0.5, 0.5), 0.3, motion=Motion()),))
    assert still.has_motion
    for a, b in zip(run(base, 300), run(still, 300)):
        np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))


def test_a_rising_floor_carries_the_cloth_with_it():
    # a floor moving up at 0.5 m/s under a sheet lying on it: every free particle ends on or
    # above the floor's final height, and the sheet has risen with it
    v, steps = 0.5, 400
    floor = Plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0), motion=Motion(velocity=(0.0, v, 0.0)))
    s = Scene(grid=16, height=0.0, planes=(floor,))
    pos, _ = run(s, steps)
    top = v * steps * DT
    assert pos[:, 1].min() >= np.float32(top) - 1e-6
    assert np.median(pos[:, 1]) == pytest.approx(top, abs=0.02)


def test_pins_attached_to_a_frame_follow_it_exactly():
    # translation only: the pinned particles are at x0 + v t, computed in float64, rounded once
    v = (0.2, -0.1, 0.05)
    s = Scene(grid=8, pin_edge="top", pin_attach="hand", frames=(Frame("hand", motion=Motion(velocity=v)),))
    steps = 123
    pos, prev = run(s, steps)
    x0 = s.initial_state(np.float64)[0][s.pinned(), :3]
    expected = (x0 + np.array(v) * (steps * DT)).astype(np.float32)
    np.testing.assert_array_equal(pos[s.pinned(), :3], expected)
    assert (pos[s.pinned(), 3] == 0).all()
    before = (x0 + np.array(v) * ((steps - 1) * DT)).astype(np.float32)
    np.testing.assert_array_equal(prev[s.pinned(), :3], before)


def test_pins_attached_to_a_rotating_collider_turn_with_it():
    # a sphere spinning at 90 degrees/s about y through its centre: after 1 s the pinned
    # corner has turned a quarter turn about that axis
    spin = Sphere((0.0, 2.0, 0.0), 0.01, name="spinner", motion=Motion(angular_velocity=(0.0, 90.0, 0.0)))
    s = Scene(grid=4, height=1.0, pin_corners=("bottom-right",), pin_attach="spinner", spheres=(spin,))
    pos, _ = run(s, 2000, "f64")
    # (1, 1, 1) relative to (0, 2, 0) is (1, -1, 1); a quarter turn about +y takes (x, z) to (z, -x)
    np.testing.assert_allclose(pos[s.pinned()[0], :3], (1.0, 1.0, -1.0), atol=1e-12)


def test_keyframes_interpolate_linearly_and_hold_outside():
    m = Motion(keyframes=((1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), (3.0, (2.0, 0.0, -4.0), (0.0, 90.0, 0.0))))
    rot, d = m.offset(2.0)
    np.testing.assert_allclose(d, (1.0, 0.0, -2.0))
    np.testing.assert_allclose(rot @ (1.0, 0.0, 0.0), (np.cos(np.pi / 4), 0.0, -np.sin(np.pi / 4)), atol=1e-15)
    np.testing.assert_array_equal(m.offset(0.0)[1], (0.0, 0.0, 0.0))
    np.testing.assert_array_equal(m.offset(9.0)[1], (2.0, 0.0, -4.0))


@pytest.mark.parametrize(
    "text, message",
    [
        ('[pins]\nedge = "top"\nattach = "ghost"\n', "pins attach to 'ghost', which names no collider or frame"),
        (
            '[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nname = "b"\n[pins]\nattach = "b"\n',
            "attach needs pinned particles",
        ),
        (
            "[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nmotion = { keyframes = [[1.0, [0, 0, 0], [0, 0, 0]], [0.5, [0, 0, 0], [0, 0, 0]]] }\n",
            "keyframe times must increase",
        ),
        (
            "[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nmotion = { velocity = [1, 0, 0], keyframes = [] }\n",
            "not both",
        ),
        ("[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nmotion = { speed = 2 }\n", "unknown key 'speed'"),
        (
            "[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nmotion = { velocity = [nan, 0, 0] }\n",
            "must be three finite numbers",
        ),
        (
            '[[sphere]]\ncenter = [0, 0, 0]\nradius = 0.1\nname = "a"\n[[frame]]\nname = "a"\n',
            "name 'a' is used more than once",
        ),
        ("[[frame]]\norigin = [0, 0, 0]\n", "\\[\\[frame\\]\\] needs a name"),
    ],
)
def test_bad_motion_and_attachments_are_refused(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))


def test_backends_without_motion_refuse_in_one_line():
    scene = load_scene("carried")
    refusal = backend_class("c").capabilities.scene_refusal("c", scene)
    takers = [n for n, e in BACKENDS.items() if e.verlet and "verlet" in backend_class(n).capabilities.moving_colliders]
    assert "numpy" in takers and "c" not in takers
    verb = "does" if len(takers) == 1 else "do"
    assert (
        refusal
        == f"c does not take moving colliders yet (it takes: fixed colliders and fixed pins; {', '.join(takers)} {verb})"
    )
    pinned = Scene(grid=4, pin_edge="top", pin_attach="f", frames=(Frame("f"),))
    assert "pins attached to a body" in backend_class("c").capabilities.scene_refusal("c", pinned)


# --- the built-in scenes that move ---------------------------------------------------------


def test_the_carried_sheets_pinned_edge_moves_with_the_bar():
    setup = load_setup("carried").replace(grid=16)
    s = setup.scene
    steps = 1000  # 0.5 s: a quarter of the bar's 0.6 m keyframed travel
    pos, _ = simulate("numpy", s, setup.solver, steps, F32)
    x0 = s.initial_state(np.float64)[0][s.pinned(), :3]
    expected = (x0 + (0.0, 0.0, 0.6 * steps * DT / 2.0)).astype(np.float32)
    np.testing.assert_array_equal(pos[s.pinned(), :3], expected)
    assert np.isfinite(pos).all()


def test_the_rotating_paddle_pushes_the_curtain_and_leaves_no_particle_inside():
    import trimesh

    from test_meshes import winding_number, world_mesh

    setup = load_setup("sweep").replace(grid=24)
    s = setup.scene
    steps = 1200  # 0.6 s: the curtain has swung down onto the paddle's path
    pos, _ = simulate("numpy", s, setup.solver, steps, F32)
    still = s.replace(meshes=())
    unswept, _ = simulate("numpy", still, setup.solver, steps, F32)
    assert np.abs(pos[:, :3] - unswept[:, :3]).max() > 0.05  # the paddle did push the curtain
    paddle = world_mesh(s.meshes[0], steps * DT)
    x = pos[:, :3].astype(np.float64)
    inside = winding_number(paddle, x) > 0.5
    _, dist, _ = trimesh.proximity.closest_point_naive(paddle, x)
    assert inside.sum() == 0 or dist[inside].max() <= 1e-5
