"""Several pinned sets, [[pins]], each following its own body (docs/scenes.md): what twist and
pile need. One [pins] table reads as before; each set's particles follow their own body
exactly; a set without a body stays; a particle in two sets is refused in one line."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.model.kernel_inputs import pin_targets
from clothbench.model.colliders.analytic import body_pose
from clothbench.errors import SceneError
from clothbench.harness import reference
from clothbench.harness.plan import without_motion
from clothbench.model.scene import load_setup, setup_from_dict

from conftest import VERLET, assert_bit_exact

FRAMES = [
    {"name": "left", "origin": [0.0, 1.0, 0.5], "motion": {"angular_velocity": [90.0, 0.0, 0.0]}},
    {"name": "right", "origin": [1.0, 1.0, 0.5], "motion": {"velocity": [0.1, 0.0, 0.0]}},
]


def two_sets(third: dict | None = None) -> dict:
    pins = [{"edge": "left", "attach": "left"}, {"edge": "right", "attach": "right"}]
    return {"cloth": {"grid": 8}, "frame": FRAMES, "pins": pins + ([third] if third else [])}


def test_each_set_follows_its_own_body_and_a_set_without_one_stays():
    scene = setup_from_dict(two_sets({"corners": []})).scene
    fixed = setup_from_dict(two_sets({"indices": [27]})).scene
    assert fixed.pin_attach == "left"  # the gate: some set follows a body
    n = fixed.grid
    pinned = fixed.pinned()
    x0 = fixed.initial_state(np.float64)[0][:, :3]
    targets = pin_targets(fixed, 1.0, np.float64)
    for edge, body in (("left", "left"), ("right", "right")):
        particles = np.arange(0, n * n, n) if edge == "left" else np.arange(n - 1, n * n, n)
        rot, trans = body_pose(fixed.body(body), 1.0)
        rot0, trans0 = body_pose(fixed.body(body), 0.0)
        expected = (x0[particles] - trans0) @ rot0 @ rot.T + trans
        np.testing.assert_allclose(targets[np.searchsorted(pinned, particles)], expected, atol=1e-12)
    assert_bit_exact(targets[np.searchsorted(pinned, [27])], x0[[27]], "the set without a body")
    assert len(scene.pinned()) == 2 * n


def test_a_turning_edge_moves_the_cloth_and_motion_off_stops_every_set():
    scene = setup_from_dict(two_sets()).scene
    moved = reference(scene, VERLET, 20, "f32")[0]
    still = reference(without_motion(scene), VERLET, 20, "f32")[0]
    left = np.arange(0, scene.particles, scene.grid)
    assert not np.array_equal(moved[left], still[left])
    assert_bit_exact(still[left, :3], scene.initial_state(np.float32)[0][left, :3], "stopped pins stay")


def test_one_pins_table_reads_as_before():
    setup = load_setup("carried")
    assert setup.scene.pin_groups == () and setup.scene.pin_attach == "bar"


@pytest.mark.parametrize(
    "third, words",
    [
        ({"corners": ["top-left"]}, "particle 0 is pinned by two [[pins]] tables"),
        ({"edge": "middle"}, "unknown pin edge 'middle'"),
        ({"indices": [27], "attach": "nobody"}, "pins attach to 'nobody'"),
        ({"edges": "top"}, "unknown key 'edges'"),
    ],
)
def test_a_wrong_pins_array_is_refused_in_one_line(third, words):
    with pytest.raises(SceneError) as e:
        setup_from_dict(two_sets(third), "s.toml")
    assert words in str(e.value) and "\n" not in str(e.value)
