"""The OpenCL backend (kernels/verlet_cloth.cl) against the NumPy reference (docs/semantics.md)."""

from __future__ import annotations

import re
import sys

import numpy as np
import pytest

from clothbench.backends import BackendOptions, availability, create_backend
from clothbench import kernel_source
from clothbench.backends.opencl import device, verlet as opencl
from clothbench.backends.opencl.build_log import error_places
from clothbench.backends.opencl.verlet_shapes import parse as parse_shape
from clothbench.cli import main
from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.harness import max_penetration, position_error, reference, simulate
from clothbench.harness.normals import grid_normals
from clothbench.kernel_source import read_kernel
from clothbench.scene import Cylinder, Plane, Scene, Sphere, load_scene
from conftest import VERLET, assert_bit_exact, every_collider_scene, require, sphere

STRICT = BackendOptions(strict=True)
FAST = BackendOptions()
# The two builds of the kernel file: specialised for the scene (the default) and --generic.
BUILDS = pytest.mark.parametrize("generic", [False, True], ids=["specialised", "generic"])


def collider_scene(name: str, n: int) -> Scene:
    return every_collider_scene(n) if name == "all-kinds" else load_scene(name).replace(grid=n)


def assert_matches_numpy_f32(scene: Scene, steps: int, **options) -> None:
    pos, prev = simulate("opencl", scene, VERLET, steps, BackendOptions(strict=True, **options))
    ref_pos, ref_prev = reference(scene, VERLET, steps, "f32")
    what = f"{scene.name} n={scene.grid} steps={steps} {options}"
    assert_bit_exact(pos, ref_pos, f"pos, {what}")
    assert_bit_exact(prev, ref_prev, f"prev, {what}")


# --- strict: bit for bit --------------------------------------------------------------------


def test_the_all_kinds_scene_touches_every_kind_within_500_steps():
    # what makes the exactness test above cover each collider's code on contact
    scene = every_collider_scene(32)
    touched = reference(scene, VERLET, 500, "f32")[0]
    for kind in ("spheres", "cylinders", "planes"):
        without = reference(scene.replace(**{kind: ()}), VERLET, 500, "f32")[0]
        assert not np.array_equal(touched, without), f"no particle touched the {kind}"


# Particles placed in every branch of every collider (docs/semantics.md, Collisions): no
# springs, no gravity, no damping, so only the colliders move them, in one step.
CASES_SCENE = Scene(
    grid=20,
    stiffness=0.0,
    damping=0.0,
    gravity=(0.0, 0.0, 0.0),
    height=5.0,
    spheres=(Sphere((0.0, 0.0, 0.0), 0.3), Sphere((0.0, 0.25, 0.0), 0.1)),
    cylinders=(
        Cylinder((1.0, 0.0, 0.0), (2.0, 0.0, 0.0), 0.2),
        Cylinder((1.0, 1.0, 0.0), (1.3, 1.4, 0.5), 0.1),
        Cylinder((3.0, 0.0, 0.0), (3.25, 0.0, 0.0), 0.5),  # short and fat: caps nearer than the side
    ),
    planes=(Plane((0.0, -1.0, 0.0), (0.0, 2.0, 0.0)), Plane((0.0, 0.0, 3.0), (0.3, -0.2, -1.0))),
    pin_indices=(300,),
)
CASES = [
    (0.1, 0.05, -0.12),  # inside sphere 0, then pushed into sphere 1 and out of it
    (0.0, 0.0, 0.0),  # at the centre: straight up
    (-0.2, -0.1, 0.05),  # inside sphere 0 only
    (1.5, 0.15, 0.0),  # cylinder 0: through the side
    (1.05, 0.0, 0.1),  # through the start cap
    (1.97, -0.05, 0.0),  # through the end cap
    (1.5, 0.0, 0.0),  # on the axis: along the fixed radial direction
    (1.15, 1.2, 0.25),  # inside the skewed cylinder
    (0.5, -1.2, 0.5),  # below floor 0
    (0.5, 0.5, 3.1),  # behind the tilted plane 1
    (3.125, 0.1, 0.0),  # cylinder 2, exactly midway between its caps: out through the start cap
    (0.5, 0.5, 2.9),  # in front of it: untouched
    (0.3, 0.2, 0.1),  # the pinned particle (index 300), inside sphere 0: never collided
]
CASE_INDEX = [0, 19, 21, 45, 50, 137, 155, 199, 222, 260, 246, 399, 300]  # border and interior


