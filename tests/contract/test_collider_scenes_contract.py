"""Strict mode on the collider scenes after contact, on every backend of the registry: each
case's sheet has reached the colliders it names by the step it is read at, and there every
strict build is the NumPy float32 reference bit for bit, with no particle inside a collider.
The cases are those the per-backend files ran each on their own backend (the GL backends'
1500 steps at n = 32 and all kinds at n = 24, CUDA's every-kind and curtain, the peers' tilted
cylinder at n = 24)."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.harness import reference, simulate
from clothbench.harness.health import max_penetration
from clothbench.scene import load_scene

from conftest import (
    VERLET,
    assert_bit_exact,
    every_collider_scene,
    every_kind,
    three_kinds_scene,
    tilted_cylinder_scene,
)
from registry_variants import backend_params, options, usable

# float32 rounding leaves a pushed-out particle up to a few ulp inside: measured 6e-8 m
PENETRATION_TOLERANCE = 1e-6
FULL = pytest.mark.full

# name: (scene, steps, the colliders it touches by then, tier). The quick tier reads the curtain
# on its sphere and the tilted cylinder and floor (all three kinds, at 600 steps) and the
# all-kinds sheet after 150 steps (on a cylinder only, by then). The built-in
# cylinder's sheet reaches its floor only after seconds, so there only the cylinder counts.
CASES = {
    "curtain-600": (lambda: load_scene("curtain").replace(grid=32), 600, ("spheres",), ()),
    "tilted-24-600": (lambda: tilted_cylinder_scene(24), 600, ("cylinders", "planes"), ()),
    "cylinder-24-600": (lambda: load_scene("cylinder").replace(grid=24), 600, ("cylinders",), FULL),
    "every-kind-300": (lambda: every_kind(32), 300, ("spheres", "cylinders", "planes"), FULL),
    "cylinder-1500": (lambda: load_scene("cylinder").replace(grid=32), 1500, ("cylinders",), FULL),
    "curtain-1500": (lambda: load_scene("curtain").replace(grid=32), 1500, ("spheres",), FULL),
    "three-kinds-1500": (lambda: three_kinds_scene(32), 1500, ("spheres", "cylinders", "planes"), FULL),
    "all-kinds-24-150": (lambda: every_collider_scene(24), 150, ("cylinders",), ()),
}


def case_params() -> list:
    return [pytest.param(name, marks=CASES[name][3], id=name) for name in CASES]


@pytest.mark.parametrize("case", case_params())
def test_each_case_reaches_its_colliders(case):
    # not vacuous: without each collider it names, the reference ends elsewhere
    make, steps, kinds, _ = CASES[case]
    scene = make()
    want = reference(scene, VERLET, steps, "f32")[0]
    for kind in kinds:
        other = reference(scene.replace(**{kind: ()}), VERLET, steps, "f32")[0]
        assert not np.array_equal(want, other), f"{case}: the cloth never touches the {kind}"


@pytest.mark.parametrize("case", case_params())
@pytest.mark.parametrize("param", backend_params(builds=True))
def test_strict_is_numpys_bits_on_the_collider_scenes_after_contact(param, case):
    name, generic = usable(param)
    make, steps, _, _ = CASES[case]
    scene = make()
    pos, prev = simulate(name, scene, VERLET, steps, options(name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    what = f"{name} generic={generic} {case}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")
    assert max_penetration(pos, scene) < PENETRATION_TOLERANCE, f"{what}: a particle ends inside a collider"
