"""The native `c` backend beyond the contract (tests/contract/ runs it in float32): strict
float64 is NumPy float64 bit for bit, so the float64 reference may be stepped by it; fast mode
is within float32's own error of NumPy float64; no compiler means one line, not a traceback;
a library is cached per set of build flags; the thread count changes no bit."""

from __future__ import annotations

import numpy as np
import pytest

from clothbench import native
from clothbench.backends import BackendOptions, availability, create_backend
from clothbench.cli import main
from clothbench.errors import ClothbenchError
from clothbench.harness import simulate
from clothbench.harness.simulate import position_error, reference
from clothbench.model.scene import load_scene

from conftest import VERLET, assert_bit_exact, every_collider_scene, require

F64 = BackendOptions(precision="f64")
STRICT_F64 = BackendOptions(precision="f64", strict=True)


def scene_named(name: str, n: int = 32):
    return every_collider_scene(n) if name == "all-kinds" else load_scene(name).replace(grid=n)


def forget_compiler() -> None:
    """Drop what this process remembers about the compiler and the c backend's probe."""
    native.compiler.cache_clear()
    availability.cache_clear()
    reference.cache_clear()


@pytest.fixture
def no_compiler(monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/clothbench-test-cc")
    forget_compiler()
    yield
    monkeypatch.undo()
    forget_compiler()


# --- float64: NumPy's bits --------------------------------------------------------------------


@pytest.mark.parametrize("steps", [1, 500])  # 500: after contact with every collider
@pytest.mark.parametrize("scene_name", ["sphere", "drape", "curtain", "cylinder", "all-kinds"])
def test_strict_f64_matches_numpy_f64_bit_for_bit(scene_name, steps):
    require("c")
    scene = scene_named(scene_name)
    got = simulate("c", scene, VERLET, steps, STRICT_F64)
    want = simulate("numpy", scene, VERLET, steps, F64)  # not reference(): that may be c itself
    assert got[0].dtype == np.float64
    assert_bit_exact(got[0], want[0], f"pos, c strict f64 {scene_name} steps={steps}")
    assert_bit_exact(got[1], want[1], f"prev, c strict f64 {scene_name} steps={steps}")


@pytest.mark.parametrize("precision", ["f64"])  # f32: tests/contract/test_verlet_contract.py, every backend
@pytest.mark.parametrize("n", [3, 4, 5, 6, 37])
def test_strict_holds_on_grids_with_little_or_odd_interior(n, precision):
    # n < 5 has no interior at all (border code only); 37 leaves a ragged SIMD remainder
    require("c")
    scene = every_collider_scene(n)
    got = simulate("c", scene, VERLET, 200, BackendOptions(precision=precision, strict=True))
    want = simulate("numpy", scene, VERLET, 200, BackendOptions(precision=precision))
    assert_bit_exact(got[0], want[0], f"pos n={n} {precision}")
    assert_bit_exact(got[1], want[1], f"prev n={n} {precision}")


def test_the_f64_reference_is_numpy_f64_bit_for_bit():
    # reference(.., "f64") steps the c backend when it can run; the switch must change no bit
    require("c")
    scene = every_collider_scene(24)
    reference.cache_clear()
    ref = reference(scene, VERLET, 300, "f64")
    want = simulate("numpy", scene, VERLET, 300, F64)
    assert_bit_exact(ref[0], want[0], "reference pos")
    assert_bit_exact(ref[1], want[1], "reference prev")


def test_a_converged_references_levels_are_stepped_by_c_with_numpys_bits(monkeypatch, reference_steppers):
    # accuracy's converged float64 references (dt halved level by level) go through reference_states,
    # so c steps them where it takes the scene: the same extrapolation from the same bits as NumPy's
    import importlib

    from clothbench.analysis.convergence import converged_reference

    require("c")
    scene, solver = every_collider_scene(12), VERLET.replace(dt=4e-4)
    by_c = converged_reference(scene, solver, 0.02, 4e-4, max_levels=3)
    assert set(reference_steppers) == {"c"} and len(reference_steppers) == 4  # dt_finest and three halvings
    runs = importlib.import_module("clothbench.harness.simulate")  # the module, not its function
    monkeypatch.setattr(runs, "C_REFERENCE_SOLVERS", ())
    reference.cache_clear()
    by_numpy = converged_reference(scene, solver, 0.02, 4e-4, max_levels=3)
    assert reference_steppers[4:] == ["numpy"] * 4
    assert_bit_exact(by_c.pos, by_numpy.pos, "converged reference pos, c against numpy")
    same = ("levels", "converged", "uncertainty")
    assert [getattr(by_c, f) for f in same] == [getattr(by_numpy, f) for f in same]


def test_the_f64_reference_falls_back_to_numpy_without_a_compiler(no_compiler):
    scene = every_collider_scene(12)
    assert not availability("c").usable
    ref = reference(scene, VERLET, 50, "f64")
    assert_bit_exact(ref[0], simulate("numpy", scene, VERLET, 50, F64)[0], "reference pos without c")


# --- fast: float32's own error ------------------------------------------------------------------


@pytest.mark.parametrize("scene_name", ["sphere", "drape", "all-kinds"])
def test_fast_f32_is_within_float32_error_of_numpy_f64(scene_name):
    # Before contact (100 steps) NumPy float32 is ~9e-6 m from float64 at n = 32, nearly all
    # of it the float32 rounding of the start and the constants, which fast mode shares; its
    # own contraction and summation order add O(1e-7 relative) per step. Tolerance: 2x NumPy
    # float32's distance and below 5e-5 m; a physics slip (one damping term lost per particle,
    # a wrong rest length) is 5x-25x (tests/contract/test_verlet_contract.py).
    require("c")
    scene, steps = scene_named(scene_name), 100
    ref64 = simulate("numpy", scene, VERLET, steps, F64)[0]
    _, f32_max = position_error(simulate("numpy", scene, VERLET, steps, BackendOptions())[0], ref64)
    fast = simulate("c", scene, VERLET, steps, BackendOptions(strict=False))[0]
    strict = simulate("c", scene, VERLET, steps, BackendOptions(strict=True))[0]
    assert not np.array_equal(fast, strict), "fast mode ran the strict arithmetic"
    _, fast_max = position_error(fast, ref64)
    assert fast_max <= min(2 * f32_max, 5e-5), f"c fast {fast_max:.3g} m vs numpy f32 {f32_max:.3g} m"


def test_fast_f64_is_within_float64_error_of_numpy_f64():
    # contraction only changes the last bits of float64: 100 steps stay within 1e-12 m
    require("c")
    scene = every_collider_scene(32)
    fast = simulate("c", scene, VERLET, 100, BackendOptions(precision="f64"))[0]
    _, worst = position_error(fast, simulate("numpy", scene, VERLET, 100, F64)[0])
    assert worst <= 1e-12, f"c fast f64 is {worst:.3g} m from numpy f64"


# --- threads ------------------------------------------------------------------------------------


@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
def test_the_thread_count_changes_no_bit(monkeypatch, strict):
    # rows are split among threads; no particle's arithmetic depends on which thread did it
    require("c")
    scene = every_collider_scene(29)
    states = {}
    for count in ("1", "2", "3"):
        monkeypatch.setenv("OMP_NUM_THREADS", count)
        with create_backend("c", scene, VERLET, BackendOptions(strict=strict)) as b:
            assert b.mode.endswith(f"/threads={count}") and b.threads == int(count), b.mode
            b.upload(*b.initial_state())
            b.advance(150)
            states[count] = b.read()
    for count in ("2", "3"):
        assert_bit_exact(states[count][0], states["1"][0], f"pos with {count} threads")
        assert_bit_exact(states[count][1], states["1"][1], f"prev with {count} threads")


def test_a_bad_thread_count_is_one_line(monkeypatch):
    require("c")
    monkeypatch.setenv("OMP_NUM_THREADS", "many")
    availability.cache_clear()
    try:
        a = availability("c")
        assert not a.usable and a.reason == "OMP_NUM_THREADS must be a positive integer, got 'many'"
    finally:
        monkeypatch.undo()
        availability.cache_clear()


def test_steps_split_across_advances_give_the_same_bits():
    # the library ping-pongs its buffers by step parity: odd chunks must hand over correctly
    require("c")
    scene = every_collider_scene(16)
    with create_backend("c", scene, VERLET, BackendOptions(strict=True)) as b:
        b.upload(*b.initial_state())
        for chunk in (1, 3, 0, 2, 7, 1):
            b.advance(chunk)
        got = b.read()
    want = simulate("numpy", scene, VERLET, 14, BackendOptions())
    assert_bit_exact(got[0], want[0], "pos after chunks 1+3+0+2+7+1")
    assert_bit_exact(got[1], want[1], "prev after chunks 1+3+0+2+7+1")


# --- no compiler, and the build cache -----------------------------------------------------------


def test_without_a_compiler_the_probe_says_why(no_compiler):
    a = availability("c")
    assert not a.usable
    assert a.reason == native.no_compiler_reason() and "/nonexistent/clothbench-test-cc" in a.reason
    with pytest.raises(ClothbenchError, match="no C compiler found"):
        create_backend("c", scene_named("sphere", 8), VERLET)


def test_without_a_compiler_run_prints_one_line_and_fails(no_compiler, capsys):
    code = main(["run", "--backend", "c", "--grid", "8", "--steps", "3"])
    err = capsys.readouterr().err
    assert code != 0
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "no C compiler found" in lines[0], err
    assert "Traceback" not in err


def test_each_set_of_flags_is_its_own_cached_library(tmp_path, monkeypatch):
    require("c")
    from clothbench.backends.c.verlet import build_flags

    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    scene = scene_named("sphere", 8)
    strict, fast = build_flags(scene, "f32", True), build_flags(scene, "f32", False)
    assert strict != fast
    native.build_library("verlet_cloth.c", strict)
    native.build_library("verlet_cloth.c", fast)
    built = sorted(p.name for p in (tmp_path / "native").glob("verlet_cloth-*.so"))
    assert len(built) == 2, built
    native.build_library("verlet_cloth.c", strict)  # the same flags again: from the cache
    assert sorted(p.name for p in (tmp_path / "native").glob("verlet_cloth-*.so")) == built
    other_grid = build_flags(scene.replace(grid=9), "f32", True)
    native.build_library("verlet_cloth.c", other_grid)
    assert len(list((tmp_path / "native").glob("verlet_cloth-*.so"))) == 3, "the grid side is a -D constant"


def _step_in_child(conn) -> None:
    scene = every_collider_scene(16)
    with create_backend("c", scene, VERLET, BackendOptions(strict=True)) as b:
        b.upload(*b.initial_state())
        b.advance(40)
        conn.send((b.mode, b.read()[0]))


def test_a_child_forked_after_openmp_ran_still_steps(monkeypatch):
    # GNU libgomp hangs in such a child; the backend steps it on one thread instead
    import multiprocessing

    require("c")
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # the parent surely runs a parallel region
    scene = every_collider_scene(16)
    want = simulate("c", scene, VERLET, 40, BackendOptions(strict=True))[0]
    context = multiprocessing.get_context("fork")
    mine, theirs = context.Pipe()
    child = context.Process(target=_step_in_child, args=(theirs,))
    child.start()
    try:
        assert mine.poll(120), "the forked child did not finish its steps"
        mode, got = mine.recv()
    finally:
        child.join(5)
        if child.is_alive():
            child.kill()
    assert mode.endswith("/threads=1"), mode
    assert_bit_exact(got, want, "pos stepped in a forked child")


# --- the thread count as the kernel shape -------------------------------------------------------


def test_the_shapes_are_every_core_halving_to_one_unless_omp_num_threads_says(monkeypatch):
    require("c")
    from clothbench import environment
    from clothbench.backends.c.verlet import CBackend

    scene = scene_named("sphere", 8)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    shapes = CBackend.kernel_shapes(scene, BackendOptions())
    assert shapes[0] == f"threads={environment.cores()}" and shapes[-1] == "threads=1"
    assert len(set(shapes)) == len(shapes)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert CBackend.kernel_shapes(scene, BackendOptions()) == ("threads=3",)


def test_an_explicit_shape_runs_and_an_unknown_one_is_refused_in_one_line(monkeypatch):
    require("c")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    scene = every_collider_scene(20)
    got = simulate("c", scene, VERLET, 60, BackendOptions(strict=True, shape="threads=1"))
    assert_bit_exact(got[0], simulate("numpy", scene, VERLET, 60, BackendOptions())[0], "pos with --shape threads=1")
    with pytest.raises(ClothbenchError) as e:
        create_backend("c", scene, VERLET, BackendOptions(shape="threads=999"))
    assert "no kernel shape 'threads=999'" in str(e.value) and "\n" not in str(e.value)


def test_tuning_chooses_a_candidate_and_remembers_it(tmp_path, monkeypatch):
    require("c")
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setenv("CLOTHBENCH_CACHE", str(tmp_path))
    monkeypatch.setenv("CLOTHBENCH_TUNING", "on")
    scene = every_collider_scene(24)
    with create_backend("c", scene, VERLET, BackendOptions(strict=True)) as b:
        candidates = b.kernel_shapes(scene, b.options)
        assert b.shape in candidates and b.mode.endswith("/" + b.shape)
        b.upload(*b.initial_state())  # tuning stepped the start; the run starts over
        b.advance(30)
        got = b.read()
    assert_bit_exact(got[0], simulate("numpy", scene, VERLET, 30, BackendOptions())[0], f"pos with tuned {b.shape}")
    if len(candidates) > 1:
        assert (tmp_path / "tuning" / "c.json").is_file(), "the choice is cached for the next run"


# --- the interior loop is SIMD ------------------------------------------------------------------


@pytest.mark.parametrize("precision", ["f32", "f64"])
@pytest.mark.parametrize("strict", [True, False], ids=["strict", "fast"])
@pytest.mark.parametrize("scene_name", ["drape", "sphere", "all-kinds", "fold"])  # fold: with the pass
def test_gcc_vectorises_the_interior_loop(scene_name, strict, precision):
    # Not a timing: whether GCC reports the interior loop vectorised, for every collider kind.
    # It silently stops when a value is loaded only under a condition (a masked load GCC 12
    # cannot vectorise here); the step then runs scalar, slower (docs/c.md), with the same results.
    import re
    import subprocess

    from clothbench.backends.c.verlet import build_flags
    from clothbench.kernel_source import kernel_path

    require("c")
    cc = native.compiler()
    if "clang" in cc.version.lower():
        pytest.skip(f"GCC's -fopt-info report is what is read here; the compiler is {cc.version}")
    source = kernel_path("verlet_cloth.c")
    lines = source.read_text().splitlines()
    # GCC names the loop by the first line of the inlined body, or by the `for` line
    first = next(i for i, line in enumerate(lines, 1) if line.startswith("INLINE void interior_particle"))
    last = next(i for i, line in enumerate(lines, 1) if i > first and line == "}")
    loop = next(i for i, line in enumerate(lines, 1) if "interior_particle(&local" in line) - 1
    assert lines[loop - 1].lstrip().startswith("for ("), "the interior loop is the line above its call"
    flags = build_flags(scene_named(scene_name), precision, strict)
    out = subprocess.run(
        [cc.path, *flags, "-fopt-info-vec-optimized", "-S", "-o", "/dev/null", str(source)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    found = re.findall(rf"{re.escape(source.name)}:(\d+):\d+: optimized: loop vectorized", out.stderr)
    assert any(first <= int(n) <= last or int(n) == loop for n in found), (
        f"the interior loop (lines {first}-{last}, {loop}) is not vectorised:\n{out.stderr}"
    )


# --- a busy machine: the threads the others leave free -----------------------------------


class _SeenLoad:
    """A LoadSampler whose sample() reports `other_cores` of 2 cores used by others."""

    def __init__(self, other_cores: float):
        self.other_cores = other_cores

    def sample(self, seconds):
        from clothbench.machine_load import BUSY_CORES, Load

        busy = self.other_cores >= BUSY_CORES
        return Load(seconds, 2, self.other_cores, self.other_cores / 2, 0.0, busy, f"other {self.other_cores}")


@pytest.mark.parametrize(
    "other_cores, options, tuning, threads",
    [
        (1.0, BackendOptions(), "on", 1),  # one core taken: one thread, not two waiting at each barrier
        (1.9, BackendOptions(), "on", 1),  # both nearly taken: still one, never none
        (0.1, BackendOptions(), "on", 2),  # quiet: the tuned two
        (1.0, BackendOptions(shape="threads=2"), "on", 2),  # the user's --shape stands
        (1.0, BackendOptions(), "off", 2),  # tuning off (the suite's default shapes): no watch at all
    ],
)
def test_a_run_that_starts_on_a_busy_machine_takes_the_threads_left_free(
    monkeypatch, other_cores, options, tuning, threads
):
    require("c")
    from clothbench import environment, machine_load
    from clothbench.backends import tuning as tuning_module

    monkeypatch.setenv("CLOTHBENCH_TUNING", tuning)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(environment, "cores", lambda: 2)
    monkeypatch.setattr(tuning_module, "choose_shape", lambda backend, key, candidates, time, retune=False: "threads=2")
    monkeypatch.setattr(machine_load, "LoadSampler", lambda *a, **k: _SeenLoad(other_cores))
    with create_backend("c", scene_named("sphere", 8), VERLET, options) as b:
        assert b.threads == threads and b.shape == f"threads={threads}"
        assert b.mode.endswith(f"threads={threads}"), b.mode
        if threads == 1:
            assert b.run_note == f"threads=1 for this run, not the tuned 2: the machine was busy (other {other_cores})"
        else:
            assert b.run_note == ""
        b.upload(*b.initial_state())
        b.advance(3)  # and it steps on them
        assert np.isfinite(b.read()[0]).all()


@pytest.mark.parametrize("other_cores, tuning, threads", [(1.0, "on", 1), (0.1, "on", 2), (1.0, "off", 2)])
def test_numba_takes_the_same_threads_left_free_on_a_busy_machine(monkeypatch, other_cores, tuning, threads):
    # the c backend's rule (machine_load.threads_left_free), for the peer whose threads can be set per run
    require("numba")
    import numba

    from clothbench import environment, machine_load

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba has one thread here: nothing to take away")
    monkeypatch.setenv("CLOTHBENCH_TUNING", tuning)
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    monkeypatch.setattr(environment, "cores", lambda: 2)
    monkeypatch.setattr(machine_load, "LoadSampler", lambda *a, **k: _SeenLoad(other_cores))
    usual = numba.get_num_threads()
    try:
        with create_backend("numba", scene_named("sphere", 8), VERLET, BackendOptions()) as b:
            b.upload(*b.initial_state())
            b.advance(2)
            assert numba.get_num_threads() == threads and b.device == f"numba parallel ({threads} threads)"
            assert ("for this run" in b.run_note) == (threads == 1), b.run_note
    finally:
        numba.set_num_threads(usual)  # the count is the calling thread's: give it back to later tests
