"""The machine's limits (kernels/machine_bounds.c) and the step bound they give
(clothbench/harness/bounds.py, docs/bounds.md). No timed assertion on the project's kernels:
only the measured limits are checked, for being positive, finite and plausible."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from clothbench import environment, native
from clothbench.errors import ClothbenchError
from clothbench.harness import bounds
from clothbench.harness.sweep_csv import fmt
from clothbench.model.scene import Cylinder, Plane, Sphere
from clothbench.model.solver import Pbd, Vbd, Verlet
from tests.conftest import sphere

pytestmark = pytest.mark.serial  # measures the machine's limits: one xdist worker

RATES = bounds.Rates(sqrt=1e10, div=1e10, sqrt_div=5e9, fp=1e11, rsqrt=2e10)


def fixed(bandwidth_gb_s: float = 20.0, rates: bounds.Rates = RATES) -> bounds.MachineBounds:
    """Limits given, not measured: what the counting tests need to be exact."""
    return bounds.MachineBounds(
        threads=2,
        triad_gb_s=bandwidth_gb_s,
        copy_gb_s=bandwidth_gb_s / 2,
        triad_pass_gb_s=bandwidth_gb_s / 2,
        copy_pass_gb_s=bandwidth_gb_s / 3,
        f32=rates,
        f64=rates,
        array_mib=1,
        compiler="test",
        seconds=0.0,
    )


def plain(n: int):
    """The sphere scene's sheet with no collider at all."""
    return sphere(n).replace(spheres=(), cylinders=(), planes=())


@pytest.fixture(scope="module")
def measured() -> bounds.MachineBounds:
    if native.compiler() is None:
        pytest.skip(native.no_compiler_reason())
    return bounds.measure_machine()


# --- the measurement -------------------------------------------------------------------


def test_measured_limits_are_positive_finite_and_plausible(measured):
    assert measured.threads == environment.cores()
    for gb_s in (measured.triad_gb_s, measured.copy_gb_s, measured.triad_pass_gb_s, measured.copy_pass_gb_s):
        assert math.isfinite(gb_s) and 0.5 <= gb_s <= 2000, measured.what()
    # a whole pass is made of chunks: never faster than its fastest one
    assert measured.triad_pass_gb_s <= measured.triad_gb_s and measured.copy_pass_gb_s <= measured.copy_gb_s
    assert measured.bandwidth_gb_s == max(measured.triad_gb_s, measured.copy_gb_s)
    # a CPU of this century on >= 1 core: 1e7 .. 1e13 operations per second of each kind
    for rates in (measured.f32, measured.f64):
        for value in (rates.sqrt, rates.div, rates.sqrt_div, rates.fp):
            assert math.isfinite(value) and 1e7 <= value <= 1e13, measured.what()
    assert 1e7 <= measured.f32.rsqrt <= 1e13 and 1e7 <= measured.f32.recip <= 1e13, measured.what()
    # no special operation outruns plain adds and multiplies: one that did was a chain the
    # compiler folded (fast math took two rounds of x = c / x as x itself once)
    for rates, ops in ((measured.f32, ("sqrt", "div", "rsqrt", "recip")), (measured.f64, ("sqrt", "div"))):
        assert all(getattr(rates, op) < rates.fp for op in ops), measured.what()
    # the Newton steps' adds and multiplies: fast_math.cl's where it takes the estimates, else none
    newton = (measured.f32.rsqrt_newton_fp, measured.f32.recip_newton_fp)
    assert newton == ((4, 2) if "avx512f" in open("/proc/cpuinfo").read() else (0, 0)), newton
    # a pair is a sqrt and a division: never more pairs per second than either alone (a 10 %
    # margin for the noise of three separate measurements)
    assert measured.f32.sqrt_div <= 1.1 * min(measured.f32.sqrt, measured.f32.div), measured.what()
    assert measured.rates("f32") is measured.f32 and measured.rates("f64") is measured.f64


