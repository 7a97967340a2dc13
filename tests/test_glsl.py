"""The two OpenGL backends, `glsl` (fragment shader, FBO ping-pong) and `glsl-compute`
(compute shader, SSBO ping-pong), each test run on both.

Strict mode equals the NumPy float32 reference bit for bit (where the driver flushes
subnormal floats, up to the step the run names); fast mode is as accurate as float32; normals follow docs/normals.md; grids of any size work; OSMesa works where
libosmesa6 is installed; without any GL the backends say why and the tests skip.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from clothbench import cli
from clothbench.backends import BackendOptions, availability, create_backend
from clothbench.backends.gl import context as gl_context
from clothbench.backends.gl import fragment as glsl
from clothbench.backends.gl import compute as glsl_compute
from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.harness import max_penetration, position_error, reference, simulate
from clothbench.harness.normals import grid_normals
from clothbench.kernel_source import read_kernel
from clothbench.model.scene import Scene, load_scene

from conftest import VERLET, assert_bit_exact, every_collider_scene, require, sphere, three_kinds_scene

pytestmark = pytest.mark.serial  # holds a GL context: one xdist worker

GL_BACKENDS = ["glsl", "glsl-compute"]

# Fast mode is float32 in another order (dot(), inversesqrt, no `precise`), so it is held to
# float32's own accuracy: its distance to the float64 reference may be at most this many
# times the float32 reference's. Measured at 300 steps of `sphere`, n = 64 (contact
# included): fast 4.9e-5 m, float32 4.7e-5 m. A wrong spring or sign is off by millimetres.
FAST_ERROR_FACTOR = 4

# Normals in fast mode vs the formula in float64 on the same float32 positions: each of the
# ~20 float32 operations on unit-length values rounds by at most 6e-8; measured 1.2e-7.
NORMAL_TOLERANCE = 1e-6


@pytest.fixture(params=GL_BACKENDS)
def backend(request) -> str:
    require(request.param)
    return request.param


def device_name(backend: str) -> str:
    return availability(backend).device


def run(backend: str, scene: Scene, steps: int, **options) -> tuple[np.ndarray, np.ndarray]:
    return simulate(backend, scene, VERLET, steps, BackendOptions(**options))


def build(backend: str, scene: Scene, **options):
    return create_backend(backend, scene, VERLET, BackendOptions(**options))


def f32_reference(scene: Scene, steps: int) -> tuple[np.ndarray, np.ndarray]:
    return reference(scene, VERLET, steps, "f32")


def assert_matches_numpy_f32(backend: str, scene: Scene, steps: int, **options) -> None:
    """Strict result == numpy float32, or a failure naming the driver that could not."""
    pos, prev = run(backend, scene, steps, strict=True, **options)
    ref_pos, ref_prev = f32_reference(scene, steps)
    what = f"{backend} --strict on {device_name(backend)}, {scene.name} n={scene.grid}, {steps} steps"
    assert_bit_exact(pos, ref_pos, f"{what}: pos")
    assert_bit_exact(prev, ref_prev, f"{what}: prev")


# --- strict: bit for bit -------------------------------------------------------------------


def test_the_other_read_path_is_exact_too(backend, monkeypatch):
    # texelFetch (fragment) and SSBO loads (compute): what a driver without image reads uses
    monkeypatch.setattr(glsl, "PREFER_IMAGE_READS", False)
    monkeypatch.setattr(glsl_compute, "PREFER_IMAGE_READS", False)
    with build(backend, sphere(33), strict=True) as b:
        assert not b.image_reads
    assert_matches_numpy_f32(backend, sphere(33), 100)


# --- colliders and specialisation ----------------------------------------------------------

# A particle pushed out of a collider lands on its surface up to float32 rounding of a few
# operations on metre-sized values (ulp(1) = 1.2e-7; measured at most 4.2e-8 m below it in
# the scenes here): "inside" means deeper than this.
INSIDE_TOLERANCE = 1e-6  # m
CONTACT = 2e-3  # m: a collider is touched when a free particle is within this of its surface


# name: (scene, the collider kinds its sheet touches in COLLIDER_STEPS); the built-in
# cylinder's sheet reaches its floor only after seconds (2.5 s at n = 64, later at n = 32), the
# three-kinds scene's in 0.5 s
COLLIDER_SCENES = {
    "cylinder": (lambda: load_scene("cylinder").replace(grid=32), {"cylinder"}),
    "curtain": (lambda: load_scene("curtain").replace(grid=32), {"sphere"}),
    "three-kinds": (three_kinds_scene, {"sphere", "cylinder", "plane"}),
}
COLLIDER_STEPS = 1500  # 0.75 s


def distance_to(pos: np.ndarray, collider) -> float:
    """The distance from `collider` to the nearest free particle outside it (m)."""
    xyz = pos[pos[:, 3] != 0, :3].astype(np.float64)
    if collider.kind == "sphere":
        d = np.linalg.norm(xyz - collider.center, axis=1) - collider.radius
    elif collider.kind == "plane":
        d = (xyz - collider.point) @ np.array(collider.unit_normal)
    else:
        u, a = np.array(collider.axis), np.array(collider.start)
        t = (xyz - a) @ u
        rho = np.linalg.norm(xyz - a - np.outer(t, u), axis=1)
        beyond = np.maximum(-t, 0) + np.maximum(t - collider.length, 0)  # past a cap, along the axis
        d = np.hypot(np.maximum(rho - collider.radius, 0), beyond)
    return float(d.min())


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
@pytest.mark.parametrize("name", COLLIDER_SCENES)
def test_no_particle_ends_inside_a_collider(backend, name, strict):
    make, touched = COLLIDER_SCENES[name]
    scene = make()
    pos, _ = run(backend, scene, COLLIDER_STEPS, strict=strict)
    assert np.isfinite(pos).all()
    depth = max_penetration(pos, scene)
    assert depth <= INSIDE_TOLERANCE, f"a particle ends {depth:.3g} m inside a collider"
    for collider in (c for c in scene.colliders if c.kind in touched):  # the test means something
        gap = distance_to(pos, collider)
        assert gap <= CONTACT, f"{collider} is not touched (nearest particle {gap:.3g} m away)"


def test_specialised_and_generic_programs_agree_bit_for_bit(backend):
    scene = every_collider_scene(24)
    specialised = run(backend, scene, 150, strict=True)
    generic = run(backend, scene, 150, strict=True, generic=True)
    for a, b, what in zip(specialised, generic, ("pos", "prev")):
        assert_bit_exact(a, b, f"{backend} specialised vs generic {what}")


def program_sources(backend: str, scene: Scene, **options) -> list[str]:
    """The code (comments removed) of the programs `backend` compiles for `scene`."""
    with build(backend, scene, **options) as b:
        sources = [b.source] if backend == "glsl" else list(b.sources.values())
    return [re.sub(r"//.*", "", source) for source in sources]


def test_a_program_holds_only_the_collider_kinds_of_its_scene(backend):
    for source in program_sources(backend, sphere(16)):  # one sphere: no cylinder, no plane
        assert "collide_sphere(" in source and "SPHERE_COUNT 1" in source
        assert not re.search("cylinder|plane", source, re.I)
    for source in program_sources(backend, load_scene("drape").replace(grid=16)):  # none at all
        assert not re.search("sphere|cylinder|plane", source, re.I)
    for source in program_sources(backend, load_scene("cylinder").replace(grid=16)):
        assert "collide_cylinder(" in source and "collide_plane(" in source and "sphere" not in source
    for source in program_sources(backend, sphere(16), generic=True):  # generic: every kind
        assert all(f"collide_{kind}(" in source for kind in ("sphere", "cylinder", "plane"))
        assert "#define GENERIC" in source and "#define N_VALUE" not in source  # n is a uniform


def test_normals_code_is_compiled_only_when_asked_for(backend):
    # the switch is a preprocessor one: the program without it declares no normal output
    without = program_sources(backend, sphere(16))
    with_normals = program_sources(backend, sphere(16), normals=True)
    assert all("#define NORMALS" not in s for s in without)
    assert all("#define NORMALS" in s for s in with_normals)


def test_one_generic_program_serves_every_scene(backend):
    device = gl_context.get_device("egl")
    scenes = [sphere(20), load_scene("cylinder").replace(grid=24), load_scene("curtain").replace(grid=12)]
    with build(backend, scenes[0], strict=True, generic=True):
        compiled = device.programs_compiled
    for scene in scenes[1:]:
        assert_matches_numpy_f32(backend, scene, 40, generic=True)
    assert device.programs_compiled == compiled


def test_pinned_particles_never_move(backend):
    scene = load_scene("drape").replace(grid=17)
    pos0, _ = scene.initial_state(np.float32)
    pos, _ = run(backend, scene, 200)
    pinned = scene.pinned()
    assert_bit_exact(pos[pinned], pos0[pinned], "pinned corners")
    assert not np.array_equal(pos, pos0)


# --- fast: as accurate as float32 ---------------------------------------------------------


def test_fast_mode_is_as_accurate_as_float32(backend):
    scene, steps = sphere(64), 300
    pos, _ = run(backend, scene, steps)
    f64 = reference(scene, VERLET, steps, "f64")[0]
    f32_rms, f32_max = position_error(f32_reference(scene, steps)[0], f64)
    rms, worst = position_error(pos, f64)
    assert worst <= FAST_ERROR_FACTOR * f32_max, f"max error {worst:.3g} m, float32's {f32_max:.3g} m"
    assert rms <= FAST_ERROR_FACTOR * f32_rms, f"RMS error {rms:.3g} m, float32's {f32_rms:.3g} m"


# --- normals (docs/normals.md) -------------------------------------------------------------


def normals_of(backend: str, scene: Scene, pos: np.ndarray, strict: bool) -> np.ndarray:
    """Upload `pos` as both positions, step once, return the normals (of `pos`)."""
    with build(backend, scene, strict=strict, normals=True) as b:
        b.upload(pos, pos)
        b.advance(1)
        normals = b.read_normals()
    assert normals.shape == (scene.particles, 4) and normals.dtype == np.float32
    assert np.all(normals[:, 3] == 0)
    return normals


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
def test_flat_sheet_normals_point_along_y(backend, strict):
    scene = sphere(33)
    pos, _ = scene.initial_state(np.float32)
    normals = normals_of(backend, scene, pos, strict)
    assert np.all(normals[:, [0, 2]] == 0)
    if strict:  # y / sqrt(y*y) is exactly 1 in IEEE arithmetic
        assert np.all(normals[:, 1] == 1)
    else:
        np.testing.assert_allclose(normals[:, 1], 1, rtol=0, atol=NORMAL_TOLERANCE)


def roof(n: int, slope: float) -> tuple[Scene, np.ndarray]:
    """A flat sheet folded along its middle column: y = height + slope * |x - 0.5|."""
    scene = sphere(n)
    pos, _ = scene.initial_state(np.float64)
    pos[:, 1] += slope * np.abs(pos[:, 0] - 0.5)
    return scene, pos.astype(np.float32)


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
def test_folded_sheet_normals_are_the_average_of_its_faces(backend, strict):
    n, a = 33, 0.6
    scene, pos = roof(n, a)
    normals = normals_of(backend, scene, pos, strict)[:, :3].reshape(n, n, 3)
    s1, s3 = math.sqrt(1 + a * a), math.sqrt(9 + a * a)
    ridge = n // 2  # column at x = 0.5
    expected = np.zeros((n, n, 3))
    expected[:, :ridge] = (a, 1, 0) / np.float64(s1)  # left face, y = a (0.5 - x) + ...
    expected[:, ridge + 1 :] = (-a, 1, 0) / np.float64(s1)  # right face
    expected[:, ridge] = (0, 1, 0)  # 3 left and 3 right triangles
    expected[0, ridge] = (-a, 3, 0) / np.float64(s3)  # top row: 1 left, 2 right triangles
    expected[-1, ridge] = (a, 3, 0) / np.float64(s3)  # bottom row: 2 left, 1 right
    # the fold's float32 positions are planar only to ~ulp(1)/h = 2e-6 in direction
    np.testing.assert_allclose(normals, expected, rtol=0, atol=1e-5)


def test_normals_belong_to_the_positions_the_last_step_read(backend):
    scene = sphere(32)
    with build(backend, scene, strict=True, normals=True) as b:
        b.upload(*b.initial_state())
        b.advance(250)  # draped over the sphere: far from flat
        pos, prev = b.read()
        normals = b.read_normals()
    assert_bit_exact(normals[:, :3], grid_normals(prev, 32, np.float32), "normals of prev")
    assert not np.array_equal(normals[:, :3], grid_normals(pos, 32, np.float32))


def test_normals_cost_nothing_unless_asked_for(backend):
    scene = sphere(16)
    with build(backend, scene) as b:
        b.upload(*b.initial_state())
        b.advance(2)
        assert b.read_normals() is None
        assert "normals" not in b.mode
    with build(backend, scene, normals=True) as b:
        b.upload(*b.initial_state())
        assert b.read_normals() is None  # no step since the upload: none computed yet
        b.advance(1)
        assert b.read_normals() is not None
        assert "normals" in b.mode


# --- host code: options, modes, caching --------------------------------------------------


def test_device_is_the_gl_renderer(backend):
    renderer = gl_context.get_device("egl").renderer
    assert availability(backend).device == renderer
    with build(backend, sphere(8)) as b:
        assert b.device == renderer


def test_modes_name_what_changes_speed_or_results():
    require("glsl-compute")
    scene = sphere(8)
    assert build("glsl", scene, strict=True).mode == "strict"
    assert build("glsl", scene, normals=True).mode == "fast/normals"
    assert build("glsl-compute", scene).mode == "fast/ls=64/wg=64"  # the default kernel shape
    assert build("glsl-compute", scene, local_size=128).mode == "fast/ls=128"
    assert glsl.GLSLBackend.capabilities.sweep_variants == ({"strict": True}, {"strict": False})
    assert glsl_compute.GLSLComputeBackend.capabilities.local_size
    assert not glsl.GLSLBackend.capabilities.local_size


def test_programs_are_compiled_once_per_context(backend):
    scene, solver = sphere(12), VERLET.replace(dt=4e-4)  # constants no other test uses: a new program
    device = gl_context.get_device("egl")
    with create_backend(backend, scene, solver, BackendOptions(strict=True)):
        compiled = device.programs_compiled
    with create_backend(backend, scene, solver, BackendOptions(strict=True)):
        assert device.programs_compiled == compiled


def test_a_nested_with_device_leaves_the_context_current(backend):
    # Every backend method enters `with device:` itself, so code already inside one (a
    # profile, a renderer) enters it again: only the outermost exit may release the context,
    # or the GL calls after an inner exit do nothing and a read fails or returns stale data.
    scene = sphere(32)
    with build(backend, scene, strict=True) as b, b.gl:
        b.upload(*b.initial_state())  # enters and leaves `with b.gl:` inside ours
        scratch = b.gl.ctx.buffer(reserve=16)  # a GL call of our own after that inner exit
        scratch.write(np.float32([1, 2, 3, 4]).tobytes())
        written = np.frombuffer(scratch.read(), np.float32).copy()
        scratch.release()
        b.advance(100)
        pos, prev = b.read()
    assert written.tolist() == [1, 2, 3, 4]
    ref_pos, ref_prev = f32_reference(scene, 100)
    assert_bit_exact(pos, ref_pos, f"{backend} inside a nested with: pos")
    assert_bit_exact(prev, ref_prev, f"{backend} inside a nested with: prev")


def test_dispatches_larger_than_65535_groups_are_spread_over_y():
    require("glsl-compute")
    # local size 1 at n = 260: the interior pass alone is 256^2 = 65536 work groups
    assert_matches_numpy_f32("glsl-compute", sphere(260), 2, local_size=1)


@pytest.mark.parametrize("shape", ["wg=64", "steps/dispatch=16"])
def test_compute_writes_the_step_over_x_t_minus_dt_and_leaves_x_t_alone(shape):
    # in place: two state buffers, a step (or a dispatch of K) writes the new state over the
    # older one and the two swap roles; the buffer that held x(t) is not written at all
    require("glsl-compute")
    scene = sphere(16)
    pos, prev = VERLET.initial_state(scene, np.float32)
    with create_backend("glsl-compute", scene, VERLET, BackendOptions(strict=True, shape=shape)) as b:
        assert len(b.state) == 2
        b.upload(pos, prev)
        first, second = b.state[b.current], b.state[1 - b.current]
        b.advance(1)
        assert b.state[b.current] is second and b.state[1 - b.current] is first
        with b.gl:
            after = b._read_buffer(first), b._read_buffer(second)
        assert_bit_exact(after[0], pos, f"{shape}: x(t), untouched")
        assert_bit_exact(after[1], f32_reference(scene, 1)[0], f"{shape}: x(t + dt) over x(t - dt)")


@pytest.mark.parametrize("local_size", [7, 100, 1024])
def test_any_work_group_size_up_to_the_limit_is_exact(local_size):
    require("glsl-compute")
    assert_matches_numpy_f32("glsl-compute", sphere(40), 30, local_size=local_size)


def test_work_group_size_past_the_limit_is_refused():
    require("glsl-compute")
    with pytest.raises(ClothbenchError, match="--local-size 4096 is more than"):
        build("glsl-compute", sphere(8), local_size=4096)


def test_both_kernels_include_the_one_step():
    # the step is written once (verlet_cloth_step.glsl); the kernels are its data access
    for filename in ("verlet_cloth.frag", "verlet_cloth.comp"):
        text = read_kernel(filename)
        assert text.count('#include "verlet_cloth_step.glsl"') == 1, filename
        assert "vec3 verlet(" not in text and "spring(" not in text, f"{filename} restates the step"
    assert "vec3 verlet(" in read_kernel("verlet_cloth_step.glsl")


def test_each_program_holds_the_step_once(backend):
    with build(backend, every_collider_scene(24), normals=True) as b:
        sources = [b.source] if backend == "glsl" else list(b.sources.values())
    for source in sources:
        assert not re.search(r"^\s*#include", source, re.M)  # every include resolved
        for definition in ("vec3 verlet(", "vec3 spring(", "vec3 normal_at(", "vec3 collide_sphere("):
            assert source.count(definition) == 1, definition


@pytest.mark.parametrize("name", GL_BACKENDS)
def test_cli_strict_run_saves_the_numpy_f32_bits(name, tmp_path, capsys):
    """As a user runs it: `clothbench run --backend glsl --strict --save` == numpy f32."""
    require(name)
    common = ["run", "--scene", "sphere", "--grid", "64", "--steps", "300", "--json"]
    assert cli.main([*common, "--backend", name, "--strict", "--save", str(tmp_path / "g.npz")]) == 0
    numpy_args = ["--backend", "numpy", "--precision", "f32", "--save", str(tmp_path / "n.npz")]
    assert cli.main([*common, *numpy_args]) == 0
    gl, ref = np.load(tmp_path / "g.npz"), np.load(tmp_path / "n.npz")
    for key in ("pos", "prev"):
        assert_bit_exact(gl[key], ref[key], f"{name} {key}")
    assert '"mode": "strict' in capsys.readouterr().out


def test_cli_saves_normals_when_asked(backend, tmp_path):
    path = tmp_path / "s.npz"
    args = ["run", "--backend", backend, "--grid", "16", "--steps", "20", "--json", "--save-normals"]
    assert cli.main([*args, "--save", str(path)]) == 0
    saved = np.load(path)
    assert saved["normals"].shape == (256, 4)
    np.testing.assert_allclose(
        saved["normals"][:, :3], grid_normals(saved["prev"], 16, np.float64), rtol=0, atol=NORMAL_TOLERANCE
    )


# --- OSMesa, and no GL at all ------------------------------------------------------------


@pytest.fixture
def osmesa():
    try:
        gl_context._load_osmesa()
    except OSError as e:
        pytest.skip(f"OSMesa not installed (apt-get install libosmesa6): {e}")
    return gl_context.get_device("osmesa")


def test_osmesa_runs_strict_bit_for_bit(backend, osmesa):
    assert osmesa.provider == "osmesa" and osmesa.version_code >= 430
    with build(backend, sphere(32), gl="osmesa", strict=True) as b:
        assert b.mode.split("/")[0] == "strict" and b.mode.endswith("/osmesa")
        assert b.gl is osmesa
    assert_matches_numpy_f32(backend, sphere(32), 200, gl="osmesa")


def test_egl_and_osmesa_contexts_interleave(osmesa):
    require("glsl")
    scene = sphere(20)
    ref = f32_reference(scene, 60)[0]
    backends = [build("glsl", scene, strict=True, gl=gl) for gl in ("egl", "osmesa")]
    for b in backends:
        b.upload(*b.initial_state())
    for _ in range(6):  # each advance makes its own context current
        for b in backends:
            b.advance(10)
    for b in backends:
        assert_bit_exact(b.read()[0], ref, b.mode)
        b.close()


@pytest.fixture
def no_gl_state(monkeypatch):
    """Fresh context caches (the real ones come back afterwards) and a fresh registry cache."""
    monkeypatch.setattr(gl_context, "_devices", {})
    monkeypatch.setattr(gl_context, "_failures", {})
    availability.cache_clear()
    yield monkeypatch
    availability.cache_clear()


def _broken(what):
    def create():
        raise RuntimeError(what)

    return create


def test_egl_failing_falls_back_to_osmesa(no_gl_state, osmesa):
    no_gl_state.setattr(gl_context, "_create_egl", _broken("no EGL display"))
    assert availability("glsl").usable
    with build("glsl", sphere(16)) as b:
        assert b.mode == "fast/osmesa"


def test_without_any_gl_the_backends_say_why_and_tests_skip(no_gl_state, capsys):
    no_gl_state.setattr(gl_context, "_create_egl", _broken("found 0 devices"))
    no_gl_state.setattr(gl_context, "_create_osmesa", _broken("libOSMesa not found"))
    for name in GL_BACKENDS:
        a = availability(name)
        assert not a.usable
        assert a.reason.startswith("no EGL display (RuntimeError: found 0 devices) and no OSMesa")
        assert "libegl1 libegl-mesa0 libgl1-mesa-dri" in a.reason
        with pytest.raises(pytest.skip.Exception, match=f"{name} unavailable: no EGL display"):
            require(name)
        assert cli.main(["run", "--backend", name, "--grid", "8", "--steps", "2"]) == 2
        err = capsys.readouterr().err
        assert f"{name} unavailable: no EGL display" in err and "Traceback" not in err


def test_asking_for_osmesa_without_it_says_so(no_gl_state):
    require("glsl")  # EGL works; only OSMesa is missing
    no_gl_state.setattr(gl_context, "_create_osmesa", _broken("libOSMesa not found"))
    with pytest.raises(BackendUnavailable, match=r"glsl unavailable: no OSMesa context: .*libosmesa6"):
        build("glsl", sphere(8), gl="osmesa")