def one_step_of_cases(name: str, options: BackendOptions) -> np.ndarray:
    pos, prev = CASES_SCENE.initial_state(np.float32 if name == "opencl" else np.float64)
    pos[:, :3] = np.linspace(5, 6, pos.shape[0])[:, None]  # everyone else far from every collider
    pos[CASE_INDEX, :3] = CASES
    prev[:, :3] = pos[:, :3]
    with create_backend(name, CASES_SCENE, VERLET, options) as b:
        b.upload(pos, prev)
        b.advance(1)
        return b.read()[0]


@BUILDS
def test_every_collider_branch_is_exact_in_strict_and_within_ulps_in_fast(generic):
    require("opencl")
    expected = one_step_of_cases("numpy", BackendOptions(precision="f32"))
    moved = expected[CASE_INDEX[:-2], :3] != np.array(CASES[:-2], np.float32)
    assert moved.any(axis=1).all(), "every case but the last two is pushed somewhere"
    strict = one_step_of_cases("opencl", BackendOptions(strict=True, generic=generic))
    assert_bit_exact(strict, expected, "strict")
    # fast: the same collider formulas, contracted where the compiler likes; ~1 ulp of 2 m
    fast = one_step_of_cases("opencl", BackendOptions(generic=generic))
    np.testing.assert_allclose(fast, expected, rtol=0, atol=1e-6)


@pytest.mark.parametrize("scene_name", ["cylinder", "curtain", "all-kinds"])
def test_specialised_equals_generic_bit_for_bit_in_strict(scene_name):
    # ls=7 and n=37: both builds padded, the interior's last vector overlapping
    require("opencl")
    scene = collider_scene(scene_name, 37)
    specialised = simulate("opencl", scene, VERLET, 300, BackendOptions(strict=True, local_size=7))
    generic = simulate("opencl", scene, VERLET, 300, BackendOptions(strict=True, generic=True))
    for a, b, what in zip(specialised, generic, ("pos", "prev")):
        assert_bit_exact(a, b, f"{scene_name} {what}")


@pytest.mark.parametrize(
    "options",
    [STRICT, FAST, BackendOptions(strict=True, generic=True), BackendOptions(generic=True)],
    ids=["strict", "fast", "strict-generic", "fast-generic"],
)
@pytest.mark.parametrize("scene_name", ["cylinder", "curtain", "all-kinds"])
def test_no_particle_ends_inside_any_collider(scene_name, options):
    require("opencl")
    scene = collider_scene(scene_name, 24)
    steps = 1500  # the curtain reaches its sphere, the sheet its cylinder
    pos, _ = simulate("opencl", scene, VERLET, steps, options)
    assert np.isfinite(pos).all()
    untouched = scene.replace(spheres=(), cylinders=(), planes=())
    assert not np.array_equal(pos, simulate("opencl", untouched, VERLET, steps, options)[0]), "no contact"
    # projections round: a few float32 ulps of the collider's size
    assert max_penetration(pos, scene) <= 1e-6


# --- fast: as accurate as float32 ------------------------------------------------------------


