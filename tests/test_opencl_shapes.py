"""The OpenCL kernel shapes (clothbench/backends/opencl/verlet_shapes.py): every candidate is
bit-exact with the NumPy float32 reference in strict mode, the multi-step kernel included;
a shape is chosen by measurement once and remembered."""

from __future__ import annotations

import functools
import json
import re

import numpy as np
import pytest

from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.opencl import verlet as opencl
from clothbench.backends.opencl import verlet_shapes as shapes
from clothbench.backends.tuning import TUNING_ROUNDS
from clothbench.cli import main
from clothbench.errors import ClothbenchError
from clothbench.model.scene import load_scene
from clothbench.harness import position_error, reference, simulate
from clothbench.harness.normals import grid_normals
from conftest import VERLET, assert_bit_exact, every_collider_scene, require, sphere

STRICT = BackendOptions(strict=True)
SCENES = {"sphere": sphere, "all-kinds": every_collider_scene}


@pytest.fixture(autouse=True)
def _opencl():
    require("opencl")


@functools.lru_cache(maxsize=None)
def numpy_f32(scene_name: str, n: int, steps: int):
    return reference(SCENES[scene_name](n), VERLET, steps, "f32")


def candidates(scene, options=STRICT) -> tuple[str, ...]:
    return opencl.OpenCLBackend.kernel_shapes(scene, options)


def multi_step(scene, options=STRICT) -> str:
    (name,) = [c for c in candidates(scene, options) if c.startswith("steps/")]
    return name


# --- strict: every candidate bit for bit ----------------------------------------------------


@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("scene_name", sorted(SCENES))
def test_every_candidate_is_bit_exact_with_numpy_f32(scene_name, n):
    # one backend per candidate, stepped 1 then 499 more: both states compared to NumPy's
    scene = SCENES[scene_name](n)
    names = candidates(scene)
    assert 3 <= len(names) <= 8, names
    assert any(c.startswith("rows/") for c in names) and any(c.startswith("steps/") for c in names)
    for name in names:
        with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, shape=name)) as b:
            b.upload(*b.initial_state())
            done = 0
            for steps in (1, 500):
                b.advance(steps - done)
                done = steps
                pos, prev = b.read()
                ref_pos, ref_prev = numpy_f32(scene_name, n, steps)
                what = f"{scene_name} n={n} {name} after {steps} steps"
                assert_bit_exact(pos, ref_pos, f"pos, {what}")
                assert_bit_exact(prev, ref_prev, f"prev, {what}")


@pytest.mark.parametrize("n", [5, 19, 37])
def test_odd_grids_write_every_particle_once_in_every_shape(n):
    # the rows kernels overlap the last vector of a row (V does not divide n) and mask the
    # edge lane by lane: after one step, the previous state must be exactly the state given
    scene = every_collider_scene(n)
    pos, prev = scene.initial_state(np.float32)
    pos = pos.copy()
    pos[:, :3] += np.random.default_rng(n).normal(0, 1e-3, (n * n, 3)).astype(np.float32)
    for name in candidates(scene):
        with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, shape=name)) as b:
            b.upload(pos, prev)
            b.advance(1)
            assert_bit_exact(b.read()[1], pos, f"prev after one step, n={n} {name}")
        ref = numpy_f32("all-kinds", n, 3)
        assert_bit_exact(simulate("opencl", scene, VERLET, 3, BackendOptions(strict=True, shape=name))[0], ref[0], name)


def test_every_candidate_computes_the_normals_of_the_state_read():
    # docs/normals.md: read_normals() belongs to read()[1], in every shape (the multi-step
    # kernel writes them at every step, so the last step's are left)
    scene = every_collider_scene(32)
    for name in candidates(scene, BackendOptions(strict=True, normals=True)):
        with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, normals=True, shape=name)) as b:
            b.upload(*b.initial_state())
            b.advance(37)
            _, prev = b.read()
            assert_bit_exact(prev, numpy_f32("all-kinds", 32, 37)[1], f"prev, {name}")
            normals = b.read_normals()
            assert_bit_exact(normals[:, :3], grid_normals(prev, 32, np.float32), f"normals, {name}")


