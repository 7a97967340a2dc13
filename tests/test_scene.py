"""The scene: spring counts as the chapter counts them, validation, built-in scenes, and
the scene file's solver settings (Setup)."""

import numpy as np
import pytest

from clothbench.errors import SceneError
from clothbench.model.scene import Scene, Setup, Sphere, builtin_scenes, count_springs, load_scene, load_setup
from clothbench.model.solver import Pbd, Verlet


def test_spring_counts_match_the_chapter():
    # the chapter: 11,412 springs at 32x32 and "approximately 780,000" at 256x256
    assert count_springs(32) == 11_412
    assert count_springs(256) == 779_284


def test_spring_count_equals_neighbours_inside_the_grid():
    # brute force over the stencil, so count_springs cannot drift from the step's skip rule
    from clothbench.model.scene import OFFSETS

    n = 7
    brute = sum(1 for r in range(n) for c in range(n) for dr, dc in OFFSETS if 0 <= r + dr < n and 0 <= c + dc < n)
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
        ({"mass": -1.0}, "mass must be > 0"),
        ({"stiffness": -5.0}, "stiffness must be >= 0"),
        ({"stiffness": float("nan")}, "stiffness must be a finite number"),
        ({"damping": -0.1}, "damping must be >= 0"),
        ({"pin_indices": (16,)}, "pin index 16 is outside the grid"),
        ({"pin_corners": ("middle",)}, "unknown pin corner"),
        ({"spheres": (Sphere((0, 0, 0), 0.0),)}, "sphere radius must be > 0"),
        ({"gravity": (0, float("inf"), 0)}, "gravity must be three finite numbers"),
    ],
)
def test_bad_scene_values_are_refused(changes, message):
    with pytest.raises(SceneError, match=message):
        Scene(grid=4).replace(**changes)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"dt": 0.0}, "dt must be > 0"),
        ({"dt": -1e-3}, "dt must be > 0"),
        ({"dt": float("nan")}, "dt must be a finite number"),
        ({"start": "warm"}, "start must be one of"),
    ],
)
@pytest.mark.parametrize("solver", [Verlet(), Pbd()], ids=["verlet", "pbd"])
def test_bad_solver_values_are_refused(solver, changes, message):
    with pytest.raises(SceneError, match=message):
        solver.replace(**changes)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"method": "newton"}, "pbd method must be one of jacobi, coloured"),
        ({"iterations": 0}, "iterations must be an integer >= 1"),
        ({"substeps": 1.5}, "substeps must be an integer >= 1"),
        ({"relaxation": 2.0}, "relaxation must be in \\(0, 2\\)"),
        ({"compliance": (1e-3, -1.0, 1e-3)}, "compliance must be >= 0"),
    ],
)
def test_bad_pbd_values_are_refused(changes, message):
    with pytest.raises(SceneError, match=message):
        Pbd().replace(**changes)


def test_bad_run_length_is_refused():
    with pytest.raises(SceneError, match="steps must be an integer >= 1"):
        Setup(Scene(grid=4), Verlet(), steps=0)


def test_pbd_without_stiffness_needs_a_compliance():
    with pytest.raises(SceneError, match="needs stiffness > 0 or an explicit \\[pbd\\] compliance"):
        Setup(Scene(grid=4, stiffness=0.0), Pbd())
    assert Setup(Scene(grid=4, stiffness=0.0), Pbd(compliance=(1e-3,) * 3)).solver.compliance == (1e-3,) * 3