@BUILDS
@pytest.mark.parametrize("scene_name", ["sphere", "drape", "cylinder", "curtain", "all-kinds"])
@pytest.mark.parametrize("n", [32, 64])
def test_opencl_fast_error_is_of_the_order_of_numpy_f32s_own(scene_name, n, generic):
    # Fast mode rounds differently from the reference: FMA contraction (fewer roundings),
    # and in the specialised build rsqrt instead of sqrt and a division (a few ulp) and
    # damping summed once per particle. Each is an O(float32 epsilon) perturbation per
    # operation, like the reference's own roundings, so over a short horizon (100 steps:
    # before contact, while the drape's and the curtain's pins take the load) its distance
    # to the float64 reference must be of the order of the NumPy float32 distance. Measured
    # here: ratio 0.99-1.00. The bound 2x still catches a physics slip: an interior damping
    # count of 11 instead of 12 gives 5x, a wrong bend rest length 25x. (After contact the
    # float32 reference itself drifts by centimetres; the colliders' fast arithmetic is
    # held to ulps by the collider-branch test above instead.)
    require("opencl")
    scene = collider_scene(scene_name, n)
    steps = 100
    ref64 = reference(scene, VERLET, steps, "f64")[0]
    _, f32_max = position_error(reference(scene, VERLET, steps, "f32")[0], ref64)
    pos, _ = simulate("opencl", scene, VERLET, steps, BackendOptions(generic=generic))
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 2 * f32_max, f"fast {fast_max:.3g} m vs numpy f32 {f32_max:.3g} m"


# --- normals (docs/normals.md) ---------------------------------------------------------------

# (the formula itself, strict and fast: tests/contract/test_verlet_contract.py)


