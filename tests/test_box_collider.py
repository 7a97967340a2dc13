"""The oriented box collider (docs/semantics.md, "Box"): the NumPy reference is the
specification operation for operation, its scene-file table refuses bad input in one line,
its kernel rows are its pose, and every backend that does not take boxes refuses a box scene
in one line before any work. The table of kinds (colliders/kinds.py) is what every reader
of a kind reads."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from clothbench.backends import BACKENDS, BackendOptions, backend_class, create_backend
from clothbench.model.kernel_inputs import ROWS_PER_COLLIDER, collider_rows
from clothbench.backends.numpy.verlet import ARGUMENTS, COLLIDE, collide_box
from clothbench.cli import main
from clothbench.model.colliders.analytic import COLLIDER_OPTIONAL_KEYS
from clothbench.model.colliders.kinds import KINDS
from clothbench.model.colliders.motion import Motion, euler_degrees
from clothbench.errors import ClothbenchError, SceneError
from clothbench.harness import max_penetration
from clothbench.harness.bounds import step_count
from clothbench.model.scene import Box, Scene, load_scene, load_setup
from clothbench.model.solver import Pbd, Vbd

from conftest import BOX_SCENE, VERLET, every_collider_scene

f32 = np.float32


def spec_box(x, c, axes, half):
    """docs/semantics.md, "Box", one particle at a time in float32 scalars: the spec's lines."""

    def dot3(a, b):
        return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]

    d = [x[i] - c[i] for i in range(3)]
    ell = [dot3(d, axes[k]) for k in range(3)]
    p = [half[k] - abs(ell[k]) for k in range(3)]
    if not (p[0] > 0 and p[1] > 0 and p[2] > 0):
        return list(x)
    k = 0
    if p[1] < p[k]:
        k = 1
    if p[2] < p[k]:
        k = 2
    s = half[k] if ell[k] >= 0 else -half[k]
    return [x[i] + axes[k][i] * (s - ell[k]) for i in range(3)]


def reference_box(points, box: Box, free=None):
    """points (P, 3) float32 through the NumPy reference's collide_box, as the step calls it."""
    rows = collider_rows(Scene(boxes=(box,)), np.float32)["boxes"]
    x = np.ascontiguousarray(points.T.reshape(3, 1, -1))
    free = np.ones((1, len(points)), bool) if free is None else free.reshape(1, -1)
    collide_box(x, free, **ARGUMENTS["box"](*rows))
    return x.reshape(3, -1).T, rows


UNROTATED = Box(center=(0.5, 0.5, 0.5), half_extents=(0.1, 0.2, 0.3))


@pytest.mark.parametrize(
    "point, moved_to",
    [
        ((0.59, 0.5, 0.5), (0.6, 0.5, 0.5)),  # near the +x face: out through it
        ((0.41, 0.5, 0.5), (0.4, 0.5, 0.5)),  # near the -x face
        ((0.5, 0.32, 0.5), (0.5, 0.3, 0.5)),  # near the -y face
        ((0.5, 0.5, 0.79), (0.5, 0.5, 0.8)),  # near the +z face
        ((0.5, 0.5, 0.5), (0.6, 0.5, 0.5)),  # the centre: least depth on axis 0, its + face (l = 0)
        ((0.65, 0.5, 0.5), (0.65, 0.5, 0.5)),  # outside: not moved
        ((0.6, 0.5, 0.5), (0.6, 0.5, 0.5)),  # on a face: not strictly inside, not moved
    ],
)
def test_a_particle_inside_leaves_through_the_face_of_least_penetration(point, moved_to):
    out, _ = reference_box(np.array([point], np.float32), UNROTATED)
    # within float32's rounding of the face's coordinate: (h - l) is rounded, then added
    np.testing.assert_allclose(out[0], moved_to, atol=2e-7, rtol=0)


def test_ties_go_to_the_lower_axis_and_l_zero_to_the_plus_face():
    cube = Box(center=(0.0, 0.0, 0.0), half_extents=(0.25, 0.25, 0.25))
    out, _ = reference_box(np.zeros((1, 3), np.float32), cube)
    assert out[0].tolist() == [0.25, 0.0, 0.0]


