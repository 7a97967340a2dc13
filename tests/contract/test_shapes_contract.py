"""The kernel-shape contract (backends/tuning.py), on every backend that declares shapes: each
shape it offers for a scene is the NumPy float32 reference bit for bit in strict mode, so
that whichever shape the tuning picks on a machine, a strict result is the same; the mode
names the shape that ran; a shape it does not have is refused in one line."""

from __future__ import annotations

import pytest

from clothbench.backends import BACKENDS, backend_class, create_backend
from clothbench.errors import ClothbenchError
from clothbench.harness import reference, simulate
from clothbench.model.scene import load_scene

from conftest import VERLET, assert_bit_exact
from registry_variants import options, usable


def shaped_params() -> list:
    params = []
    for name, entry in BACKENDS.items():
        for solver in entry.solvers():
            if backend_class(name, solver).capabilities.shapes:
                params.append(pytest.param((name, solver), id=f"{name}-{solver}"))
    return params


@pytest.mark.parametrize("steps", [1, 500])
@pytest.mark.parametrize("grid", [32, 64])
@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
@pytest.mark.parametrize("param", shaped_params())
def test_every_shape_is_bit_exact_in_strict_mode(param, scene_name, grid, steps):
    name, solver_name = usable(param)
    if solver_name != "verlet":
        pytest.skip("the PBD contract holds its own shapes to NumPy (tests/contract/test_pbd_contract.py)")
    scene = load_scene(scene_name).replace(grid=grid)
    cls = backend_class(name)
    shapes = cls.kernel_shapes(scene, options(name, strict=True))
    assert shapes, f"{name} declares shapes but offers none for {scene_name} n={grid}"
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    for shape in shapes:
        pos, prev = simulate(name, scene, VERLET, steps, options(name, strict=True, shape=shape))
        what = f"{name} shape {shape} {scene_name} n={grid} steps={steps}"
        assert_bit_exact(pos, ref_pos, f"pos, {what}")
        assert_bit_exact(prev, ref_prev, f"prev, {what}")


@pytest.mark.parametrize("param", shaped_params())
def test_the_mode_names_the_shape_and_an_unknown_shape_is_refused(param):
    name, solver_name = usable(param)
    if solver_name != "verlet":
        pytest.skip("Verlet only here")
    scene = load_scene("sphere").replace(grid=32)
    shapes = backend_class(name).kernel_shapes(scene, options(name))
    with create_backend(name, scene, VERLET, options(name, shape=shapes[-1])) as b:
        assert shapes[-1] in b.mode, b.mode
    with pytest.raises(ClothbenchError) as e:
        create_backend(name, scene, VERLET, options(name, shape="no-such-shape"))
    message = str(e.value)
    assert "\n" not in message and "no-such-shape" in message and shapes[0] in message
