"""The `c` backend's VBD solver beyond tests/contract/test_vbd_contract.py (which runs strict
float32 on 24^2 and fast float32): strict float64 is NumPy float64 bit for bit; grids whose
colours leave no or odd interior columns, with substeps and Chebyshev, on every thread count;
one step per advance gives the same bits; GCC vectorises the interior loop of a colour; the
Verlet library compiles none of it."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench import native
from clothbench.backends import BackendOptions, create_backend
from clothbench.backends.c.verlet import CBackend, build_flags
from clothbench.harness import reference, simulate
from clothbench.kernel_source import kernel_path, read_kernel, resolve_includes
from clothbench.model.scene import load_scene
from clothbench.model.solver import Vbd

from conftest import assert_bit_exact, every_collider_scene, require

AT_60HZ = 1 / 60


def scene_named(name: str, n: int):
    return every_collider_scene(n) if name == "all-kinds" else load_scene(name).replace(grid=n)


@pytest.mark.parametrize("scene_name", ["curtain", "all-kinds"])
def test_strict_f64_vbd_matches_numpy_f64_bit_for_bit(scene_name):
    require("c")
    scene, solver = scene_named(scene_name, 16), Vbd(dt=AT_60HZ, chebyshev_rho=0.9)
    want = simulate("numpy", scene, solver, 100, BackendOptions(precision="f64"))
    got = simulate("c", scene, solver, 100, BackendOptions(precision="f64", strict=True))
    assert got[0].dtype == np.float64
    assert_bit_exact(got[0], want[0], f"pos, c strict f64 vbd {scene_name}")
    assert_bit_exact(got[1], want[1], f"prev, c strict f64 vbd {scene_name}")


def test_the_f64_vbd_reference_is_stepped_by_c_and_is_numpy_f64_bit_for_bit(reference_steppers):
    # reference(.., "f64") steps c's VBD where it takes the scene (the accuracy study's converged
    # references were hours of NumPy's colour loop); the switch must change no bit
    require("c")
    scene, solver = scene_named("all-kinds", 12), Vbd(dt=AT_60HZ, iterations=6, substeps=2, chebyshev_rho=0.9)
    ref = reference(scene, solver, 40, "f64")
    assert reference_steppers == ["c"]
    want = simulate("numpy", scene, solver, 40, BackendOptions(precision="f64"))
    assert_bit_exact(ref[0], want[0], "reference pos, vbd")
    assert_bit_exact(ref[1], want[1], "reference prev, vbd")


def test_fast_f64_vbd_is_within_float64_error_of_numpy_f64():
    # contraction and one 1/sqrt per spring: measured 1.5e-13 m at most after 40 steps of the
    # 24^2 sheet across every collider; 1e-9 m leaves room for contact to amplify it and is
    # still far below anything a wrong operation gives (millimetres)
    require("c")
    scene, solver = scene_named("all-kinds", 16), Vbd(dt=AT_60HZ)
    want = simulate("numpy", scene, solver, 60, BackendOptions(precision="f64"))[0]
    got = simulate("c", scene, solver, 60, BackendOptions(precision="f64"))[0]
    assert np.abs(got[:, :3] - want[:, :3]).max() < 1e-9


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("n", [3, 4, 5, 6, 7, 13])  # 3, 4: no interior row; 5-7: one column or none of a colour
def test_strict_vbd_holds_on_grids_with_little_or_odd_interior(n, precision):
    require("c")
    scene = scene_named("all-kinds", n)
    solver = Vbd(dt=AT_60HZ, iterations=3, substeps=2, chebyshev_rho=0.9)
    want = simulate("numpy", scene, solver, 30, BackendOptions(precision=precision))
    options = BackendOptions(precision=precision, strict=True)
    for shape in CBackend.kernel_shapes(scene, options, solver):
        got = simulate("c", scene, solver, 30, BackendOptions(precision=precision, strict=True, shape=shape))
        assert_bit_exact(got[0], want[0], f"pos, c strict {precision} vbd n={n} {shape}")
        assert_bit_exact(got[1], want[1], f"prev, c strict {precision} vbd n={n} {shape}")


@pytest.mark.parametrize("precision", ["f32", "f64"])
def test_vbd_steps_one_advance_at_a_time_give_the_same_bits(precision):
    # one parallel region per advance: at 4^2 in float64 a thread's rows are one 64-byte
    # vector, where GCC's predictive commoning once wrote back other threads' rows (see
    # kernels/vbd_cloth.c update_rows); it showed in some runs only, so several are run
    require("c")
    scene, solver = scene_named("all-kinds", 4), Vbd(dt=AT_60HZ, iterations=2, substeps=2, chebyshev_rho=0.9)
    want = simulate("numpy", scene, solver, 30, BackendOptions(precision=precision))
    options = BackendOptions(precision=precision, strict=True)
    for shape in CBackend.kernel_shapes(scene, options, solver):
        for run in range(4):
            with create_backend("c", scene, solver, BackendOptions(precision=precision, strict=True, shape=shape)) as b:
                b.upload(*b.initial_state())
                for _ in range(30):
                    b.advance(1)
                got = b.read()
            for g, w, what in zip(got, want, ("pos", "prev")):
                assert_bit_exact(g, w, f"{what}, {precision} {shape} run {run}, 30 advances of one step")


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
@pytest.mark.parametrize("scene_name", [pytest.param("drape", marks=pytest.mark.full), "all-kinds"])  # no colliders too
def test_gcc_vectorises_the_interior_loop_of_a_colour(scene_name, strict, precision):
    # Not a timing: whether GCC reports the loop vectorised. It stops silently when a lane
    # that keeps its value becomes a masked store at stride 2 (kernels/vbd_cloth.c sweep_row)
    # or when a value is loaded only under a condition; the sweep then runs scalar.
    import re
    import subprocess

    require("c")
    cc = native.compiler()
    if "clang" in cc.version.lower():
        pytest.skip(f"GCC's -fopt-info report is what is read here; the compiler is {cc.version}")
    source = kernel_path("vbd_cloth.c")
    lines = source.read_text().splitlines()
    loop = next(i for i, line in enumerate(lines, 1) if "vbd_particle(&local, 1" in line) - 1
    assert lines[loop - 1].lstrip().startswith("for ("), "the interior loop is the line above its call"
    flags = build_flags(scene_named(scene_name, 32), precision, strict)
    command = [cc.path, *flags, "-I", str(source.parent), "-fopt-info-vec-optimized", "-S", "-o", "/dev/null"]
    out = subprocess.run([*command, str(source)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    found = re.findall(rf"{re.escape(source.name)}:(\d+):\d+: optimized: loop vectorized", out.stderr)
    # GCC names it by its `for` line or by the call's (the first line of the inlined body)
    assert any(int(n) in (loop, loop + 1) for n in found), (
        f"the interior loop (line {loop}) is not vectorised:\n{out.stderr}"
    )


def test_the_verlet_library_compiles_none_of_vbd():
    # the VBD kernel includes the Verlet one, never the other way: a Verlet build is the same
    # source (and cached library) it was before VBD
    source = resolve_includes("verlet_cloth.c", read_kernel("verlet_cloth.c"), lambda *_: "")[0]
    assert "vbd" not in source.lower()


def test_an_edit_to_any_file_the_vbd_kernel_includes_is_a_new_tuning_key(monkeypatch):
    # the thread count was measured on vbd_cloth.c and what it includes: an edit to vbd_newton.h
    # (or verlet_cloth.c) must measure again, as an edit to vbd_cloth.c does
    require("c")
    from clothbench import kernel_source

    with create_backend("c", load_scene("drape").replace(grid=8), Vbd(), BackendOptions()) as b:
        before = b._tuning_key()
        assert b._tuning_key() == before and "planes" not in before  # the text, nothing else
        original = kernel_source.read_kernel
        for name in ("vbd_newton.h", "verlet_cloth.c", "vbd_cloth.c"):
            monkeypatch.setattr(
                kernel_source, "read_kernel", lambda n, name=name: original(n) + ("//\n" if n == name else "")
            )
            assert b._tuning_key()["kernel"] != before["kernel"], name