@pytest.mark.parametrize("scene_name", ["drape", "all-kinds"])
def test_every_candidate_in_fast_mode_is_as_accurate_as_numpy_f32(scene_name):
    # Fast mode rounds differently in every shape (contraction; rsqrt, on AVX-512 the
    # hardware estimate and a Newton step, about 23 bits), so it is held to float64 as
    # tests/test_opencl.py holds the default shape, and for the same reason: before contact
    # (100 steps) its distance to float64 must be of the order of NumPy float32's own; 2x
    # still catches a physics slip (a missed spring at the edge: several times more).
    scene = every_collider_scene(32) if scene_name == "all-kinds" else load_scene(scene_name).replace(grid=32)
    ref64 = reference(scene, VERLET, 100, "f64")[0]
    _, f32_max = position_error(reference(scene, VERLET, 100, "f32")[0], ref64)
    for name in candidates(scene, BackendOptions()):
        pos, _ = simulate("opencl", scene, VERLET, 100, BackendOptions(shape=name))
        _, fast_max = position_error(pos, ref64)
        assert fast_max <= 2 * f32_max, f"{name}: fast {fast_max:.3g} m vs numpy f32 {f32_max:.3g} m"


# --- several steps per launch -----------------------------------------------------------------


@pytest.mark.parametrize("scene_name", sorted(SCENES))
def test_a_step_count_not_a_multiple_of_k_is_exact(scene_name):
    scene = SCENES[scene_name](32)
    name = multi_step(scene)
    k = shapes.parse(name).steps_per_launch
    assert 37 % k, "the test needs a remainder"
    pos, prev = simulate("opencl", scene, VERLET, 37, BackendOptions(strict=True, shape=name))
    ref_pos, ref_prev = numpy_f32(scene_name, 32, 37)
    assert_bit_exact(pos, ref_pos, f"pos, {name}")
    assert_bit_exact(prev, ref_prev, f"prev, {name}")


