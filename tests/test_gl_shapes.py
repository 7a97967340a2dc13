"""Kernel shapes of glsl-compute (clothbench/backends/gl/shapes.py) and the GL backends' driver.

Every shape of a strict build is NumPy float32 bit for bit (a shape splits the particles
differently, never changes the operations on one); the several-steps-per-dispatch shape
returns the state of its last step exactly, whatever way the steps are split into calls; a
shape that is not a candidate is refused in one line; the tuned choice is measured once per
key, cached, and measured again on --retune; the mode names the shape; the driver names the
GL renderer and version.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from clothbench import kernel_source
from clothbench import cli
from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.gl import context as gl_context
from clothbench.backends.gl import shapes
from clothbench.backends.gl.compute import GLSLComputeBackend
from clothbench.backends.tuning import TUNING_ROUNDS
from clothbench.errors import ClothbenchError
from clothbench.harness import reference

from conftest import VERLET, assert_bit_exact, every_collider_scene, require, sphere

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker

SCENES = {"sphere": sphere, "all-kinds": every_collider_scene}


@pytest.fixture(autouse=True)
def compute():
    require("glsl-compute")


def build(scene, **options):
    return create_backend("glsl-compute", scene, VERLET, BackendOptions(**options))


def all_shapes(scene, **options) -> tuple[str, ...]:
    return GLSLComputeBackend.kernel_shapes(scene, BackendOptions(**options))


# --- strict: every shape bit for bit ------------------------------------------------------


@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("scene_name", SCENES)
def test_every_shape_is_numpy_f32_bit_for_bit(scene_name, n):
    scene = SCENES[scene_name](n)
    names = all_shapes(scene, strict=True)
    assert any(name.startswith("steps/dispatch=") for name in names)  # small grids have it
    assert any("x" in name for name in names)  # and 2-D tiles
    for name in names:
        with build(scene, strict=True, shape=name) as b:
            b.upload(*b.initial_state())
            for done, steps in ((1, 1), (500, 499)):  # 500: after contact with every collider
                b.advance(steps)
                pos, prev = b.read()
                ref_pos, ref_prev = reference(scene, VERLET, done, "f32")
                what = f"glsl-compute --shape {name} {scene_name} n={n} after {done} steps"
                assert_bit_exact(pos, ref_pos, f"{what}: pos")
                assert_bit_exact(prev, ref_prev, f"{what}: prev")


@pytest.mark.parametrize("name", ["steps/dispatch=16", "wg=16x16"])
def test_generic_programs_of_a_shape_are_exact_too(name):
    scene = every_collider_scene(32)
    with build(scene, strict=True, generic=True, shape=name) as b:
        b.upload(*b.initial_state())
        b.advance(200)
        pos, prev = b.read()
    ref_pos, ref_prev = reference(scene, VERLET, 200, "f32")
    assert_bit_exact(pos, ref_pos, f"generic {name}: pos")
    assert_bit_exact(prev, ref_prev, f"generic {name}: prev")


def run_split(scene, name: str, splits: tuple[int, ...]):
    with build(scene, strict=True, shape=name) as b:
        b.upload(*b.initial_state())
        for steps in splits:
            b.advance(steps)
        return b.read()


@pytest.mark.parametrize("name", [f"steps/dispatch={k}" for k in shapes.STEPS_PER_DISPATCH])
def test_several_steps_per_dispatch_end_on_the_last_step_however_split(name):
    # 37 is no multiple of K: full dispatches and a remainder; 1 + 5 + 31 splits it otherwise
    scene = every_collider_scene(32)
    ref_pos, ref_prev = reference(scene, VERLET, 37, "f32")
    whole = run_split(scene, name, (37,))
    split = run_split(scene, name, (1, 5, 31))
    for got, what in ((whole, "advance(37)"), (split, "advance(1, 5, 31)")):
        assert_bit_exact(got[0], ref_pos, f"{name} {what}: pos")
        assert_bit_exact(got[1], ref_prev, f"{name} {what}: prev")


def test_several_steps_per_dispatch_fall_back_to_a_scratch_buffer_past_shared_memory():
    # 64^2 particles need 96 KiB of scratch: more than llvmpipe's 32 KiB of shared memory
    device = gl_context.get_device("egl")
    _, shared_bytes = shapes.limits(device)
    scene = sphere(64)
    with build(scene, strict=True, shape="steps/dispatch=16") as b:
        assert b.plan.layout.shared == (scene.particles * shapes.SCRATCH_BYTES_PER_PARTICLE <= shared_bytes)
        assert b.plan.layout.local * b.plan.layout.ppi >= scene.particles
        b.upload(*b.initial_state())
        b.advance(37)
        pos, prev = b.read()
    ref_pos, ref_prev = reference(scene, VERLET, 37, "f32")
    assert_bit_exact(pos, ref_pos, "steps/dispatch=16 n=64: pos")
    assert_bit_exact(prev, ref_prev, "steps/dispatch=16 n=64: prev")


def test_normals_of_several_steps_per_dispatch_belong_to_the_last_step():
    # the normals of the state the last step read, as the one-step-per-dispatch shape gives them
    scene = sphere(32)
    results = {}
    for name in ("wg=64", "steps/dispatch=16"):
        with build(scene, strict=True, normals=True, shape=name) as b:
            b.upload(*b.initial_state())
            b.advance(37)
            results[name] = (*b.read(), b.read_normals())
    for a, c, what in zip(results["wg=64"], results["steps/dispatch=16"], ("pos", "prev", "normals")):
        assert_bit_exact(c, a, f"steps/dispatch=16 vs wg=64 {what}")
    assert np.abs(results["wg=64"][2][:, 1]).max() > 0.5  # real normals, not zeros


def test_steps_layout_fits_one_work_group():
    assert shapes.steps_layout(1024, 1024, 32768) == shapes.StepsLayout(1024, 1, True)
    assert shapes.steps_layout(4096, 1024, 32768) == shapes.StepsLayout(1024, 4, False)
    # 36^2 = 1296: two particles per invocation, 648 invocations (a multiple of 8)
    assert shapes.steps_layout(1296, 1024, 32768) == shapes.StepsLayout(648, 2, True)
    assert shapes.steps_layout(9, 1024, 32768) == shapes.StepsLayout(16, 1, True)


# --- refusals ------------------------------------------------------------------------------


def test_an_unknown_shape_is_refused_in_one_line():
    with pytest.raises(ClothbenchError) as e:
        build(sphere(16), shape="wg=3x3")
    message = str(e.value)
    assert "\n" not in message and "'wg=3x3'" in message and "wg=64" in message


def test_several_steps_per_dispatch_is_no_candidate_on_large_grids():
    big = sphere(128)  # past MULTI_STEP_MAX_PARTICLES
    assert not any(name.startswith("steps/") for name in all_shapes(big))
    with pytest.raises(ClothbenchError, match="no kernel shape 'steps/dispatch=16'"):
        build(big, shape="steps/dispatch=16")


def test_shape_and_local_size_exclude_each_other():
    with pytest.raises(ClothbenchError, match="exclude each other"):
        build(sphere(16), shape="wg=8x8", local_size=64)


def test_cli_refuses_an_unknown_shape_in_one_line(capsys):
    args = ["run", "--backend", "glsl-compute", "--scene", "sphere", "--grid", "16", "--steps", "2"]
    assert cli.main([*args, "--shape", "nonsense"]) != 0
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no kernel shape 'nonsense'" in err


def test_the_fragment_backend_has_no_shapes():
    require("glsl")
    with pytest.raises(ClothbenchError, match="--shape"):
        create_backend("glsl", sphere(16), VERLET, BackendOptions(shape="wg=64"))


# --- mode, tuning, driver ------------------------------------------------------------------


def mode_of(scene, **options) -> str:
    with build(scene, **options) as b:
        return b.mode


def test_the_mode_names_the_shape():
    scene = sphere(32)
    assert mode_of(scene) == "fast/ls=64/wg=64"  # the default shape where tuning is off
    assert mode_of(scene, strict=True, shape="wg=16x16") == "strict/ls=256/wg=16x16"
    assert mode_of(scene, shape="steps/dispatch=16") == "fast/ls=1024/steps/dispatch=16"
    assert mode_of(scene, local_size=128) == "fast/ls=128"  # --local-size: that 1-D shape, untuned


@pytest.fixture
def tuning(monkeypatch, tmp_path):
    """Tuning on, into an empty cache, with fake timings (wg=8x8 fastest); returns the
    names timed so far."""
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    timed: list[str] = []

    def fake(backend, name):
        timed.append(name)
        return 1e-4 if name == "wg=8x8" else 2e-4

    monkeypatch.setattr(shapes, "time_shape", fake)
    return timed


def test_tuning_measures_once_per_key_and_again_on_retune(tuning, tmp_path):
    scene = sphere(32)
    candidates = all_shapes(scene, strict=True)
    with build(scene, strict=True) as b:
        assert b.shape == "wg=8x8" and b.mode.endswith("/wg=8x8")
        driver = b.driver
    assert sorted(tuning) == sorted(candidates * TUNING_ROUNDS)  # each candidate timed once a turn
    stored = json.loads((tmp_path / "tuning" / "glsl-compute.json").read_text())
    (key,) = [json.loads(k) for k in stored]
    assert key["driver"] == driver and key["grid"] == "32" and key["arithmetic"] == "strict"
    with build(scene, strict=True) as b:  # cached: nothing measured
        assert b.shape == "wg=8x8"
    assert len(tuning) == TUNING_ROUNDS * len(candidates)
    with build(scene, strict=True, retune=True) as b:  # measured again
        assert b.shape == "wg=8x8"
    assert len(tuning) == 2 * TUNING_ROUNDS * len(candidates)
    with build(scene, strict=False):  # another key (fast arithmetic): measured for it
        pass
    assert len(tuning) == 3 * TUNING_ROUNDS * len(candidates)


def test_a_real_tuning_run_picks_a_candidate_that_stays_exact(monkeypatch, tmp_path):
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    scene = sphere(32)
    with build(scene, strict=True) as b:
        assert b.shape in all_shapes(scene, strict=True)
        b.upload(*b.initial_state())  # after the timed runs, from the start again
        b.advance(40)
        pos, prev = b.read()
    stored = json.loads((tmp_path / "tuning" / "glsl-compute.json").read_text())
    (entry,) = stored.values()
    assert entry["choice"] == b.shape and set(entry["ms"]) == set(all_shapes(scene, strict=True))
    assert min(entry["ms"], key=entry["ms"].get) == b.shape
    ref_pos, ref_prev = reference(scene, VERLET, 40, "f32")
    assert_bit_exact(pos, ref_pos, f"tuned {b.shape}: pos")
    assert_bit_exact(prev, ref_prev, f"tuned {b.shape}: prev")


@pytest.mark.parametrize("backend", ["glsl", "glsl-compute"])
def test_the_driver_is_the_gl_renderer_and_version(backend):
    require(backend)
    device = gl_context.get_device("egl")
    with create_backend(backend, sphere(8), VERLET, BackendOptions()) as b:
        driver = b.driver
    assert device.renderer in driver and device.ctx.info["GL_VERSION"] in driver
    if device.renderer.startswith("llvmpipe"):  # this project's machines
        assert driver.startswith("llvmpipe (LLVM ") and "Mesa" in driver


def test_the_anatomy_tool_cuts_every_part_it_names():
    # docs/llvmpipe.md's breakdown: each row must remove something more from the step's
    # shader, and a cut that no longer matches the kernel must fail rather than time the
    # previous row again
    from clothbench.backends.gl import anatomy
    from clothbench.backends.gl.compute import PASS_INTERIOR

    with build(sphere(16), strict=True, shape="wg=64") as b:
        source = b.sources[(PASS_INTERIOR, "wg=64")]
        rows = anatomy.variants(source, anatomy.COMPUTE_CUTS)
        assert len(rows) == len(anatomy.COMPUTE_CUTS) + 1
        for (_, before), (label, after) in zip(rows, rows[1:]):
            assert after != before, label
        with b.gl:
            for label, variant in rows:  # each one still compiles
                b.gl.ctx.compute_shader(variant).release()
    with pytest.raises(ClothbenchError, match="finds nothing to cut"):
        anatomy.variants(source.replace("P vec3 f = s * d - bv;", "P vec3 f = s * d + -bv;"), anatomy.COMPUTE_CUTS)


def test_an_edit_to_any_file_the_step_includes_is_a_new_tuning_key(monkeypatch):
    # the choice was measured on the kernels' text: verlet_cloth.comp includes the step's file,
    # whose edit must measure again as an edit to the top file does (generated parts aside)
    before = kernel_source.kernel_hash(*shapes.VERLET_KERNELS)
    assert kernel_source.kernel_hash(*shapes.VERLET_KERNELS) == before  # the text, nothing else
    original = kernel_source.read_kernel
    edited = {"verlet_cloth_step.glsl": "// a comment\n"}
    monkeypatch.setattr(kernel_source, "read_kernel", lambda name: original(name) + edited.get(name, ""))
    assert kernel_source.kernel_hash(*shapes.VERLET_KERNELS) != before


class _PlanRecorder:
    """What time_shape asks of a backend, without a GL context: the steps of each timed run."""

    def __init__(self, scene):
        self.scene, self.runs = scene, []

    def build_plan(self, name):
        return SimpleNamespace(shape=shapes.parse(name, self.scene, 1024))

    def initial_state(self):
        return None, None

    def upload(self, pos, prev):
        pass

    def run_plan(self, plan, steps):
        self.runs.append(steps)

    def synchronize(self):
        pass


@pytest.mark.parametrize("grid, steps", [(64, shapes.TUNING_STEPS), (1024, 1), (2048, 1)])
def test_a_shape_is_timed_over_fewer_steps_on_a_larger_grid(grid, steps):
    # a turn is about tuning.TURN_PARTICLE_STEPS of work: 8 steps of 2048^2 took 0.44 s a turn
    # on llvmpipe, 60 turns a row; one is 55 ms, still long against a dispatch
    backend = _PlanRecorder(sphere(grid))
    shapes.time_shape(backend, "wg=64")
    assert set(backend.runs) == {steps} and len(backend.runs) == 1 + shapes.TUNING_REPEATS


def test_the_one_group_shape_is_timed_over_its_steps_per_dispatch_at_least():
    backend = _PlanRecorder(sphere(64))
    shapes.time_shape(backend, "steps/dispatch=64", steps=1)
    assert set(backend.runs) == {64}
