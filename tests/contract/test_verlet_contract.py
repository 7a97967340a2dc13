"""The backend contract for the Verlet step, checked on every backend of the registry.

Strict mode is the NumPy float32 reference bit for bit (docs/semantics.md: the same operations
in the same order, no contraction, no fast math); fast mode stays within float32's own error
of the float64 reference; work-group size and transfer mode change no bit; normals, where a
backend computes them, are the formula of docs/normals.md; options a backend lacks are
refused in one line before anything is built; a run's mode names its options.
"""

from __future__ import annotations

import numpy as np
import pytest

from clothbench.backends import BACKENDS, BackendOptions, backend_class, create_backend
from clothbench.errors import ClothbenchError
from clothbench.harness import position_error, reference, simulate
from clothbench.harness.normals import grid_normals
from clothbench.harness.plan import plan_variants
from clothbench.model.scene import builtin_scenes, load_scene

from conftest import VERLET, assert_bit_exact, bent_state, every_collider_scene
from registry_variants import backend_params, options, solver_params, usable

SCENES = (*builtin_scenes(), "all-kinds")
MESH_SCENES = ("torus", "sweep", "carried")  # a triangle mesh or a moving body: docs/scenes.md
N = 32  # big enough for every collider to be touched within 500 steps (tests/test_colliders.py)


def scene_named(name: str, n: int = N):
    return every_collider_scene(n) if name == "all-kinds" else load_scene(name).replace(grid=n)


# --- strict: bit for bit ------------------------------------------------------------------


def strict_cases() -> list:
    """(param, scene, steps): 500 steps is after contact with every collider. The quick tier runs
    every backend and scene for 1 step and clothbench's own backends for 500 on the analytic
    scenes; the peers' 500 steps run in the full tier, the generic kernels' (the specialised
    kernel's operations with the scene's numbers as arguments) and NumPy's own (NumPy has one
    mode: its row is NumPy's reference run again, so past the first step it shows nothing new). The mesh
    scenes run 1 step here; after contact they are test_bodies_contract.py's, with each mesh search."""
    cases = []
    for param in backend_params(builds=True):
        name, generic = param.values[0]
        for scene_name in SCENES:
            for steps in (1,) if scene_name in MESH_SCENES else (1, 500):
                heavy = steps == 500 and (BACKENDS[name].peer or name == "numpy" or generic)
                cases.append(
                    pytest.param(
                        param.values[0],
                        scene_name,
                        steps,
                        id=f"{param.id}-{scene_name}-{steps}",
                        marks=pytest.mark.full if heavy else (),
                    )
                )
    return cases


