"""Moving colliders and pins attached to a body (docs/semantics.md, "Moving colliders" and
"Pins attached to a body"): poses per step in float64 rounded once, the motion carrying the
cloth, pins following a body exactly, keyframes and refusals. The built-in scenes that move
(the carried sheet's pins on the bar, the paddle leaving no particle inside) are checked on
every backend that takes them by tests/contract/test_bodies_contract.py."""

import numpy as np
import pytest

pytest.importorskip("trimesh", reason="the built-in mesh scenes load with trimesh (pip install trimesh)")

from clothbench.backends import BackendOptions
from clothbench.backends.kernel_inputs import collider_rows
from clothbench.colliders.motion import Frame, Motion
from clothbench.errors import SceneError
from clothbench.harness import simulate
from clothbench.scene import Plane, Scene, Sphere, load_scene
from clothbench.solver import Verlet

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
