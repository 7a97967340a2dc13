"""The box collider's contract, on every backend of the registry that declares it takes boxes
(Capabilities.boxes): strict mode is the NumPy float32 reference bit for bit on a scene of two
oriented boxes, a fixed rotated one and a moving one (tests/data/boxes.toml; with its motion
stopped on a backend that takes no moving colliders), over enough steps that the sheet
reaches both. A backend that does not declare boxes refuses the scene
(tests/test_box_collider.py)."""

from __future__ import annotations


import numpy as np
import pytest

from clothbench.backends import BACKENDS, backend_class, create_backend
from clothbench.backends.numpy import verlet as numpy_verlet
from clothbench.harness import reference, simulate
from clothbench.harness.plan import without_motion
from clothbench.model.scene import load_setup
from clothbench.model.solver import Pbd, Vbd

from conftest import BOX_SCENE, BOX_STEPS, assert_bit_exact
from registry_variants import options, usable

# BOX_STEPS, the scene's steps: the sheet reaches both boxes, moving or stopped, well within
# them (numpy float32: by step 291; test_the_sheet_reaches_both_boxes_within_the_steps_compared
# holds it)
PBD = Pbd(dt=5e-4, iterations=4, substeps=2)
VBD = Vbd(dt=5e-4, iterations=4, substeps=2)


def box_params(solver: str) -> list:
    """pytest params (backend, generic): each backend that declares boxes for `solver`, once
    per kernel build it has; an unusable one skips with the registry's reason."""
    params = []
    for name, entry in BACKENDS.items():
        if solver not in entry.solvers():
            continue
        try:
            caps = backend_class(name, solver).capabilities
        except Exception:  # its module cannot load here: it declares nothing here
            continue
        if solver not in caps.boxes:
            continue
        for generic in (False, True) if caps.generic else (False,):
            params.append(pytest.param((name, generic), id=f"{name}{'-generic' if generic else ''}-{solver}"))
    return params


def box_setup():
    return load_setup(str(BOX_SCENE))


def box_scene(name: str, solver: str = "verlet"):
    """The box scene as `name` takes it: moving, or with every motion stopped."""
    scene = box_setup().scene
    return scene if solver in backend_class(name, solver).capabilities.moving_colliders else without_motion(scene)


@pytest.mark.parametrize("param", box_params("verlet"))
def test_strict_boxes_match_numpy_f32_bit_for_bit(param):
    name, generic = usable(param)
    scene = box_scene(name)
    pos, prev = simulate(name, scene, box_setup().solver, BOX_STEPS, options(name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, box_setup().solver, BOX_STEPS, "f32")
    what = f"{name} generic={generic} boxes moving={scene.has_motion} n={scene.grid} steps={BOX_STEPS}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")


@pytest.mark.parametrize("param", box_params("verlet"))
def test_strict_float64_boxes_match_numpy_f64_bit_for_bit(param):
    """The float64 reference of a box scene is stepped by whichever backend takes it in strict
    float64 (harness.reference: c where it runs), so that one must be NumPy's float64 too."""
    name, generic = usable(param)
    if "f64" not in backend_class(name).capabilities.precisions:
        pytest.skip(f"{name} has no float64")
    scene = box_scene(name)
    pos, prev = simulate(name, scene, box_setup().solver, BOX_STEPS, options(name, strict=True, precision="f64"))
    ref_pos, ref_prev = simulate("numpy", scene, box_setup().solver, BOX_STEPS, options("numpy", precision="f64"))
    assert_bit_exact(pos, ref_pos, f"pos, {name} f64 boxes steps={BOX_STEPS}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} f64 boxes steps={BOX_STEPS}")


# NumPy's own rows (its strict run against its plain one: 10 s for VBD, most of the quick
# tier's box time) in --full; the quick tier holds NumPy's strict to its reference on the
# Verlet boxes, and every other backend's PBD and VBD boxes to NumPy's here
@pytest.mark.parametrize(
    "param, solver",
    [
        pytest.param(p.values[0], s, id=p.id, marks=pytest.mark.full if p.values[0][0] == "numpy" else ())
        for s in (PBD, VBD)
        for p in box_params(s.name)
    ],
)
def test_strict_pbd_and_vbd_boxes_match_numpy_f32_bit_for_bit(param, solver):
    name, generic = usable(param)
    scene = box_scene(name, solver.name)
    pos, prev = simulate(name, scene, solver, BOX_STEPS, options(name, solver.name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, solver, BOX_STEPS, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, {name} {solver.name} boxes steps={BOX_STEPS}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} {solver.name} boxes steps={BOX_STEPS}")


@pytest.mark.parametrize("moving", [True, False], ids=["moving", "stopped"])
# Verlet's in the quick tier; PBD's and VBD's (NumPy's iterations over the scene's steps: the quick
# tier's slowest) in --full, where they hold the strict PBD and VBD cases to contact as well
@pytest.mark.parametrize(
    "solver",
    [box_setup().solver, pytest.param(PBD, marks=pytest.mark.full), pytest.param(VBD, marks=pytest.mark.full)],
    ids=["verlet", "pbd", "vbd"],
)
def test_the_sheet_reaches_both_boxes_within_the_steps_compared(monkeypatch, solver, moving):
    """Without contact the strict comparison would prove nothing about the box's response:
    both boxes must push some particle in the reference run that is compared against."""
    pushed: dict[float, int] = {}
    response = numpy_verlet.COLLIDE["box"]

    def counting(x, free, **box):
        before = x.copy()
        response(x, free, **box)
        pushed[float(box["h0"])] = pushed.get(float(box["h0"]), 0) + int((before != x).any(axis=0).sum())

    monkeypatch.setitem(numpy_verlet.COLLIDE, "box", counting)
    scene = box_setup().scene if moving else without_motion(box_setup().scene)
    with create_backend("numpy", scene, solver) as b:
        b.upload(*b.initial_state())
        b.advance(BOX_STEPS)
        pos, _ = b.read()
    assert np.isfinite(pos).all()
    halves = {float(np.float32(box.half_extents[0])) for box in scene.boxes}
    assert set(pushed) == halves, "every box is applied every step"
    assert all(pushed[h] > 0 for h in halves), f"a box pushed no particle in {BOX_STEPS} steps: {pushed}"
