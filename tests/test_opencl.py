"""The OpenCL backend (kernels/verlet_cloth.cl) against the NumPy reference (docs/semantics.md)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from clothbench.backends import BackendOptions, availability, create_backend
from clothbench.backends import opencl
from clothbench.cli import main
from clothbench.errors import BackendUnavailable, ClothbenchError
from clothbench.harness import position_error, reference, simulate
from clothbench.scene import Plane, load_scene
from conftest import assert_bit_exact, require

STRICT = BackendOptions(strict=True)
FAST = BackendOptions()


def sphere(n: int):
    return load_scene("sphere").replace(grid=n)


@pytest.mark.parametrize("n", [32, 64])
@pytest.mark.parametrize("steps", [1, 500])
def test_opencl_strict_matches_numpy_f32_bit_for_bit(n, steps):
    # Same operations in the same order, no contraction: IEEE rounding leaves no room.
    # (Without the kernel's FP_CONTRACT OFF pragma, PoCL fuses and 16 values already differ
    # after one step at n = 32.) 500 steps include the contact with the sphere.
    require("opencl")
    scene = sphere(n)
    pos, prev = simulate("opencl", scene, steps, STRICT)
    ref_pos, ref_prev = reference(scene, steps, "f32")
    assert_bit_exact(pos, ref_pos, f"pos n={n} steps={steps}")
    assert_bit_exact(prev, ref_prev, f"prev n={n} steps={steps}")


@pytest.mark.parametrize("scene_name", ["sphere", "drape"])
@pytest.mark.parametrize("n", [32, 64])
def test_opencl_fast_error_is_of_the_order_of_numpy_f32s_own(scene_name, n):
    # Fast mode rounds differently from the reference: FMA contraction (fewer roundings),
    # rsqrt instead of sqrt and a division (a few ulp), damping summed once per particle.
    # Each is an O(float32 epsilon) perturbation per operation, like the reference's own
    # roundings, so over a short horizon (100 steps: before the contact with the sphere,
    # while the drape's pinned corners take the load) its distance to the float64 reference
    # must be of the order of the NumPy float32 distance. Measured here: ratio 1.00. The
    # bound 2x still catches a physics slip: an interior damping count of 11 instead of 12
    # gives 5x, a wrong bend rest length 25x.
    require("opencl")
    scene = load_scene(scene_name).replace(grid=n)
    steps = 100
    ref64 = reference(scene, steps, "f64")[0]
    _, f32_max = position_error(reference(scene, steps, "f32")[0], ref64)
    pos, _ = simulate("opencl", scene, steps, FAST)
    _, fast_max = position_error(pos, ref64)
    assert fast_max <= 2 * f32_max, f"fast {fast_max:.3g} m vs numpy f32 {f32_max:.3g} m"


@pytest.mark.parametrize("strict", [True, False])
def test_per_step_transfer_equals_resident_bit_for_bit(strict):
    # The chapter's upload-every-step variant moves the same bits; it only costs time.
    require("opencl")
    scene = sphere(32)
    resident = simulate("opencl", scene, 50, BackendOptions(strict=strict))
    per_step = simulate("opencl", scene, 50, BackendOptions(strict=strict, transfer="per-step"))
    for a, b, what in zip(per_step, resident, ("pos", "prev")):
        assert_bit_exact(a, b, f"{what} strict={strict}")


@pytest.mark.parametrize("n", [3, 5, 20, 21, 37])
def test_fast_mode_writes_every_particle_once_per_step(n):
    # The fast step splits the grid between an interior kernel (V particles per work item,
    # the last vector of a row overlapping) and a border kernel; the previous position
    # written for every particle must be exactly the position it had, so none is missed.
    require("opencl")
    scene = sphere(n)
    pos, prev = scene.initial_state(np.float32)
    pos = pos.copy()
    pos[:, :3] += np.random.default_rng(n).normal(0, 1e-3, (n * n, 3)).astype(np.float32)
    for ls in (None, 7):
        with create_backend("opencl", scene, BackendOptions(local_size=ls)) as b:
            b.upload(pos, prev)
            b.advance(1)
            assert_bit_exact(b.read()[1], pos, f"prev after one step, n={n} ls={ls}")


def test_work_group_size_changes_no_result():
    # 7 divides neither n*n nor the interior: the launches are padded and the kernels return
    # early past their last item. Strict stays bit-exact; fast stays bit-identical to itself.
    require("opencl")
    scene = sphere(24)
    assert_bit_exact(
        simulate("opencl", scene, 40, BackendOptions(strict=True, local_size=7))[0],
        reference(scene, 40, "f32")[0],
        "strict ls=7",
    )
    assert_bit_exact(
        simulate("opencl", scene, 40, BackendOptions(local_size=7))[0],
        simulate("opencl", scene, 40, FAST)[0],
        "fast ls=7",
    )


def test_kernel_rejects_a_wrongly_typed_argument():
    # The chapter (section 22.8): a float passed where the kernel wants an int failed
    # silently. Every argument has a declared dtype, so the wrapper refuses it instead.
    require("opencl")
    with create_backend("opencl", sphere(16), FAST) as b:
        b.upload(*b.scene.initial_state(np.float32))
        border = b.kernels[-1]
        pos, prev, pos_out, prev_out = b._state
        good = [pos, prev, b._inv_mass, pos_out, prev_out, b._spheres, *b._constants, b._border]
        count = np.int32(1)
        border(b.queue, (1,), None, *good, count).wait()  # well typed: runs
        with pytest.raises(Exception, match=r"arg#14 \(1-based\)"):
            border(b.queue, (1,), None, *good, 3.5)  # a float for `const int count`
        with pytest.raises(Exception, match=r"arg#7 \(1-based\)"):
            border(b.queue, (1,), None, *good[:6], b._border, *good[7:], count)  # a buffer for k
        with pytest.raises(Exception, match=r"arg#1 \(1-based\)"):
            border(b.queue, (1,), None, np.float32(3.0), *good[1:], count)  # a float for a pointer


def test_build_error_shows_the_compiler_log(monkeypatch):
    require("opencl")
    source = opencl.read_kernel(opencl.KERNEL_FILE) + "\nfloat broken(void) { return no_such_value; }\n"
    monkeypatch.setattr(opencl, "read_kernel", lambda name: source)
    with pytest.raises(ClothbenchError) as e:
        create_backend("opencl", sphere(8), STRICT)
    message = str(e.value)
    assert message.startswith("OpenCL build failed on ")
    assert "-DCLOTH_STRICT" in message, "the message names the build options"
    assert "no_such_value" in message and "undeclared identifier" in message, message


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
        create_backend("opencl", sphere(8))
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
    monkeypatch.setattr(opencl, "_PROBE_SOURCE", "__kernel void k(void) { undeclared_thing; }")
    a = opencl.probe()
    assert not a.usable
    assert a.reason.startswith("no OpenCL device here can compile a kernel (")
    assert "undeclared identifier 'undeclared_thing'" in a.reason, a.reason


def test_unknown_device_lists_the_devices_there_are():
    require("opencl")
    with pytest.raises(ClothbenchError, match=r"no OpenCL device '9:9' .*here: 0:0 "):
        create_backend("opencl", sphere(8), BackendOptions(device="9:9"))


@pytest.mark.parametrize(
    "options, message",
    [
        (BackendOptions(transfer="sometimes"), "transfer must be one of resident, per-step, got 'sometimes'"),
        (BackendOptions(precision="f64"), "opencl runs in f32 only"),
    ],
)
def test_bad_options_are_refused(options, message):
    require("opencl")
    with pytest.raises(ClothbenchError, match=message):
        create_backend("opencl", sphere(8), options)


def test_colliders_other_than_spheres_are_refused_not_ignored():
    require("opencl")
    scene = sphere(8).replace(planes=(Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0)),))
    with pytest.raises(ClothbenchError, match="spheres only so far"):
        create_backend("opencl", scene, FAST)


def test_mode_names_what_changes_speed_or_results():
    require("opencl")
    with create_backend("opencl", sphere(16), STRICT) as b:
        assert b.mode == "strict/resident/ls=auto"
    with create_backend("opencl", sphere(16), BackendOptions(transfer="per-step", local_size=4)) as b:
        assert b.mode == "fast/per-step/ls=4"


def test_profiling_events_time_the_last_advance():
    require("opencl")
    with create_backend("opencl", sphere(32), FAST) as b:
        assert b.device_elapsed_ms() is None  # nothing advanced yet
        b.upload(*b.scene.initial_state(np.float32))
        b.advance(3)
        b.synchronize()
        assert b.device_elapsed_ms() > 0
        assert len(b._events) == 3 * len(b._launches), "one event per kernel launch"


def test_cli_strict_run_saves_the_numpy_f32_arrays(tmp_path):
    # The must-show, at a smaller size: the saved files are identical.
    require("opencl")
    common = ["run", "--scene", "sphere", "--grid", "16", "--steps", "60"]
    s, n = tmp_path / "s.npz", tmp_path / "n.npz"
    assert main(common + ["--backend", "opencl", "--strict", "--save", str(s)]) == 0
    assert main(common + ["--backend", "numpy", "--precision", "f32", "--save", str(n)]) == 0
    with np.load(s) as a, np.load(n) as b:
        for key in ("pos", "prev"):
            assert_bit_exact(a[key], b[key], key)