def test_the_reference_is_the_spec_bit_for_bit_on_a_rotated_box():
    box = Box(center=(0.2, -0.1, 0.4), half_extents=(0.3, 0.15, 0.2), rotation=(25.0, -40.0, 70.0))
    rng = np.random.default_rng(28)
    points = (np.array(box.center) + rng.uniform(-0.45, 0.45, (4000, 3))).astype(np.float32)
    out, rows = reference_box(points, box)
    c, axes, half = rows[0, :3], [rows[k, :3] for k in (1, 2, 3)], [rows[k, 3] for k in (1, 2, 3)]
    expected = np.array([spec_box(p, c, axes, half) for p in points], np.float32)
    assert np.array_equal(out.view(np.uint32), expected.view(np.uint32)), "not the spec's float32 operations"
    moved = (out != points).any(axis=1)
    assert 100 < moved.sum() < len(points), "the sample must hold points inside and outside"
    # each moved point lies on a face: one local coordinate at its half extent (float32 rounding)
    local = np.abs((out[moved].astype(np.float64) - box.center) @ euler_degrees(box.rotation))
    assert np.abs(local - np.array(box.half_extents)).min(axis=1).max() < 1e-6


def test_pinned_particles_are_not_moved_by_a_box():
    out, _ = reference_box(np.array([[0.59, 0.5, 0.5]], np.float32), UNROTATED, free=np.array([False]))
    assert out[0].tolist() == np.array([0.59, 0.5, 0.5], np.float32).tolist()


def test_box_rows_are_its_pose_rounded_once():
    box = Box(center=(0.1, 0.2, 0.3), half_extents=(0.4, 0.5, 0.6), rotation=(10.0, 20.0, 30.0))
    rows = collider_rows(Scene(boxes=(box,)), np.float32)["boxes"]
    rot = euler_degrees(box.rotation)
    expected = [(*box.center, 0.0)] + [(*rot[:, i], box.half_extents[i]) for i in range(3)]
    assert np.array_equal(rows, np.array(expected, np.float64).astype(np.float32))
    plain = collider_rows(Scene(boxes=(dataclasses.replace(box, rotation=(0.0, 0.0, 0.0)),)))["boxes"]
    assert np.array_equal(plain[1:, :3], np.eye(3, dtype=np.float32)), "no rotation is the identity exactly"
    moving = dataclasses.replace(box, motion=Motion(velocity=(1.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 90.0)))
    rot_t, center_t = moving.pose_at(0.5)
    rows_t = collider_rows(Scene(boxes=(moving,)), np.float32, 0.5)["boxes"]
    assert np.array_equal(rows_t[0, :3], center_t.astype(np.float32)) and center_t[0] == 0.6
    assert np.array_equal(rows_t[1:, :3], rot_t.T.astype(np.float32))  # row i: column i of R(t)


# --- the scene file -----------------------------------------------------------------------


def test_the_box_scene_reads_its_boxes():
    scene = load_scene(str(BOX_SCENE))
    tilted, rising = scene.boxes
    assert tilted == Box((0.3, 0.55, 0.4), (0.15, 0.12, 0.2), (25.0, 35.0, 10.0), name="tilted")
    assert rising.motion == Motion(velocity=(0.0, 0.2, 0.0), angular_velocity=(0.0, 90.0, 30.0))
    assert rising.rotation == (0.0, 0.0, 0.0)
    assert [c.kind for c in scene.colliders] == ["sphere", "box", "box", "plane"], "boxes before planes"


