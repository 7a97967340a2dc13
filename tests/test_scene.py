"""The scene: spring counts as the chapter counts them, validation, built-in scenes."""

import numpy as np
import pytest

from clothbench.errors import SceneError
from clothbench.scene import Scene, Sphere, builtin_scenes, count_springs, load_scene


def test_spring_counts_match_the_chapter():
    # the chapter: 11,412 springs at 32x32 and "approximately 780,000" at 256x256
    assert count_springs(32) == 11_412
    assert count_springs(256) == 779_284


def test_spring_count_equals_neighbours_inside_the_grid():
    # brute force over the stencil, so count_springs cannot drift from the step's skip rule
    from clothbench.scene import OFFSETS

    n = 7
    brute = sum(
        1
        for r in range(n)
        for c in range(n)
        for dr, dc in OFFSETS
        if 0 <= r + dr < n and 0 <= c + dc < n
    )
    assert count_springs(n) == brute


def test_initial_sheet_is_flat_at_rest_length():
    s = Scene(grid=5, size=2.0, height=0.7)
    pos, prev = s.initial_state()
    assert np.array_equal(pos, prev)
    assert np.all(pos[:, 1] == 0.7)
    assert pos[6, 0] == pytest.approx(0.5) and pos[6, 2] == pytest.approx(0.5)  # row 1, col 1
    assert np.all(pos[:, 3] == 1 / s.mass)


def test_pins_by_corner_edge_and_index_have_zero_inverse_mass():
    s = Scene(grid=4, pin_corners=("top-right", "bottom-left"), pin_indices=(5,), pin_edge="left")
    assert list(s.pinned()) == [0, 3, 4, 5, 8, 12]
    pos, _ = s.initial_state()
    assert np.array_equal(np.flatnonzero(pos[:, 3] == 0), s.pinned())


def test_builtin_scenes_load():
    assert {"sphere", "drape"} <= set(builtin_scenes())
    sphere = load_scene("sphere")
    assert sphere.spheres and sphere.spheres[0].radius > 0
    drape = load_scene("drape")
    assert list(drape.pinned()) == [0, drape.grid - 1]


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"grid": 2}, "grid must be an integer >= 3"),
        ({"steps": 0}, "steps must be an integer >= 1"),
        ({"dt": 0.0}, "dt must be > 0"),
        ({"dt": -1e-3}, "dt must be > 0"),
        ({"dt": float("nan")}, "dt must be a finite number"),
        ({"mass": -1.0}, "mass must be > 0"),
        ({"stiffness": -5.0}, "stiffness must be >= 0"),
        ({"stiffness": float("nan")}, "stiffness must be a finite number"),
        ({"damping": -0.1}, "damping must be >= 0"),
        ({"pin_indices": (16,)}, "pin index 16 is outside the grid"),
        ({"pin_corners": ("middle",)}, "unknown pin corner"),
        ({"spheres": (Sphere((0, 0, 0), 0.0),)}, "sphere radius must be > 0"),
        ({"gravity": (0, float("inf"), 0)}, "gravity must be three finite numbers"),
        ({"start": "warm"}, "start must be one of"),
    ],
)
def test_bad_scene_values_are_refused(changes, message):
    with pytest.raises(SceneError, match=message):
        Scene(grid=4).replace(**changes)


@pytest.mark.parametrize(
    "text, message",
    [
        ("[cloth]\ngrid = 16\nstifness = 3\n", "unknown key 'stifness' in \\[cloth\\]"),
        ("[clothes]\ngrid = 16\n", "unknown table or key 'clothes'"),
        ("[cloth\ngrid = 16\n", "not valid TOML"),
        ("[[sphere]]\ncenter = [0, 0]\nradius = 1\n", "sphere center must be three finite numbers"),
        ("[[sphere]]\ncenter = [0, 0, 0]\n", "missing: 'radius'"),
        ("[pins]\nindices = [99999]\n", "pin index 99999 is outside the grid"),
        ("[sim]\ndt = 'fast'\n", "dt must be a finite number"),
    ],
)
def test_malformed_scene_files_are_refused(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))


def test_unknown_scene_name_lists_the_builtins():
    with pytest.raises(SceneError, match="built in: .*sphere"):
        load_scene("spheer")


def test_values_float32_cannot_hold_are_refused():
    with pytest.raises(SceneError, match="sphere radius 1e\\+39 is too large for float32"):
        Scene(spheres=(Sphere((0, 0, 0), 1e39),))