@pytest.mark.parametrize("param, scene_name, steps", strict_cases())
def test_strict_matches_numpy_f32_bit_for_bit(param, scene_name, steps):
    name, generic = usable(param)
    scene = scene_named(scene_name)
    refusal = backend_class(name).capabilities.scene_refusal(name, scene)
    if refusal:  # a mesh or moving scene on a backend that does not take it yet
        pytest.skip(refusal)
    pos, prev = simulate(name, scene, VERLET, steps, options(name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    what = f"{name} generic={generic} {scene_name} n={N} steps={steps}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")


@pytest.mark.parametrize("steps", [1, pytest.param(500, marks=pytest.mark.full)])  # 500 at 32^2 is quick
@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
@pytest.mark.parametrize("param", backend_params(builds=True))
def test_strict_matches_numpy_f32_bit_for_bit_on_a_larger_grid(param, scene_name, steps):
    # 64: the built-in scenes' own grid, where launches and vector widths divide differently
    name, generic = usable(param)
    scene = scene_named(scene_name, 64)
    pos, prev = simulate(name, scene, VERLET, steps, options(name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, {name} generic={generic} {scene_name} n=64 steps={steps}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} generic={generic} {scene_name} n=64 steps={steps}")


def small_grid_cases() -> list:
    """(param, scene, n, steps): grids with little or no interior, or a ragged one. n < 5 has no
    interior at all (border code only, and none for the compute shader's split), 5 a 1 x 1 one;
    6, 33, 37 and 100 leave a ragged SIMD or work-group remainder. Every collider for 200
    steps, the sphere scene for 20. The quick tier runs clothbench's own specialised builds; the
    generic builds and the peers run in the full tier."""
    cases = []
    for param in backend_params(builds=True):
        name, generic = param.values[0]
        heavy = generic or BACKENDS[name].peer
        for scene_name, grids, steps in (("all-kinds", (3, 4, 5, 6, 37), 200), ("sphere", (3, 4, 5, 33, 100), 20)):
            for n in grids:
                cases.append(
                    pytest.param(
                        param.values[0],
                        scene_name,
                        n,
                        steps,
                        id=f"{param.id}-{scene_name}-{n}",
                        marks=pytest.mark.full if heavy else (),
                    )
                )
    return cases


@pytest.mark.parametrize("param, scene_name, n, steps", small_grid_cases())
def test_strict_holds_on_grids_with_little_or_odd_interior(param, scene_name, n, steps):
    name, generic = usable(param)
    scene = scene_named(scene_name, n)
    pos, prev = simulate(name, scene, VERLET, steps, options(name, strict=True, generic=generic))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos, {name} generic={generic} {scene_name} n={n} steps={steps}")
    assert_bit_exact(prev, ref_prev, f"prev, {name} generic={generic} {scene_name} n={n} steps={steps}")


# --- fast: as accurate as float32 ------------------------------------------------------------


@pytest.mark.parametrize(
    "scene_name",
    ["sphere", pytest.param("drape", marks=pytest.mark.full), pytest.param("all-kinds", marks=pytest.mark.full)],
)
@pytest.mark.parametrize("param", backend_params(builds=True))
def test_fast_error_is_of_the_order_of_numpy_f32s_own(param, scene_name):
    # Fast mode may contract FMAs and use rsqrt, division and dot built-ins: each an
    # O(float32 epsilon) perturbation per operation, like the reference's own roundings, so
    # over 100 steps (before contact turns rounding into centimetres) its distance to the
    # float64 reference is of the order of NumPy float32's. 3x (with a 1 um floor) still
    # catches a physics slip: an interior damping count of 11 instead of 12 gives 5x, a
    # wrong bend rest length 25x (tests/test_opencl.py measured the per-backend ratios).
    name, generic = usable(param)
    scene, steps = scene_named(scene_name), 100
    ref64 = reference(scene, VERLET, steps, "f64")[0]
    _, f32_max = position_error(reference(scene, VERLET, steps, "f32")[0], ref64)
    pos, _ = simulate(name, scene, VERLET, steps, options(name, generic=generic))
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 3 * max(f32_max, 1e-6), f"{name} fast {fast_max:.3g} m vs numpy f32 {f32_max:.3g} m"


# --- what must not change a bit --------------------------------------------------------------


@pytest.mark.parametrize("param", backend_params(builds=True, needs="local_size"))
def test_work_group_size_changes_no_result(param):
    # 7 divides neither n*n nor an interior: launches are padded and items past the end
    # return early. Strict stays bit-exact; fast stays bit-identical to itself.
    name, generic = usable(param)
    scene = scene_named("sphere", 24)
    strict = simulate(name, scene, VERLET, 40, options(name, strict=True, local_size=7, generic=generic))
    assert_bit_exact(strict[0], reference(scene, VERLET, 40, "f32")[0], f"{name} strict ls=7")
    fast = simulate(name, scene, VERLET, 40, options(name, local_size=7, generic=generic))
    assert_bit_exact(fast[0], simulate(name, scene, VERLET, 40, options(name, generic=generic))[0], f"{name} fast ls=7")


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
@pytest.mark.parametrize("param", backend_params(builds=True, needs="transfers"))
def test_every_transfer_mode_moves_the_same_bits(param, strict):
    # the chapter's upload-every-step and device-to-device copy variants only cost time
    name, generic = usable(param)
    scene = every_collider_scene(N)
    modes = backend_class(name).capabilities.transfers
    default = simulate(name, scene, VERLET, 50, options(name, strict=strict, generic=generic))
    for transfer in modes[1:]:
        other = simulate(name, scene, VERLET, 50, options(name, strict=strict, generic=generic, transfer=transfer))
        for a, b, what in zip(other, default, ("pos", "prev")):
            assert_bit_exact(a, b, f"{name} {what} transfer={transfer} against {modes[0]}")


@pytest.mark.parametrize("param", backend_params())
def test_upload_then_read_returns_the_same_bits(param):
    name, _ = usable(param)
    scene = every_collider_scene(9)
    rng = np.random.default_rng(5)
    pos, prev = VERLET.initial_state(scene, np.float32)
    pos[:, :3] += rng.standard_normal((scene.particles, 3)).astype(np.float32) * 0.01
    with create_backend(name, scene, VERLET, options(name)) as b:
        b.upload(pos, prev)
        got_pos, got_prev = b.read()
    assert_bit_exact(got_pos, pos, f"{name} pos")
    assert_bit_exact(got_prev, prev, f"{name} prev")


# --- normals (docs/normals.md) ---------------------------------------------------------------


def normals_after(name: str, scene, steps: int, **values):
    with create_backend(name, scene, VERLET, options(name, normals=True, **values)) as b:
        b.upload(*b.initial_state())
        assert b.read_normals() is None, "no step since the upload: no normals yet"
        b.advance(steps)
        return (*b.read(), b.read_normals())


@pytest.mark.parametrize("n", [3, 21, 37])
@pytest.mark.parametrize("param", backend_params(builds=True, needs="normals"))
def test_strict_normals_are_the_formula_in_float32_bit_for_bit(param, n):
    # 500 steps of the all-kinds scene: the sheet folds over spheres and cylinders
    name, generic = usable(param)
    pos, prev, normals = normals_after(name, every_collider_scene(n), 500, strict=True, generic=generic)
    assert normals.shape == (n * n, 4) and normals.dtype == np.float32
    assert_bit_exact(normals[:, :3], grid_normals(prev, n, np.float32), f"{name}: normals of read()[1]")
    assert (normals[:, 3] == 0).all()
    if n > 3:  # a 3x3 sheet hardly bends
        assert np.ptp(normals[:, 1]) > 0.5, "the sheet is folded: normals differ"


@pytest.mark.parametrize("param", backend_params(builds=True, needs="normals"))
def test_normals_change_no_step(param):
    name, generic = usable(param)
    scene = every_collider_scene(24)
    pos, prev, _ = normals_after(name, scene, 200, strict=True, generic=generic)
    ref_pos, ref_prev = reference(scene, VERLET, 200, "f32")
    assert_bit_exact(pos, ref_pos, f"{name} pos with normals on")
    assert_bit_exact(prev, ref_prev, f"{name} prev with normals on")


def normals_of(name: str, scene, pos: np.ndarray, **values) -> np.ndarray:
    """Upload `pos` as both positions, step once, return the normals (of `pos`)."""
    with create_backend(name, scene, VERLET, options(name, normals=True, **values)) as b:
        b.upload(pos, pos)
        b.advance(1)
        normals = b.read_normals()
    assert normals.shape == (scene.particles, 4) and normals.dtype == np.float32
    assert (normals[:, 3] == 0).all()
    return normals


@pytest.mark.parametrize("param", backend_params(builds=True, needs="normals"))
def test_strict_normals_of_a_bent_sheet_are_the_formula_bit_for_bit(param):
    # every face a different direction: no symmetry hides a wrong neighbour or sign
    name, generic = usable(param)
    scene, pos = bent_state(29)
    normals = normals_of(name, scene, pos, strict=True, generic=generic)
    expected = grid_normals(pos, scene.grid, np.float32)
    assert_bit_exact(normals[:, :3], expected, f"{name} generic={generic}: normals of a bent sheet")
    assert np.abs(expected[:, 1]).max() < 1  # bent: the test is not the flat sheet again


# Fast normals against the formula in float64 on the same float32 positions: each of the ~20
# float32 operations on unit-length values rounds by at most 6e-8 (contracted where the compiler
# likes, rsqrt for 1/sqrt); measured 1.2e-7.
NORMAL_TOLERANCE = 1e-6


@pytest.mark.parametrize("param", backend_params(builds=True, needs="normals"))
def test_fast_normals_are_the_formula_within_float32_rounding(param):
    # a bent sheet, and the all-kinds sheet folded over its colliders after 500 steps
    name, generic = usable(param)
    scene, pos = bent_state(29)
    normals = normals_of(name, scene, pos, generic=generic)
    expected = grid_normals(pos, scene.grid, np.float64)
    np.testing.assert_allclose(normals[:, :3], expected, rtol=0, atol=NORMAL_TOLERANCE, err_msg=f"{name} bent")
    _, prev, normals = normals_after(name, every_collider_scene(37), 500, generic=generic)
    expected = grid_normals(prev, 37, np.float64)
    np.testing.assert_allclose(normals[:, :3], expected, rtol=0, atol=NORMAL_TOLERANCE, err_msg=f"{name} folded")


@pytest.mark.parametrize("param", backend_params())
def test_normals_only_when_asked_for(param):
    name, _ = usable(param)
    scene = scene_named("sphere", 8)
    with create_backend(name, scene, VERLET, options(name)) as b:
        b.upload(*b.initial_state())
        b.advance(2)
        assert b.read_normals() is None and "normals" not in b.mode


# --- options and names -----------------------------------------------------------------------


def lacking(caps) -> list[tuple[BackendOptions, str]]:
    """An option value for each capability a backend does not declare, and its flag."""
    out = [(BackendOptions(transfer="sometimes"), "--transfer")]
    if "f64" not in caps.precisions:
        out.append((BackendOptions(precision="f64"), "--precision"))
    if not caps.local_size:
        out.append((BackendOptions(local_size=64), "--local-size"))
    if not caps.generic:
        out.append((BackendOptions(generic=True), "--generic"))
    if not caps.normals:
        out.append((BackendOptions(normals=True), "--save-normals"))
    if not caps.device:
        out.append((BackendOptions(device="0:0"), "--device"))
    if not caps.gl:
        out.append((BackendOptions(gl="osmesa"), "--gl"))
    return out


@pytest.mark.parametrize("param", solver_params())
def test_options_it_lacks_are_refused_in_one_line(param):
    from clothbench.model.solver import solver_for_spec

    name, solver = usable(param)
    caps = backend_class(name, solver).capabilities
    settings = solver_for_spec(solver, VERLET)  # the solver of that name (a c VBD is not a PBD)
    for bad, flag in lacking(caps):
        with pytest.raises(ClothbenchError) as e:
            create_backend(name, scene_named("curtain", 8), settings, bad)
        message = str(e.value)
        assert message.startswith(f"{name} does not take {flag}") and "\n" not in message, message


@pytest.mark.parametrize("param", backend_params())
def test_mode_names_the_options_in_one_spelling(param):
    name, _ = usable(param)
    caps = backend_class(name).capabilities
    scene = scene_named("sphere", 8)
    variants, _ = plan_variants([name], [VERLET], generic="both")
    modes = []
    for v in variants:
        with create_backend(name, scene, VERLET, v.options) as b:
            parts = b.mode.split("/")
        modes.append(b.mode)
        if len(caps.precisions) > 1:
            assert v.options.precision in parts
        if caps.strict:
            assert ("strict" if v.options.strict else "fast") in parts
        assert ("generic" in parts) == v.options.generic
        if caps.transfers:
            assert (v.options.transfer or caps.transfers[0]) in parts
        assert any(p.startswith("ls=") for p in parts) == caps.local_size
        assert b.mode.startswith(v.mode.rsplit("/ls=", 1)[0]), "the mode a plan names is the one a run reports"
    assert len(set(modes)) == len(modes), f"two sweep variants of {name} share a mode: {modes}"


@pytest.mark.parametrize("param", solver_params())
def test_capabilities_are_declared_on_the_backend_class_itself(param):
    name, solver = usable(param)
    cls = backend_class(name, solver)
    assert "capabilities" in vars(cls), f"{cls.__name__} inherits its capabilities instead of declaring them"
    assert cls.capabilities.sweep_variants, "a sweep must have at least one variant to time"