def test_measured_once_per_process(measured):
    assert bounds.measure_machine() is measured
    assert bounds.machine_or_reason() == (measured, "")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/maps")
def test_measuring_does_not_load_openmp_into_the_caller():
    """GNU OpenMP does not survive a fork (a forked row worker's first parallel region hangs),
    so the measurement runs in a child process and the caller never loads libgomp."""
    if native.compiler() is None:
        pytest.skip(native.no_compiler_reason())
    code = (
        "from clothbench.harness import bounds; b = bounds.measure_machine(array_mib=4); "
        "print(b.triad_gb_s > 0, 'libgomp' in open('/proc/self/maps').read())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.split() == ["True", "False"], out.stderr


def test_no_compiler_gives_none_and_the_reason(monkeypatch):
    monkeypatch.setattr(native, "compiler", lambda: None)
    unmeasured = bounds._measured.__wrapped__  # around the per-process cache
    with pytest.raises(ClothbenchError, match="no C compiler"):
        unmeasured(2, 1)
    monkeypatch.setattr(bounds, "_measured", unmeasured)
    found, reason = bounds.machine_or_reason()
    assert found is None and reason == native.no_compiler_reason()
    assert bounds.step_bound_ms(sphere(32), "f32", found) is None
    assert bounds.bound_columns(sphere(32), "f32", 1.0) == {"bound_ms": "", "bound_kind": "", "bound_fraction": ""}
    assert set(bounds.machine_columns().values()) == {""}


# --- the count -------------------------------------------------------------------------


def brute_force_springs(n: int) -> int:
    """Springs the kernel evaluates (each from both ends): every in-grid stencil neighbour."""
    row, col = np.divmod(np.arange(n * n), n)
    offsets = [(0, -1), (0, 1), (-1, 0), (1, 0), (-1, -1), (-1, 1), (1, -1), (1, 1), (-2, -2), (-2, 2), (2, -2), (2, 2)]
    return int(sum(((0 <= row + dr) & (row + dr < n) & (0 <= col + dc) & (col + dc < n)).sum() for dr, dc in offsets))


@pytest.mark.parametrize("precision, dtype", [("f32", np.float32), ("f64", np.float64)])
def test_bytes_per_step_are_the_kernels_buffers(precision, dtype):
    """Independent count: the buffers a kernel streams once per step, as arrays. Every layout
    reads pos and pos_prev and the inverse mass (its own plane, or the w of float4 state);
    the c kernel writes x(t+dt) over x(t-dt), the specialised OpenCL one writes pos_out and
    pos_prev_out, float4 state writes both as float4, or (in place) x(t+dt) alone. Colliders
    add work, not bytes."""
    n = 48
    p = n * n
    plane3, plane1, float4 = (np.zeros(shape, dtype).nbytes for shape in ((3, p), p, (p, 4)))
    expected = {
        "ping-pong": 2 * plane3 + plane1 + plane3,
        "soa": 2 * plane3 + plane1 + 2 * plane3,
        "float4": 2 * float4 + 2 * float4,
        "float4-in-place": 2 * float4 + float4,
    }
    assert set(expected) == set(bounds.LAYOUT_ELEMENTS)
    spheres = plain(n).replace(spheres=(Sphere((0.5, 0.5, 0.5), 0.3),) * 3)
    for layout, nbytes in expected.items():
        assert bounds.step_count(plain(n), precision, layout=layout).bytes == nbytes
        assert bounds.step_count(spheres, precision, layout=layout).bytes == nbytes
    # the bound takes the least: 40 bytes a particle in float32
    least = {"f32": 40, "f64": 80}[precision] * p
    assert bounds.step_count(plain(n), precision).bytes == min(expected.values()) == least
    normals = bounds.step_count(plain(n), precision, normals=True)
    assert normals.bytes == expected["ping-pong"] + plane3


@pytest.mark.parametrize("n", [5, 32, 101])
def test_operations_per_step_follow_the_stencil_and_the_colliders(n):
    springs = brute_force_springs(n)
    assert springs == plain(n).springs
    p = n * n
    strict = bounds.step_count(plain(n), "f32", strict=True)
    assert (strict.sqrt, strict.div, strict.rsqrt) == (springs, springs + 3 * p, 0)
    assert strict.fp == 19 * springs + 24 * p
    fast = bounds.step_count(plain(n), "f32")
    assert (fast.sqrt, fast.div, fast.rsqrt, fast.fp) == (0, 0, springs, 10 * springs + 15 * p)
    one_each = plain(n).replace(
        spheres=(Sphere((0.5, 0.5, 0.5), 0.3),),
        cylinders=(Cylinder((0.1, 0.7, 0.2), (0.9, 0.7, 0.3), 0.05),),
        planes=(Plane((0.0, 0.0, 0.0), (0.0, 1.0, 0.0)),),
    )
    collided = bounds.step_count(one_each, "f32", strict=True)
    # sphere and cylinder: one sqrt and one division each per particle; the plane: neither
    assert (collided.sqrt - strict.sqrt, collided.div - strict.div) == (2 * p, 2 * p)
    assert collided.fp - strict.fp == (14 + 42 + 14) * p
    # f64 is the numpy reference: strict arithmetic whatever the flag says
    f64 = bounds.step_count(plain(n), "f64", strict=False)
    assert f64 == bounds.step_count(plain(n), "f64", strict=True)
    assert f64 == strict + bounds.Ops(bytes=strict.bytes)  # the same work on twice the bytes


def test_bad_precision_or_layout_is_one_clear_error():
    with pytest.raises(ClothbenchError, match="precision must be one of f32, f64, got 'f16'"):
        bounds.step_count(plain(8), "f16")
    with pytest.raises(
        ClothbenchError, match="layout must be one of ping-pong, soa, float4, float4-in-place, got 'aos'"
    ):
        bounds.step_count(plain(8), layout="aos")


# --- the bound -------------------------------------------------------------------------


def test_memory_bound_grows_linearly_with_particles():
    """4x the particles, the same measured limits: exactly 4x the bytes, so 4x memory_ms, and
    4x bound_ms where memory sets it (a machine with arithmetic to spare)."""
    roomy = fixed(rates=bounds.Rates(sqrt=1e15, div=1e15, sqrt_div=1e15, fp=1e17, rsqrt=1e15))
    for strict in (False, True):
        small = bounds.step_bound_ms(sphere(64), "f32", roomy, strict=strict)
        large = bounds.step_bound_ms(sphere(128), "f32", roomy, strict=strict)
        assert small["bound_kind"] == large["bound_kind"] == "memory"
        assert large["memory_ms"] / small["memory_ms"] == pytest.approx(4.0, rel=1e-9)
        assert large["bound_ms"] / small["bound_ms"] == pytest.approx(4.0, rel=1e-9)
        assert small["memory_ms"] == pytest.approx(40 * 64 * 64 / 20e9 * 1e3, rel=1e-12)


def test_arithmetic_bound_is_linear_in_the_work():
    """Where arithmetic sets the bound, it grows as the counted work: 4x for the per-particle
    part, the springs' ratio for theirs (an edge particle has fewer), so between them."""
    slow = fixed(bandwidth_gb_s=1e6, rates=bounds.Rates(sqrt=1e10, div=1e10, sqrt_div=5e9, fp=1e12, rsqrt=2e10))
    small = bounds.step_bound_ms(plain(64), "f32", slow, strict=True)
    large = bounds.step_bound_ms(plain(128), "f32", slow, strict=True)
    assert small["bound_kind"] == large["bound_kind"] == "arithmetic"
    # with these rates the divider is the busiest unit: its pairs at the pair rate
    assert small["arithmetic_ms"] == pytest.approx(brute_force_springs(64) / 5e9 * 1e3, rel=1e-12)
    ratio = large["bound_ms"] / small["bound_ms"]
    assert ratio == pytest.approx(brute_force_springs(128) / brute_force_springs(64), rel=1e-9)
    assert 4.0 < ratio < 4.0 * (1 + 3 / 64)


def test_arithmetic_part_grows_with_colliders(measured):
    base = plain(64)
    for rates_of in (measured, fixed()):
        scenes = [base.replace(spheres=(Sphere((0.5, 0.2, 0.5), 0.3),) * k) for k in range(4)]
        times = [bounds.step_bound_ms(s, "f32", rates_of, strict=True)["arithmetic_ms"] for s in scenes]
        assert times == sorted(times) and len(set(times)) == 4, times
    # planes cost only adds and multiplies: they grow the bound where those are the busiest
    fp_bound = fixed(rates=bounds.Rates(sqrt=1e15, div=1e15, sqrt_div=1e15, fp=1e10, rsqrt=1e15))
    no_plane = bounds.step_bound_ms(base, "f32", fp_bound)["arithmetic_ms"]
    two = bounds.step_bound_ms(base.replace(planes=(Plane((0, 0, 0), (0, 1, 0)),) * 2), "f32", fp_bound)
    assert two["arithmetic_ms"] == pytest.approx(no_plane + 2 * 9 * 64 * 64 / 1e10 * 1e3, rel=1e-12)


def test_newton_steps_add_to_the_adds_and_multiplies():
    """Fast Verlet springs: 10 fp and 1 rsqrt each. With the rsqrt's Newton step counted (4 adds
    and multiplies, fast_math.cl's), the pipes' time grows by 4 per spring and the estimate's own
    time is unchanged; PBD's reciprocals add theirs (2 each) in the same way."""
    base = dict(sqrt=1e10, div=1e10, sqrt_div=5e9, fp=1e11, rsqrt=2e10, recip=3e10)
    plain_rates, newton_rates = bounds.Rates(**base), bounds.Rates(**base, rsqrt_newton_fp=4, recip_newton_fp=2)
    scene = plain(64)
    work = bounds.step_count(scene, "f32")
    apart, counted = (bounds.step_bound_ms(scene, "f32", fixed(1e6, r)) for r in (plain_rates, newton_rates))
    assert apart["newton_ms"] == 0.0 and apart["fp_ms"] == pytest.approx(work.fp / 1e11 * 1e3, rel=1e-12)
    assert counted["fp_ms"] == pytest.approx((work.fp + 4 * work.rsqrt) / 1e11 * 1e3, rel=1e-12)
    assert counted["rsqrt_ms"] == apart["rsqrt_ms"] == pytest.approx(work.rsqrt / 2e10 * 1e3, rel=1e-12)
    jacobi = Pbd(dt=5e-4, iterations=2)
    pbd = bounds.iterative_count(scene, jacobi, "f32")
    got = bounds.step_bound_ms(scene, "f32", fixed(1e6, newton_rates), solver=jacobi)
    assert got["fp_ms"] == pytest.approx((pbd.fp + 4 * pbd.rsqrt + 2 * pbd.recip) / 1e11 * 1e3, rel=1e-12)
    # strict counts neither estimate: its bound is the same whatever the Newton steps cost
    assert bounds.step_bound_ms(scene, "f32", fixed(1e6, newton_rates), strict=True) == bounds.step_bound_ms(
        scene, "f32", fixed(1e6, plain_rates), strict=True
    )


def test_bound_is_the_larger_part_and_names_it(measured):
    for strict in (False, True):
        for n in (32, 256, 1024):
            b = bounds.step_bound_ms(sphere(n), "f32", measured, strict=strict)
            assert b["bound_ms"] == max(b["memory_ms"], b["arithmetic_ms"]) > 0
            assert b["bound_kind"] == ("memory" if b["memory_ms"] >= b["arithmetic_ms"] else "arithmetic")
            assert b["arithmetic_ms"] == max(b["divider_ms"], b["rsqrt_ms"], b["fp_ms"])


def test_pbd_jacobi_count_by_hand():
    """8 x 8, no collider, 2 iterations, 1 substep, strict f32: 64 particles, 564 directed
    constraints (282 = 112 structural + 98 shear + 72 bend, each seen from both ends)."""
    scene, solver = plain(8), Pbd(dt=5e-4, iterations=2)
    assert (scene.particles, scene.springs, len(scene.pinned())) == (64, 564, 0)
    got = bounds.iterative_count(scene, solver, "f32", strict=True)
    # the state once (13 elements of 4 bytes); predict 9 + update 6 fp and 3 div a particle;
    # per iteration 22 fp, 1 sqrt, 2 div a directed constraint and 6 fp a particle
    assert got == bounds.Ops(
        bytes=13 * 4 * 64, fp=15 * 64 + 2 * (22 * 564 + 6 * 64), sqrt=2 * 564, div=3 * 64 + 2 * 2 * 564
    )
    # past the caches each iteration streams x 3 + w 1 read, 3 written, and the multipliers
    # (written both times, read only in the second)
    past = bounds.iterative_count(scene, solver, "f32", strict=True, cache=1)
    assert past.bytes - got.bytes == (2 * 7 * 64 + 3 * 564) * 4 and past.fp == got.fp
    held = (7 * 64 + 564) * 4  # x, w and the next iterate, the multipliers
    assert bounds.iterative_count(scene, solver, "f32", strict=True, cache=held).bytes == got.bytes


def test_pbd_coloured_count_by_hand():
    scene, solver = plain(8), Pbd(dt=5e-4, method="coloured", iterations=2)
    got = bounds.iterative_count(scene, solver, "f32", strict=True)
    # 282 constraints, 28 fp, 1 sqrt, 3 div each (both ends moved); no per-particle pass
    assert got == bounds.Ops(bytes=13 * 4 * 64, fp=15 * 64 + 2 * 28 * 282, sqrt=2 * 282, div=3 * 64 + 2 * 3 * 282)
    past = bounds.iterative_count(scene, solver, "f32", strict=True, cache=1)
    assert past.bytes - got.bytes == (2 * 7 * 64 + 3 * 282) * 4
    # fast: the divisions are reciprocal estimates (fast_math.cl's fast_recip), off the divider
    fast = bounds.iterative_count(scene, solver, "f32")
    assert (fast.fp, fast.sqrt, fast.div, fast.rsqrt, fast.recip) == (12 * 64 + 2 * 20 * 282, 0, 0, 2 * 282, 2 * 282)


def test_vbd_count_by_hand():
    """A pinned corner of the 8 x 8 sheet has 4 springs (right, down, diagonal, bend): its 63
    free neighbours' sweeps evaluate 564 - 4 of them; predict skips it, update does not."""
    scene, solver = plain(8).replace(pin_indices=(0,)), Vbd(dt=5e-4, iterations=2)
    assert scene.pinned().tolist() == [0]
    got = bounds.iterative_count(scene, solver, "f32", strict=True)
    fp = 9 * 63 + 3 * 64 + 2 * (38 * 63 + 35 * 560)
    assert got == bounds.Ops(bytes=13 * 4 * 64, fp=fp, sqrt=2 * 560, div=3 * 64 + 2 * (6 * 63 + 2 * 560))
    past = bounds.iterative_count(scene, solver, "f32", strict=True, cache=1)
    assert past.bytes - got.bytes == 2 * 13 * 64 * 4  # x, w, y, x0 read and x written, each iteration
    # float64 counts the strict arithmetic on 8-byte elements
    f64 = bounds.iterative_count(scene, solver, "f64")
    assert f64.bytes == 2 * got.bytes and f64.fp == got.fp and f64.div == got.div


def test_substeps_and_chebyshev_scale_the_count():
    scene = plain(8)
    one = bounds.iterative_count(scene, Pbd(dt=5e-4, iterations=3), "f32")
    two = bounds.iterative_count(scene, Pbd(dt=5e-4, iterations=3, substeps=2), "f32")
    assert two.fp == 2 * one.fp and two.bytes == one.bytes  # the state still streamed once a step
    cheb = bounds.iterative_count(scene, Pbd(dt=5e-4, iterations=3, chebyshev_rho=0.9), "f32")
    assert cheb.fp - one.fp == 2 * (6 * 64 + 2 * 564)  # the second and third iterations extrapolated


def test_every_solver_has_a_bound():
    for solver in (Verlet(dt=5e-4), Pbd(dt=5e-4), Pbd(dt=5e-4, method="coloured"), Vbd(dt=5e-4)):
        b = bounds.step_bound_ms(sphere(32), "f32", fixed(), solver=solver)
        assert b is not None and b["bound_ms"] > 0, solver.spec
        cells = bounds.bound_columns(sphere(32), "f32", 1.0, solver=solver, bounds=fixed())
        assert cells["bound_ms"] == fmt(b["bound_ms"]) and cells["bound_kind"] in ("memory", "arithmetic")
    # the iterations are the work: ten cost more than one
    ten = bounds.step_bound_ms(sphere(32), "f32", fixed(), solver=Pbd(dt=5e-4))["arithmetic_ms"]
    one = bounds.step_bound_ms(sphere(32), "f32", fixed(), solver=Pbd(dt=5e-4, iterations=1))["arithmetic_ms"]
    assert ten > 5 * one


def test_cache_size_counts_each_shared_cache_once(tmp_path):
    """Two CPUs, each with its own L1d and L2, sharing one L3: the instruction caches left out."""
    caches = [("1", "Data", "48K", "{cpu}"), ("1", "Instruction", "32K", "{cpu}"), ("2", "Unified", "1024K", "{cpu}")]
    caches.append(("3", "Unified", "32768K", "0-1"))
    for cpu in (0, 1):
        for k, (level, kind, size, shared) in enumerate(caches):
            index = tmp_path / f"cpu{cpu}" / "cache" / f"index{k}"
            index.mkdir(parents=True)
            for name, value in (("level", level), ("type", kind), ("size", size), ("shared_cpu_list", shared)):
                (index / name).write_text(value.format(cpu=cpu) + "\n")
    assert bounds.cache_bytes([0, 1], root=tmp_path) == 2 * (48 << 10) + 2 * (1 << 20) + (32 << 20)
    assert bounds.cache_bytes([0], root=tmp_path) == (48 << 10) + (1 << 20) + (32 << 20)
    assert bounds.cache_bytes([0], root=tmp_path / "none") == 0  # sysfs silent: unknown
    assert bounds.MachineBounds.from_dict(fixed().to_dict()).cache_bytes == 0  # unknown: every iteration fits


def test_csv_cells():
    limits = fixed()
    b = bounds.step_bound_ms(sphere(64), "f32", limits, strict=True)
    cells = bounds.bound_columns(sphere(64), "f32", "0.5", strict=True, bounds=limits)
    fraction = fmt(b["bound_ms"] / 0.5)
    assert cells == {"bound_ms": fmt(b["bound_ms"]), "bound_kind": b["bound_kind"], "bound_fraction": fraction}
    # the sweep's call: the row's solver fourth; fast (the default) is the smaller count
    verlet = bounds.bound_columns(sphere(64), "f32", 0.5, Verlet(dt=5e-4), bounds=limits)
    fast = bounds.step_bound_ms(sphere(64), "f32", limits)
    assert verlet["bound_ms"] == fmt(fast["bound_ms"]) and fast["arithmetic_ms"] < b["arithmetic_ms"]
    assert bounds.bound_columns(sphere(64), "f32", "", bounds=limits)["bound_fraction"] == ""
    assert bounds.bound_columns(sphere(64), "f32", 0.0, bounds=limits)["bound_fraction"] == ""
    machine = bounds.machine_columns(limits)
    assert set(machine) == set(bounds.MACHINE_COLUMN_DOCS)
    assert machine["bandwidth_gb_s"] == "20" and machine["copy_gb_s"] == "10" and machine["sqrt_gops"] == "10"
    assert set(cells) == set(bounds.BOUND_COLUMN_DOCS)