def normals_after(scene: Scene, steps: int, **options) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pos, prev, normals) after `steps` steps with normals on."""
    with create_backend("opencl", scene, VERLET, BackendOptions(normals=True, **options)) as b:
        b.upload(*b.initial_state())
        assert b.read_normals() is None, "no step since the upload: no normals yet"
        b.advance(steps)
        return (*b.read(), b.read_normals())


def test_a_flat_sheet_has_normals_straight_up():
    require("opencl")
    scene = sphere(20).replace(gravity=(0.0, 0.0, 0.0))
    for generic in (False, True):
        normals = normals_after(scene, 1, strict=True, generic=generic)[2]
        assert_bit_exact(normals, np.tile(np.float32([0, 1, 0, 0]), (400, 1)), f"generic={generic}")


@BUILDS
def test_normals_cost_nothing_unless_asked_for_and_change_no_step(generic):
    require("opencl")
    scene = every_collider_scene(24)
    with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, generic=generic)) as b:
        b.upload(*b.initial_state())
        b.advance(2)
        assert b.read_normals() is None
        assert "normals" not in b.mode and "NORMALS" not in str(b.key)
    with create_backend("opencl", scene, VERLET, BackendOptions(strict=True, generic=generic, normals=True)) as b:
        assert "normals" in b.mode and "-DCLOTH_NORMALS" in str(b.key)
    pos, prev, _ = normals_after(scene, 200, strict=True, generic=generic)
    ref_pos, ref_prev = reference(scene, VERLET, 200, "f32")
    assert_bit_exact(pos, ref_pos, "pos with normals on")
    assert_bit_exact(prev, ref_prev, "prev with normals on")


def test_cli_saves_normals_when_asked(tmp_path):
    require("opencl")
    path = tmp_path / "s.npz"
    args = ["run", "--backend", "opencl", "--strict", "--grid", "16", "--steps", "20", "--json", "--save-normals"]
    assert main([*args, "--save", str(path)]) == 0
    with np.load(path) as saved:
        assert_bit_exact(saved["normals"][:, :3], grid_normals(saved["prev"], 16, np.float32), "saved normals")


# --- specialisation and the program cache ----------------------------------------------------


def test_a_sphere_only_build_has_no_cylinder_or_plane_code(monkeypatch):
    # Break the cylinder and plane colliders of the specialised build: a scene without
    # them still builds and runs exactly (their code never reaches the compiler); a scene
    # with a cylinder does not build.
    require("opencl")
    source = read_kernel(opencl.KERNEL_FILE)
    broken = source
    for signature in ("void collide_cylinder_v(", "void collide_plane_v("):
        assert signature in broken
        broken = broken.replace(signature, "no_such_type " + signature.split()[1])
    monkeypatch.setattr(device, "read_kernel", lambda name: broken)
    scene = sphere(24)
    with create_backend("opencl", scene, VERLET, STRICT) as b:
        options = " ".join(o for program_options in b.key for o in program_options)
        assert "-DCLOTH_SPHERES=1" in options
        assert "CYLINDER" not in options and "PLANE" not in options, options
    assert_matches_numpy_f32(scene, 100)
    with pytest.raises(ClothbenchError) as e:
        create_backend("opencl", collider_scene("cylinder", 24), VERLET, STRICT)
    broken_line = next(line for line in broken.splitlines() if "no_such_type collide_cylinder_v(" in line)
    assert_names_the_place(str(e.value), opencl.KERNEL_FILE, broken, broken_line, "unknown type name 'no_such_type'")


def test_both_kernel_files_take_the_colliders_from_collide_cl():
    # the float4 colliders are written once (collide.cl); the host resolves the include, so
    # the program's source is all of it
    for filename in ("verlet_cloth.cl", "pbd_cloth.cl"):
        text = read_kernel(filename)
        assert text.count('#include "collide.cl"') == 1, filename
        assert "float3 collide_sphere(" not in text, f"{filename} restates the colliders"
        source = device.program_source(filename)
        assert not re.search(r"^\s*#include", source, re.M), "every include resolved"
        assert source.count("float3 collide_sphere(") == 1


def test_an_edit_to_collide_cl_reaches_the_compiler(monkeypatch):
    # the program caches (ours, PoCL's) are keyed on the source: an included file's edit
    # must change it, and the build log names the file and line it is about
    require("opencl")
    real = kernel_source.read_kernel
    edited = {"collide.cl": real("collide.cl") + "\nno_such_type broken;\n"}
    monkeypatch.setattr(kernel_source, "read_kernel", lambda name: edited.get(name) or real(name))
    with pytest.raises(ClothbenchError) as e:
        create_backend("opencl", sphere(8), VERLET, BackendOptions(strict=True, generic=True))
    assert_names_the_place(
        str(e.value), "collide.cl", edited["collide.cl"], "no_such_type broken;", "unknown type name 'no_such_type'"
    )


def assert_names_the_place(message: str, filename: str, text: str, broken: str, error: str) -> None:
    """The build error `message` names `filename`, the line of `text` (the file's content)
    that is `broken`, and the compiler's `error` there, in either runtime's form (PoCL's
    "error: file:line:col: ...", Intel's "file:line:col: error: ...": build_log.py)."""
    line = text.splitlines().index(broken) + 1
    assert message.startswith("OpenCL build failed on "), message
    assert (filename, line, error) in error_places(message), message


def split_shape(scene, options: BackendOptions) -> BackendOptions:
    """`options` with the interior + border kernel pair (the shape named by its width alone)."""
    from clothbench.backends.opencl.verlet import OpenCLBackend

    name = next(s for s in OpenCLBackend.kernel_shapes(scene, options) if s.startswith("v"))
    return BackendOptions(**{**options.__dict__, "shape": name})


def test_a_second_backend_of_the_same_key_builds_nothing(monkeypatch):
    require("opencl")
    built = []
    real_program = device.import_pyopencl().Program
    monkeypatch.setattr(device.import_pyopencl(), "Program", lambda *a: built.append(a) or real_program(*a))
    scene = every_collider_scene(29)  # a grid no other test builds
    split = split_shape(scene, STRICT)
    # the interior kernel is built at the device's preferred width P, the border at 1: two
    # programs, or one where P is 1 (Intel's runtime), the same options serving both
    width = parse_shape(split.shape).width
    with create_backend("opencl", scene, VERLET, split) as first:
        assert len(built) == len({width, 1}), f"interior (v{width}) and border (v1) programs, built once each"
        assert len({options for options in first.key}) == len(built), first.key
    with create_backend("opencl", scene.replace(stiffness=800.0), VERLET.replace(dt=4e-4), split) as second:
        pass  # the numbers are arguments: same key, no build
    assert len(built) == len({width, 1})
    assert second.programs == first.programs and second.key == first.key
    # generic: one program for every scene, whatever its grid or colliders
    generic = [
        create_backend("opencl", s, VERLET, BackendOptions(strict=True, generic=True)) for s in (scene, sphere(31))
    ]
    assert generic[0].programs == generic[1].programs and len(built) <= len({width, 1}) + 1
    for b in generic:
        b.close()


def test_more_colliders_than_the_constant_buffer_holds_are_refused():
    require("opencl")
    with create_backend("opencl", sphere(8), VERLET, FAST) as b:
        rows = b._device.max_constant_buffer_size // 16 + 1
    scene = sphere(8).replace(spheres=(Sphere((0.0, 0.0, 0.0), 0.1),) * rows)
    with pytest.raises(ClothbenchError, match=rf"{rows} colliders take .* constant buffer; use fewer"):
        create_backend("opencl", scene, VERLET, BackendOptions(generic=True))


@pytest.mark.parametrize("strict", [True, False])
@pytest.mark.parametrize("n", [3, 5, 20, 21, 37])
def test_specialised_step_writes_every_particle_once(n, strict):
    # The split shape divides the grid between an interior kernel (V particles per work
    # item, the last vector of a row overlapping) and a border kernel, the rows shapes mask
    # a row's last vector lane by lane; in every shape the previous position
    # written for every particle must be exactly the position it had, so none is missed.
    require("opencl")
    scene = sphere(n)
    pos, prev = scene.initial_state(np.float32)
    pos = pos.copy()
    pos[:, :3] += np.random.default_rng(n).normal(0, 1e-3, (n * n, 3)).astype(np.float32)
    from clothbench.backends.opencl.verlet import OpenCLBackend

    for ls in (None, 7):
        options = BackendOptions(strict=strict, local_size=ls)
        for shape in OpenCLBackend.kernel_shapes(scene, options):  # the rows kernels mask the edges instead
            with create_backend(
                "opencl", scene, VERLET, BackendOptions(strict=strict, local_size=ls, shape=shape)
            ) as b:
                b.upload(pos, prev)
                b.advance(1)
                assert_bit_exact(b.read()[1], pos, f"prev after one step, n={n} ls={ls} shape={shape}")


def test_kernel_rejects_a_wrongly_typed_argument():
    # The chapter (section 22.8): a float passed where the kernel wants an int failed
    # silently. Every argument has a declared dtype, so the wrapper refuses it instead.
    require("opencl")
    with create_backend("opencl", sphere(16), VERLET, split_shape(sphere(16), FAST)) as b:
        b.upload(*b.initial_state())
        border = b.kernels[-1]
        pos, prev, pos_out, prev_out = b._state
        good = [pos, prev, b._inv_mass, pos_out, prev_out, *b._constants, b._colliders, b._border]
        count = np.int32(1)
        border(b.queue, (1,), None, *good, count).wait()  # well typed: runs
        with pytest.raises(Exception, match=r"arg#14 \(1-based\)"):
            border(b.queue, (1,), None, *good, 3.5)  # a float for `const int count`
        with pytest.raises(Exception, match=r"arg#6 \(1-based\)"):
            border(b.queue, (1,), None, *good[:5], b._border, *good[6:], count)  # a buffer for k
        with pytest.raises(Exception, match=r"arg#1 \(1-based\)"):
            border(b.queue, (1,), None, np.float32(3.0), *good[1:], count)  # a float for a pointer


def test_build_error_shows_the_compiler_log(monkeypatch):
    require("opencl")
    source = read_kernel(opencl.KERNEL_FILE) + "\nfloat broken(void) { return no_such_value; }\n"
    monkeypatch.setattr(device, "read_kernel", lambda name: source)
    with pytest.raises(ClothbenchError) as e:
        create_backend("opencl", sphere(8), VERLET, STRICT)
    message = str(e.value)
    assert "-DCLOTH_STRICT" in message, "the message names the build options"
    assert_names_the_place(
        message,
        opencl.KERNEL_FILE,
        source,
        "float broken(void) { return no_such_value; }",
        "use of undeclared identifier 'no_such_value'",
    )


@pytest.fixture
def fresh_availability():
    """The registry caches probe results: clear them around a test that fakes the machine."""
    availability.cache_clear()
    yield
    availability.cache_clear()


def test_missing_platform_is_a_clear_unavailable(monkeypatch, fresh_availability, capsys):
    pyopencl = pytest.importorskip("pyopencl")
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setattr(pyopencl, "get_platforms", lambda: [])
    with pytest.raises(BackendUnavailable, match=r"^opencl unavailable: no OpenCL platform found \("):
        create_backend("opencl", sphere(8), VERLET)
    assert main(["run", "--backend", "opencl", "--grid", "8", "--steps", "2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "opencl unavailable: no OpenCL platform found (pip install" in err


def test_missing_pyopencl_says_what_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyopencl", None)  # import pyopencl raises ImportError
    a = opencl.probe()
    assert not a.usable
    assert a.reason.startswith("pyopencl not installed (pip install pyopencl")


def test_device_that_cannot_compile_is_not_usable(monkeypatch):
    # PoCL 3.0 (LLVM 14) lists CPUs newer than its LLVM and then fails every build with
    # "unknown target CPU 'generic'": listed is not usable, and the reason names the fix.
    require("opencl")
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    monkeypatch.setattr(device, "_PROBE_SOURCE", "__kernel void k(void) { undeclared_thing; }")
    a = opencl.probe()
    assert not a.usable
    assert a.reason.startswith("no OpenCL device here can compile a kernel (")
    assert "undeclared identifier 'undeclared_thing'" in a.reason, a.reason


def test_unknown_device_lists_the_devices_there_are():
    require("opencl")
    with pytest.raises(ClothbenchError, match=r"no OpenCL device '9:9' .*here: 0:0 "):
        create_backend("opencl", sphere(8), VERLET, BackendOptions(device="9:9"))


def test_mode_names_what_changes_speed_or_results():
    require("opencl")
    with create_backend("opencl", sphere(16), VERLET, STRICT) as b:  # + the kernel shape
        assert b.mode == f"strict/resident/ls=auto/{b.shape}"
    with create_backend("opencl", sphere(16), VERLET, BackendOptions(transfer="per-step", local_size=4)) as b:
        assert b.mode == f"fast/per-step/ls=4/{b.shape}"
    with create_backend("opencl", sphere(16), VERLET, BackendOptions(strict=True, generic=True)) as b:
        assert b.mode == "strict/generic/resident/ls=auto"
    with create_backend("opencl", sphere(16), VERLET, BackendOptions(normals=True, generic=True)) as b:
        assert b.mode == "fast/normals/generic/resident/ls=auto"
    assert opencl.OpenCLBackend.capabilities.generic, "the sweep measures --generic beside the default"


def test_profiling_events_time_the_last_advance():
    require("opencl")
    with create_backend("opencl", sphere(32), VERLET, FAST) as b:
        assert b.device_elapsed_ms() is None  # nothing advanced yet
        b.upload(*b.initial_state())
        b.advance(3)
        b.synchronize()
        assert b.device_elapsed_ms() > 0
        assert len(b._events) == 3 * len(b._launches), "one event per kernel launch"


def test_cli_strict_run_saves_the_numpy_f32_arrays(tmp_path):
    # As a user runs it, at a smaller size: the saved files are identical.
    require("opencl")
    common = ["run", "--scene", "sphere", "--grid", "16", "--steps", "60"]
    s, n = tmp_path / "s.npz", tmp_path / "n.npz"
    assert main(common + ["--backend", "opencl", "--strict", "--save", str(s)]) == 0
    assert main(common + ["--backend", "numpy", "--precision", "f32", "--save", str(n)]) == 0
    with np.load(s) as a, np.load(n) as b:
        for key in ("pos", "prev"):
            assert_bit_exact(a[key], b[key], key)