def test_the_scene_is_the_model_only():
    # how it is stepped (solver.py) and for how long (a steps argument) are not the scene's
    scene = Scene()
    for moved in (
        "dt",
        "steps",
        "start",
        "solver",
        "pbd_method",
        "iterations",
        "substeps",
        "relaxation",
        "compliance",
        "pbd_compliance",
    ):
        assert not hasattr(scene, moved), moved


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
        ("[sim]\ndt = -1e-3\n", "dt must be > 0"),
        ("[sim]\nsteps = 0\n", "steps must be an integer >= 1"),
        ("[sim]\nsolver = 'fem'\n", "solver must be one of verlet, pbd"),
        ("[sim]\nstart = 'warm'\n", "start must be one of"),
        ("[sim]\nsubsteps = 2\n", "unknown key 'substeps' in \\[sim\\]"),
        ("[pbd]\niteration = 4\n", "unknown key 'iteration' in \\[pbd\\]"),
        ("[pbd]\niterations = 0\n", "iterations must be an integer >= 1"),
        ("[sim]\nsolver = 'pbd'\n[pbd]\nmethod = 'newton'\n", "pbd method must be one of"),
        ("[sim]\nsolver = 'verlet'\n[pbd]\nrelaxation = 3.0\n", "relaxation must be in"),
    ],
)
def test_malformed_scene_files_are_refused(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match=message) as err:
        load_setup(str(path))
    assert "\n" not in str(err.value), "a refusal is one line"
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))


def test_a_builtin_setup_is_its_scene_its_solver_and_its_length():
    run = load_setup("sphere")
    assert run.scene == load_scene("sphere")
    assert run.solver == Verlet(dt=5e-4, start="rest")
    assert run.steps == 300
    assert run.pbd == Pbd(dt=5e-4)  # no [pbd] table: the defaults, at the file's dt


def test_a_scene_file_names_its_solver(tmp_path):
    path = tmp_path / "pbd.toml"
    path.write_text(
        "[cloth]\ngrid = 8\n"
        "[sim]\ndt = 0.01\nsteps = 40\nstart = 'second-order'\nsolver = 'pbd'\n"
        "[pbd]\nmethod = 'coloured'\niterations = 4\nsubsteps = 2\nrelaxation = 1.2\n"
        "compliance = [1e-3, 2e-3, 3e-3]\n"
    )
    run = load_setup(str(path))
    want = Pbd(
        dt=0.01,
        start="second-order",
        method="coloured",
        iterations=4,
        substeps=2,
        relaxation=1.2,
        compliance=(1e-3, 2e-3, 3e-3),
    )
    assert run.solver == want and run.pbd == want
    assert run.steps == 40 and run.scene.grid == 8
    assert run.solver.spec == "pbd-coloured"
    # a Verlet file keeps its [pbd] table for commands that switch solver
    path.write_text(path.read_text().replace("solver = 'pbd'", "solver = 'verlet'"))
    run = load_setup(str(path))
    assert run.solver == Verlet(dt=0.01, start="second-order")
    assert run.pbd == want
    assert run.solver_for("pbd") == want
    assert run.solver_for("pbd-jacobi") == want.replace(method="jacobi")
    assert run.solver_for("verlet") == run.solver


def test_setup_replace_overrides_what_it_is_given():
    run = load_setup("curtain")
    assert run.replace() == run
    short = run.replace(grid=8, steps=10, dt=1e-3)
    assert short.scene == run.scene.replace(grid=8)
    assert (short.steps, short.solver) == (10, Verlet(dt=1e-3))
    pbd = short.replace(solver="pbd", method="coloured", iterations=3, substeps=2)
    assert pbd.solver == Pbd(dt=1e-3, method="coloured", iterations=3, substeps=2)
    assert (pbd.scene, pbd.steps) == (short.scene, 10)
    assert pbd.replace(iterations=5).solver == pbd.solver.replace(iterations=5)
    # back to Verlet and to PBD again: the PBD settings are kept meanwhile
    verlet = pbd.replace(solver="verlet")
    assert verlet.solver == Verlet(dt=1e-3)
    assert verlet.replace(solver="pbd").solver == pbd.solver
    with pytest.raises(SceneError, match="steps must be an integer >= 1"):
        run.replace(steps=0)
    with pytest.raises(SceneError, match="unknown solver 'fem'"):
        run.replace(solver="fem")


def test_unknown_scene_name_lists_the_builtins():
    with pytest.raises(SceneError, match="built in: .*sphere"):
        load_scene("spheer")


def test_values_float32_cannot_hold_are_refused():
    with pytest.raises(SceneError, match="sphere radius 1e\\+39 is too large for float32"):
        Scene(spheres=(Sphere((0, 0, 0), 1e39),))