def test_advance_in_pieces_equals_one_call_and_launches_once_per_k_steps():
    scene = every_collider_scene(32)
    name = multi_step(scene)
    k = shapes.parse(name).steps_per_launch
    options = BackendOptions(strict=True, shape=name)
    with create_backend("opencl", scene, VERLET, options) as whole:
        whole.upload(*whole.initial_state())
        whole.advance(37)
        assert len(whole._events) == -(-37 // k), "ceil(37 / K) launches, the last with the rest"
        expected = whole.read()
    with create_backend("opencl", scene, VERLET, options) as pieces:
        pieces.upload(*pieces.initial_state())
        for steps in (1, 5, 31):  # odd counts: the state's buffers swap after each
            pieces.advance(steps)
        got = pieces.read()
    assert_bit_exact(got[0], expected[0], "pos, 1+5+31 vs 37")
    assert_bit_exact(got[1], expected[1], "prev, 1+5+31 vs 37")
    assert_bit_exact(got[1], numpy_f32("all-kinds", 32, 37)[1], "prev vs numpy")


def test_the_multi_step_shape_is_offered_only_where_it_fits(monkeypatch):
    assert any(c.startswith("steps/") for c in candidates(sphere(shapes.STEPS_MAX_GRID)))
    assert not any(c.startswith("steps/") for c in candidates(sphere(shapes.STEPS_MAX_GRID + 1)))
    per_step = BackendOptions(strict=True, transfer="per-step")
    assert not any(c.startswith("steps/") for c in candidates(sphere(32), per_step)), "the host uploads every step"
    with create_backend("opencl", sphere(8), VERLET, STRICT) as b:
        limit = b._device.max_work_group_size
    monkeypatch.setattr(shapes, "STEPS_WORK_GROUP", limit + 1)
    assert not any(c.startswith("steps/") for c in candidates(sphere(32))), "a work-group the device cannot run"


# --- choosing a shape -------------------------------------------------------------------------


def test_an_unknown_shape_is_refused_in_one_line_naming_the_candidates(capsys):
    scene = sphere(32)
    names = ", ".join(candidates(scene, BackendOptions()))
    with pytest.raises(ClothbenchError, match=re.escape(f"no kernel shape 'v3' for this scene (it has: {names})")):
        create_backend("opencl", scene, VERLET, BackendOptions(shape="v3"))
    assert main(["run", "--backend", "opencl", "--grid", "32", "--steps", "2", "--shape", "v3"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for name in candidates(scene, BackendOptions()):
        assert name in err
    with pytest.raises(ClothbenchError, match="--generic has one kernel shape"):
        create_backend("opencl", scene, VERLET, BackendOptions(generic=True, shape="v16"))


def test_the_mode_ends_with_the_shape_and_its_work_group_size():
    scene = sphere(32)
    with create_backend("opencl", scene, VERLET, STRICT) as b:
        assert b.shape == candidates(scene)[0] and b.mode == f"strict/resident/ls=auto/{b.shape}"
    name = next(c for c in candidates(scene) if c.startswith("rows/") and "/wg=" in c)
    with create_backend("opencl", scene, VERLET, BackendOptions(shape=name)) as b:
        wg = shapes.parse(name).work_group
        assert b.mode == f"fast/resident/ls={wg}/{name}"
    with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, generic=True)) as b:
        assert b.shape is None and b.mode == "strict/generic/resident/ls=auto"


def test_a_user_work_group_size_replaces_the_fixed_ones():
    names = candidates(sphere(32), BackendOptions(local_size=8))
    assert not any("/wg=" in c and not c.startswith("steps/") for c in names), names
    assert multi_step(sphere(32), BackendOptions(local_size=8)).endswith("/wg=8")


def test_the_choice_is_measured_once_cached_and_remeasured_on_retune(monkeypatch, tmp_path):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    # one device throughout: --retune also measures the default device again, and on a busy
    # machine another runtime (with other vector widths) can win that race
    from clothbench.backends.opencl.device import default_device

    monkeypatch.setenv("PYOPENCL_CTX", default_device().spec)
    timed: list[str] = []
    real = opencl.OpenCLBackend._time_shape
    monkeypatch.setattr(opencl.OpenCLBackend, "_time_shape", lambda self, name: timed.append(name) or real(self, name))
    scene = sphere(32)
    names = candidates(scene)
    with create_backend("opencl", scene, VERLET, STRICT) as first:
        assert sorted(timed) == sorted(names * TUNING_ROUNDS), "every candidate measured, once a turn"
        chosen = first.shape
        assert chosen in names and first.mode.endswith("/" + chosen)
        # what tuning leaves behind is the initial state, and the chosen shape steps it exactly
        assert first.device_elapsed_ms() is None, "the tuning runs are not the caller's advance()"
        first.advance(3)
        assert_bit_exact(first.read()[0], numpy_f32("sphere", 32, 3)[0], f"after tuning, {chosen}")
    (entry,) = json.loads((tmp_path / "tuning" / "opencl.json").read_text()).values()
    assert entry["choice"] == chosen and sorted(entry["ms"]) == sorted(names)
    timed.clear()
    with create_backend("opencl", scene.replace(stiffness=900.0), VERLET, STRICT) as second:
        assert second.shape == chosen and timed == [], "the same key: read back, not measured"
    with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, retune=True)):
        assert sorted(timed) == sorted(names * TUNING_ROUNDS), "--retune measures again"
    timed.clear()
    with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, shape=names[-1])) as named:
        assert named.shape == names[-1] and timed == [], "a named shape is not measured"
