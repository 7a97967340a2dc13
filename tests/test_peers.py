"""The peer backends (taichi, warp, numba) run the step of docs/semantics.md, checked
against the NumPy reference. Each test skips with the registry's reason when its package
is missing (pip install 'clothbench[peers]').

What each peer gives against the NumPy float32 reference, measured:
- strict (taichi fast_math=False, numba fastmath=False, warp's one kernel): bit for bit,
  except that Taichi flushes subnormal results to zero on its threads (its Program sets
  FTZ) where NumPy keeps them: values of ~1e-37 m near an axis can differ.
- warp fast (its default, the same kernel): bit for bit as well. Warp has no fast-math
  knob on the CPU, and its generated C++ makes one inline call per operation, so clang
  never contracts to FMA.
- taichi's default (fast_math=True) marks every operation `reassoc ninf nsz` in the
  LLVM IR, so LLVM re-associates sums and products (and folds the compiled-in
  constants): up to 2e-6 m after 100 steps at n = 64, growing as the cloth's dynamics
  amplify it.
- numba fast (fastmath=True): FMA contraction (vfmadd), approximate reciprocal square
  roots (vrsqrtps) and reassociation: up to 2e-6 m after 100 steps.
Those are different roundings, not different physics, so the fast modes are held to the
size of float32 rounding itself: no further from the float32 reference than that
reference is from the float64 one (~9e-6 m after 100 steps on both scenes).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.errors import ClothbenchError
from clothbench.harness import position_error, reference, simulate
from clothbench.harness.health import max_penetration
from clothbench.scene import Sphere, load_scene

from conftest import VERLET, assert_bit_exact, require, tilted_cylinder_scene

PEERS = ("taichi", "warp", "numba")
FAST_ROUNDS_DIFFERENTLY = ("taichi", "numba")  # warp's default is already IEEE
SHORT = 100  # steps: 0.05 s, before the sheet reaches the sphere (about 200 steps)
CONTACT = 300  # steps: the sphere scene's own horizon, well into contact
SMALL = 24  # grid for the cylinder/curtain/plane checks
SMALL_CONTACT = 600  # steps: at n = 24 the sheet reaches the cylinder (~400), the curtain its sphere (~600)
STRICT = BackendOptions(strict=True)


def _assert_state_bit_exact(got, want, what):
    assert_bit_exact(got[0], want[0], f"{what} pos")
    assert_bit_exact(got[1], want[1], f"{what} prev")


@pytest.mark.parametrize("name", PEERS)
def test_strict_peer_matches_numpy_where_results_underflow(name):
    # at n = 40, after 30 steps, coordinates that started at exactly 0 have drifted to
    # ~1e-37 and their differences pass through the subnormal range (below 1.2e-38)
    require(name)
    scene = load_scene("sphere").replace(grid=40)
    got, want = simulate(name, scene, VERLET, 30, STRICT), reference(scene, VERLET, 30, "f32")
    near_zero = (want[0] != 0) & (np.abs(want[0]) < 1e-30)
    assert near_zero.any(), "the case no longer reaches the subnormal range"
    if name != "taichi":
        _assert_state_bit_exact(got, want, f"{name} --strict, n=40, 30 steps")
        return
    for g, w in zip(got, want):  # Taichi: equal, except where flush-to-zero changed a tiny value
        differ = g != w
        assert (np.abs(g[differ]) < 1e-30).all() and (np.abs(w[differ]) < 1e-30).all(), (
            f"taichi --strict differs from numpy beyond flush-to-zero: {int(differ.sum())} values, "
            f"max |diff| {float(np.abs(g.astype(np.float64) - w).max()):.3g}"
        )


def test_taichi_leaves_numpys_floating_point_environment_alone():
    # ti.init sets flush-to-zero on the calling thread; the backend restores it, or NumPy
    # (and every reference computed after it in this process) would flush subnormals too.
    # A fresh process, so that ti.init really runs here.
    require("taichi")
    code = """if True:
        import numpy as np
        from clothbench.backends import create_backend
        from clothbench.scene import load_scene
        from clothbench.solver import Verlet
        def subnormal():
            return np.float32(1e-38) * np.float32(1e-3)
        assert subnormal() != 0
        scene = load_scene("drape").replace(grid=8)
        with create_backend("taichi", scene, Verlet()) as b:
            b.upload(*b.initial_state())
            b.advance(2)
            b.synchronize()
            print(subnormal() != 0)
    """
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True", "after ti.init, NumPy flushes subnormals to zero"


@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
def test_warp_default_matches_numpy_bit_for_bit(scene_name):
    require("warp")
    scene = load_scene(scene_name)
    got = simulate("warp", scene, VERLET, CONTACT)
    _assert_state_bit_exact(got, reference(scene, VERLET, CONTACT, "f32"), f"warp default, {scene_name}")


@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
@pytest.mark.parametrize("name", FAST_ROUNDS_DIFFERENTLY)
def test_fast_peer_matches_numpy_within_float32_rounding(name, scene_name):
    require(name)
    scene = load_scene(scene_name)
    f32, f64 = reference(scene, VERLET, SHORT, "f32")[0], reference(scene, VERLET, SHORT)[0]
    budget = position_error(f32, f64)[1]  # how far float32 rounding alone moves the result
    pos = simulate(name, scene, VERLET, SHORT)[0]
    worst = position_error(pos, f32)[1]
    assert worst <= budget, (
        f"{name} fast, {scene_name}: {worst:.3g} m from the numpy float32 state after {SHORT} "
        f"steps, more than float32 rounding itself ({budget:.3g} m from float64)"
    )


@pytest.mark.parametrize("name", PEERS)
def test_every_sphere_collides_in_scene_order(name):
    # two overlapping spheres: a particle pushed out of the first can land in the second,
    # so the order matters, and strict mode must still match numpy bit for bit
    require(name)
    scene = load_scene("sphere").replace(
        spheres=(Sphere((0.5, 0.5, 0.5), 0.3), Sphere((0.65, 0.55, 0.5), 0.25)), grid=32
    )
    got = simulate(name, scene, VERLET, CONTACT, STRICT)  # the sheet touches both by then
    _assert_state_bit_exact(got, reference(scene, VERLET, CONTACT, "f32"), f"{name} --strict, two spheres")


@pytest.mark.parametrize("name", PEERS)
def test_pinned_particles_never_move(name):
    require(name)
    scene = load_scene("drape")
    start = scene.initial_state(np.float32)[0]
    pinned = scene.pinned()
    pos, prev = simulate(name, scene, VERLET, CONTACT)
    assert_bit_exact(pos[pinned], start[pinned], f"{name}: pinned pos")
    assert_bit_exact(prev[pinned], start[pinned], f"{name}: pinned prev")
    free = np.setdiff1d(np.arange(scene.particles), pinned)
    assert (pos[free, 1] < start[free, 1]).all(), f"{name}: the free particles did not fall"


@pytest.mark.parametrize("name", PEERS)
def test_no_particle_ends_inside_the_sphere(name):
    require(name)
    scene = load_scene("sphere")
    pos = simulate(name, scene, VERLET, CONTACT)[0]
    sphere = scene.spheres[0]
    dist = np.sqrt(((pos[:, :3].astype(np.float64) - sphere.center) ** 2).sum(axis=1))
    assert dist.min() < sphere.radius + 1e-3, f"{name}: the sheet never reached the sphere"
    # pushed out to c + d * (r / |d|) in float32: on the surface to a few ulp of r (3e-8 m)
    assert max_penetration(pos, scene) <= 1e-6, f"{name}: a particle is inside the sphere"


@pytest.mark.parametrize("name", PEERS)
def test_two_instances_in_one_process_keep_their_own_state(name):
    require(name)
    scenes = [load_scene("sphere").replace(grid=16), load_scene("drape").replace(grid=24)]
    backends = [create_backend(name, s, VERLET, STRICT) for s in scenes]
    try:
        for b, s in zip(backends, scenes):
            b.upload(*b.initial_state())
        for _ in range(5):  # interleaved: neither may disturb the other
            for b in backends:
                b.advance(20)
        for b, s in zip(backends, scenes):
            b.synchronize()
            _assert_state_bit_exact(b.read(), reference(s, VERLET, 100, "f32"), f"{name} n={s.grid}")
    finally:
        for b in backends:
            b.close()


def test_taichi_refuses_a_second_mode_while_one_is_alive():
    require("taichi")
    scene = load_scene("drape").replace(grid=8)
    with create_backend("taichi", scene, VERLET, BackendOptions(strict=False)):
        with pytest.raises(ClothbenchError, match="close the other taichi backend"):
            create_backend("taichi", scene, VERLET, STRICT)
    with create_backend("taichi", scene, VERLET, STRICT) as b:  # alone, it may switch
        b.upload(*b.initial_state())
        b.advance(10)
        _assert_state_bit_exact(b.read(), reference(scene, VERLET, 10, "f32"), "taichi after switching")


@pytest.mark.parametrize("name", PEERS)
def test_missing_package_is_reported_with_the_install_command(name):
    # without its package (each imports the module of its own name) the backend's module
    # still imports, and probe() says what to install
    code = (
        f"import sys; sys.modules[{name!r}] = None\n"
        f"from clothbench.backends import availability\n"
        f"print(availability({name!r}).reason)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"{name} not installed (pip install 'clothbench[peers]')"


def _small(scene_name):
    return load_scene(scene_name).replace(grid=SMALL)


def _assert_contact(scene, steps, kinds, what):
    """Each of these kinds of collider changes the numpy result: contact really happens."""
    want = reference(scene, VERLET, steps, "f32")[0]
    for kind in kinds:
        other = reference(scene.replace(**{kind: ()}), VERLET, steps, "f32")[0]
        assert not np.array_equal(want, other), f"{what}: the cloth never touches the {kind}"


# scene, and the colliders it reaches in SMALL_CONTACT steps (the built-in floor is not reached)
SCENES_WITH_CONTACT = {
    "cylinder": (lambda: _small("cylinder"), ("cylinders",)),
    "curtain": (lambda: _small("curtain"), ("spheres",)),
    "tilted": (lambda: tilted_cylinder_scene(SMALL), ("cylinders", "planes")),
}


@pytest.mark.parametrize("scene_name", list(SCENES_WITH_CONTACT))
@pytest.mark.parametrize("strict", [False, True])
@pytest.mark.parametrize("name", PEERS)
def test_no_particle_ends_inside_a_cylinder_plane_or_sphere(name, strict, scene_name):
    require(name)
    make, kinds = SCENES_WITH_CONTACT[scene_name]
    scene = make()
    _assert_contact(scene, SMALL_CONTACT, kinds, scene_name)
    pos = simulate(name, scene, VERLET, SMALL_CONTACT, BackendOptions(strict=strict))[0]
    assert np.isfinite(pos).all(), f"{name}: non-finite positions on {scene_name}"
    assert max_penetration(pos, scene) <= 1e-6, (
        f"{name} strict={strict}: a particle is inside a collider ({scene_name})"
    )


@pytest.mark.parametrize("scene_name", ["cylinder", "tilted"])
def test_warp_default_matches_numpy_bit_for_bit_with_cylinders_and_planes(scene_name):
    require("warp")
    scene = SCENES_WITH_CONTACT[scene_name][0]()
    got = simulate("warp", scene, VERLET, SMALL_CONTACT)
    want = reference(scene, VERLET, SMALL_CONTACT, "f32")
    _assert_state_bit_exact(got, want, f"warp default, {scene_name}")


@pytest.mark.parametrize("name", FAST_ROUNDS_DIFFERENTLY)
def test_fast_peer_matches_numpy_within_float32_rounding_on_cylinder(name):
    require(name)
    scene = load_scene("cylinder")
    f32, f64 = reference(scene, VERLET, SHORT, "f32")[0], reference(scene, VERLET, SHORT)[0]
    budget = position_error(f32, f64)[1]
    worst = position_error(simulate(name, scene, VERLET, SHORT)[0], f32)[1]
    assert worst <= budget, f"{name} fast, cylinder: {worst:.3g} m from numpy f32, budget {budget:.3g} m"