@pytest.mark.parametrize(
    "box, message",
    [
        ("center = [0, 0.5, 0]\n", "\\[\\[box\\]\\] needs center, half_extents .*missing: 'half_extents'"),
        ("half_extents = [1, 1, 1]\n", "missing: 'center'"),
        ("center = [0, 0.5, 0]\nhalf_extents = [1, 1, 1]\nsize = 2\n", "unknown: 'size'"),
        ("center = [0, 0.5, 0]\nhalf_extents = [0.1, 0, 0.1]\n", "box half_extents must be > 0"),
        ("center = [0, 0.5, 0]\nhalf_extents = [0.1, -1, 0.1]\n", "box half_extents must be > 0"),
        ("center = [0, nan, 0]\nhalf_extents = [1, 1, 1]\n", "box center must be three finite numbers"),
        ("center = [0, 0.5, 0]\nhalf_extents = [1, inf, 1]\n", "box half_extents must be three finite numbers"),
        ("center = [0, 0.5, 0]\nhalf_extents = [1, 1, 1]\nrotation = [0, 90]\n", "box rotation must be three"),
        ("center = [0, 0.5, 0]\nhalf_extents = [1, 1, 1]\nmotion = 3\n", "motion must be a table"),
    ],
)
def test_a_bad_box_table_is_refused_in_one_line(tmp_path, capsys, box, message):
    path = tmp_path / "box.toml"
    path.write_text(f"[[box]]\n{box}")
    with pytest.raises(SceneError, match=message):
        load_scene(str(path))
    assert main(["run", "--backend", "numpy", "--scene", str(path), "--grid", "4", "--steps", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


# --- who takes boxes ----------------------------------------------------------------------


def every_backend_and_solver():
    return [(name, solver) for name, entry in BACKENDS.items() for solver in entry.solvers()]


def declares_boxes(name: str, solver: str) -> bool | None:
    """Whether the backend's class declares boxes for `solver`; None where it cannot load here."""
    try:
        return solver in backend_class(name, solver).capabilities.boxes
    except Exception:
        return None


@pytest.mark.parametrize("name, solver", every_backend_and_solver())
def test_a_backend_without_boxes_refuses_a_box_scene_in_one_line_before_any_work(name, solver):
    declared = declares_boxes(name, solver)
    if declared is None:
        pytest.skip(f"{name} {solver}: its module does not load here")
    if declared:
        pytest.skip(f"{name} {solver} takes boxes (tests/contract/test_box_contract.py runs it)")
    setup = load_setup(str(BOX_SCENE))
    takers = [n for n, s in every_backend_and_solver() if s == solver and declares_boxes(n, s)]
    who = name if solver == "verlet" else f"{name} {solver}"
    expected = f"{who} does not take box colliders (they run on: {', '.join(takers)})"
    cls = backend_class(name, solver)
    assert cls.capabilities.scene_refusal(name, setup.scene, solver) == expected
    settings = {"verlet": VERLET, "pbd": Pbd(), "vbd": Vbd()}[solver]
    with pytest.raises(ClothbenchError) as e:
        cls(setup.scene, settings, cls.capabilities.adapt(BackendOptions()))  # refused before it builds
    assert str(e.value) == expected


def test_numpy_takes_boxes_with_both_solvers():
    assert declares_boxes("numpy", "verlet") and declares_boxes("numpy", "pbd")
    scene = load_scene(str(BOX_SCENE))
    with create_backend("numpy", scene, Pbd()) as b:
        b.upload(*b.initial_state())
        b.advance(1)


# --- the table of kinds -------------------------------------------------------------------


def test_the_scene_holds_one_field_per_kind_in_the_steps_order():
    fields = [f.name for f in dataclasses.fields(Scene)]
    plurals = [k.plural for k in KINDS]
    assert [f for f in fields if f in plurals] == plurals
    assert list(collider_rows(Scene())) == plurals and list(ROWS_PER_COLLIDER) == plurals
    assert [k.name for k in KINDS][-1] == "plane", "a floor plane acts after every other kind"


@pytest.mark.parametrize("kind", KINDS, ids=lambda k: k.name)
def test_a_kinds_table_keys_rows_and_reference_agree_with_its_dataclass(kind):
    own = {f.name for f in dataclasses.fields(kind.type)} - set(COLLIDER_OPTIONAL_KEYS)
    assert kind.type.kind == kind.name
    assert set(kind.keys) | set(kind.optional) == own, "every field is a key of its table"
    scene = every_collider_scene(8).replace(boxes=load_scene(str(BOX_SCENE)).boxes)
    colliders = getattr(scene, kind.plural)
    assert colliders and len(collider_rows(scene)[kind.plural]) == kind.rows * len(colliders)
    assert COLLIDE[kind.name].__name__ == kind.function("numpy")


def test_a_particle_inside_a_box_is_its_depth_of_penetration():
    box = Box(center=(0.5, 0.5, 0.5), half_extents=(0.1, 0.2, 0.3), rotation=(0.0, 0.0, 90.0))
    # rotated 90 degrees about z: its axis 0 is world y, so the least depth of (0.5, 0.55, 0.5) is 0.05
    pos = np.array([[0.5, 0.55, 0.5, 1.0], [0.9, 0.9, 0.9, 1.0]])
    assert max_penetration(pos, Scene(boxes=(box,))) == pytest.approx(0.05, abs=1e-12)
    assert max_penetration(pos[1:], Scene(boxes=(box,))) == 0.0


def test_a_box_counts_its_operations_per_particle():
    scene = Scene(grid=8)
    with_box = scene.replace(boxes=(UNROTATED,))
    for strict, fp in ((True, 28), (False, 19)):  # docs/bounds.md, "per particle and box"
        extra = step_count(with_box, strict=strict).fp - step_count(scene, strict=strict).fp
        assert extra == fp * scene.particles
