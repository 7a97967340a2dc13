"""The machine's limits, measured in the same run, and the lower bound they put on one cloth
step (docs/bounds.md).

`measure_machine()` measures, once per process, the streaming bandwidth (STREAM triad and a
copy-like scale over arrays far larger than the caches) and the throughput of float32 and
float64 sqrt, division, sqrt+division pairs, add/multiply and (float32) the fast reciprocal
square root and reciprocal as the fast kernels compute them, on every CPU the process may use
(kernels/machine_bounds.c, built by clothbench.native). It runs in a child process: GNU
OpenMP's threads do not survive a fork, so a sweep that forks its row workers after measuring
must not have loaded it.

`step_bound_ms(scene, precision, bounds)` counts the bytes a Verlet step moves and the
operations it does (from the kernels in kernels/; docs/bounds.md shows the count) and turns
them into milliseconds: the larger of the memory time and the arithmetic time is a lower
bound on a step here. `bound_columns` and `machine_columns` are the sweep's CSV cells.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterable

from clothbench.model.colliders.kinds import KINDS
from clothbench.model.scene import OFFSETS
from clothbench.model.solver import ITERATIVE
from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import BOUND_COLUMN_DOCS, MACHINE_COLUMN_DOCS, fmt

SOURCE = "machine_bounds.c"
FLAGS = ("-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-math-errno")
WIDE = ("-mprefer-vector-width=512",)  # GCC prefers 256-bit vectors on some AVX-512 CPUs
FAST = ("-DMB_FAST", "-ffast-math")  # the second build: rsqrt and reciprocal as a fast kernel computes them
ARRAY_MIB = 512  # per array; three of them, far past the L3 (docs/bounds.md: why this size)
SMALLEST_MIB = 64  # where memory is short, halved down to this before giving up
STREAM_ROUNDS = 2  # triad + scale passes over the arrays; the fastest chunk and pass count
ARITH_SECONDS = 0.004  # one timed run of an arithmetic test, per thread
ARITH_REPEATS = 3
CHILD_TIMEOUT_S = 120.0


@dataclass(frozen=True)
class Rates:
    """Operations per second on all the measured threads, of one precision."""

    sqrt: float
    div: float
    sqrt_div: float  # pairs (one sqrt and one division) per second: shows whether they share a unit
    fp: float  # separate adds and multiplies (a fused one counts once: same ports)
    rsqrt: float = 0.0  # float32 only: the fast kernels' estimate and Newton step
    recip: float = 0.0  # float32 only: the fast kernels' reciprocal (estimate and Newton step)
    # float32 only: the adds and multiplies of those Newton steps, which run on the add/multiply
    # pipes beside the rest of the step's (kernels/fast_math.cl's, where the fast kernels take
    # its estimates: AVX-512; 0 where they take the built-ins, whose work is not known)
    rsqrt_newton_fp: int = 0
    recip_newton_fp: int = 0


@dataclass(frozen=True)
class MachineBounds:
    threads: int
    triad_gb_s: float  # fastest chunks (what the bound uses)
    copy_gb_s: float
    triad_pass_gb_s: float  # fastest whole passes, as STREAM times them: what a whole step sees
    copy_pass_gb_s: float
    f32: Rates
    f64: Rates
    array_mib: int  # size of each streamed array
    compiler: str
    seconds: float  # what measuring cost, child process included
    # data cache the measured threads can hold between them (cache_bytes()); 0: unknown, and
    # then every iteration's working set is taken to fit (the smaller bound)
    cache_bytes: int = 0

    @property
    def bandwidth_gb_s(self) -> float:
        """The best streaming rate measured: what the bound's memory part divides by."""
        return max(self.triad_gb_s, self.copy_gb_s)

    def rates(self, precision: str) -> Rates:
        return self.f64 if precision == "f64" else self.f32

    def what(self) -> str:
        """What was measured, in one line."""
        return (
            f"{self.threads} threads: STREAM triad {self.triad_gb_s:.1f} GB/s, copy {self.copy_gb_s:.1f} GB/s "
            f"(whole passes {self.triad_pass_gb_s:.1f}, {self.copy_pass_gb_s:.1f}; 3 x {self.array_mib} MiB); "
            f"f32 sqrt {self.f32.sqrt / 1e9:.2f}, div {self.f32.div / 1e9:.2f}, "
            f"sqrt+div {self.f32.sqrt_div / 1e9:.2f} pairs, add/mul {self.f32.fp / 1e9:.1f}, "
            f"rsqrt {self.f32.rsqrt / 1e9:.2f}, reciprocal {self.f32.recip / 1e9:.2f} G/s "
            f"(Newton steps {self.f32.rsqrt_newton_fp} and {self.f32.recip_newton_fp} adds/multiplies); "
            f"f64 sqrt {self.f64.sqrt / 1e9:.2f}, div {self.f64.div / 1e9:.2f} G/s "
            f"({self.compiler}; {self.seconds:.2f} s)"
        )

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "MachineBounds":
        return cls(**{**d, "f32": Rates(**d["f32"]), "f64": Rates(**d["f64"])})


# --- measuring -------------------------------------------------------------------------


def measure_machine(threads: int | None = None, array_mib: int = ARRAY_MIB) -> MachineBounds:
    """The machine's limits on `threads` threads (default: every CPU this process may use),
    measured once per process, in a child process. Raises ClothbenchError with the reason
    when they cannot be measured (no C compiler, a failed build, no memory)."""
    from clothbench import environment

    return _measured(threads or environment.cores() or 1, array_mib)


@lru_cache(maxsize=None)
def _measured(threads: int, array_mib: int) -> MachineBounds:
    from clothbench.native import compiler, no_compiler_reason

    if compiler() is None:
        raise ClothbenchError(no_compiler_reason())
    if threads < 1 or array_mib < 1:
        raise ClothbenchError(f"machine bounds need threads >= 1 and array_mib >= 1, got {threads}, {array_mib}")
    t0 = time.perf_counter()
    package_root = str(Path(__file__).resolve().parents[2])  # so a checkout's child imports this clothbench
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [package_root, os.environ.get("PYTHONPATH")])))
    command = [sys.executable, "-m", "clothbench.harness.bounds", "--json", "--threads", str(threads)]
    command += ["--array-mib", str(array_mib)]
    try:
        out = subprocess.run(command, capture_output=True, text=True, timeout=CHILD_TIMEOUT_S, env=env)
    except subprocess.TimeoutExpired:
        raise ClothbenchError(f"measuring the machine's limits took over {CHILD_TIMEOUT_S:.0f} s") from None
    lines = out.stdout.strip().splitlines()
    try:
        result = json.loads(lines[-1])
    except (IndexError, ValueError):
        tail = (out.stderr.strip().splitlines() or [f"exit status {out.returncode}"])[-1]
        raise ClothbenchError(f"measuring the machine's limits failed: {tail}") from None
    if "error" in result:
        raise ClothbenchError(result["error"])
    return MachineBounds.from_dict({**result, "seconds": time.perf_counter() - t0})


def machine_or_reason(threads: int | None = None) -> tuple[MachineBounds | None, str]:
    """(the limits, "") or (None, why they could not be measured)."""
    try:
        return measure_machine(threads), ""
    except ClothbenchError as e:
        return None, str(e)


def _library(flags: tuple[str, ...]) -> ctypes.CDLL:
    from clothbench.native import build_library

    try:
        return build_library(SOURCE, flags + WIDE)
    except ClothbenchError:  # a compiler (or target) without the vector-width option
        return build_library(SOURCE, flags)


def measure_here(threads: int, array_mib: int) -> dict:
    """The measurement itself, in this process (it loads GNU OpenMP: see the module doc)."""
    from clothbench.native import compiler

    lib, fast = _library(FLAGS), _library(FLAGS + FAST)
    stream = lib.mb_stream
    stream.restype = ctypes.c_int
    stream.argtypes = [ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.POINTER(ctypes.c_double)]
    streamed = (ctypes.c_double * 4)()  # fastest chunks: triad, scale; whole passes: triad, scale
    wanted = array_mib
    while stream(array_mib * (1 << 20) // 4, threads, STREAM_ROUNDS, streamed) != 0:
        if array_mib // 2 < min(wanted, SMALLEST_MIB):
            raise ClothbenchError(f"machine bounds: could not allocate 3 x {array_mib} MiB for the bandwidth test")
        array_mib //= 2
    triad, scale, triad_pass, scale_pass = (v / 1e9 for v in streamed)

    def rate(library, name: str) -> float:
        fn = getattr(library, name)
        fn.restype, fn.argtypes = ctypes.c_double, [ctypes.c_double, ctypes.c_int, ctypes.c_int]
        return fn(ARITH_SECONDS, threads, ARITH_REPEATS)

    def newton_fp(name: str) -> int:
        fn = getattr(fast, name)
        fn.restype = ctypes.c_int
        return fn()

    ops = ("sqrt", "div", "sqrt_div", "addmul")
    f32 = Rates(
        *(rate(lib, f"mb_{op}_f32") for op in ops),
        rsqrt=rate(fast, "mb_rsqrt_f32"),
        recip=rate(fast, "mb_recip_f32"),
        rsqrt_newton_fp=newton_fp("mb_newton_fp_rsqrt"),
        recip_newton_fp=newton_fp("mb_newton_fp_recip"),
    )
    f64 = Rates(*(rate(lib, f"mb_{op}_f64") for op in ops))
    measured = {"triad": triad, "copy": scale, **{f"f32 {k}": v for k, v in asdict(f32).items() if "newton" not in k}}
    measured.update({f"f64 {k}": v for k, v in asdict(f64).items() if k in ("sqrt", "div", "sqrt_div", "fp")})
    nothing = [name for name, value in measured.items() if not (math.isfinite(value) and value > 0)]
    if nothing:  # a clock that did not advance, or a test the compiler emptied: no bound from it
        raise ClothbenchError(f"machine bounds: the {', '.join(nothing)} test measured no rate")
    return dict(
        threads=threads,
        triad_gb_s=triad,
        copy_gb_s=scale,
        triad_pass_gb_s=triad_pass,
        copy_pass_gb_s=scale_pass,
        f32=asdict(f32),
        f64=asdict(f64),
        array_mib=array_mib,
        compiler=compiler().version,
        seconds=0.0,
        cache_bytes=cache_bytes(),
    )


SYS_CPU = Path("/sys/devices/system/cpu")
CACHE_UNITS = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}  # sysfs writes sizes as 48K, 32768K


def cache_bytes(cpus: Iterable[int] | None = None, root: Path = SYS_CPU) -> int:
    """The data caches the CPUs this process may use hold between them (every level, each
    shared cache once), from Linux's sysfs; 0 where it does not say. What a PBD or VBD
    iteration's working set must exceed before it streams from memory each iteration."""
    cpus = sorted(os.sched_getaffinity(0)) if cpus is None and hasattr(os, "sched_getaffinity") else cpus or [0]
    seen, total = set(), 0
    for cpu in cpus:
        for index in sorted((root / f"cpu{cpu}" / "cache").glob("index*")):
            try:
                kind = (index / "type").read_text().strip()
                level = (index / "level").read_text().strip()
                shared = (index / "shared_cpu_list").read_text().strip()
                size = (index / "size").read_text().strip()
            except OSError:
                continue
            if kind == "Instruction" or (level, shared) in seen:
                continue
            seen.add((level, shared))
            total += int(size[:-1]) * CACHE_UNITS[size[-1]] if size[-1] in CACHE_UNITS else int(size)
    return total


# --- counting --------------------------------------------------------------------------


@dataclass(frozen=True)
class Ops:
    """Work of one step, or of one unit of it: bytes streamed and operations by kind."""

    bytes: float = 0.0
    fp: float = 0.0  # add, subtract, multiply (fused multiply-add: one)
    sqrt: float = 0.0
    div: float = 0.0
    rsqrt: float = 0.0  # fast: a reciprocal square root estimate and its Newton step
    recip: float = 0.0  # fast: a reciprocal estimate and its Newton step (a division's)

    def values(self) -> tuple[float, ...]:
        return (self.bytes, self.fp, self.sqrt, self.div, self.rsqrt, self.recip)

    def __add__(self, other: "Ops") -> "Ops":
        return Ops(*(a + b for a, b in zip(self.values(), other.values())))

    def __mul__(self, times: float) -> "Ops":
        return Ops(*(a * times for a in self.values()))


# Elements streamed per particle, by state layout (neighbours come from the cache). The
# bound takes the least any kernel here moves: a bound must hold for every backend.
LAYOUT_ELEMENTS = {
    # kernels/verlet_cloth.c: pos and prev read (3 + 3), inverse mass (1), x(t+dt) written
    # over x(t-dt) in place (3): two state buffers, ping-ponged
    "ping-pong": 10,
    # kernels/verlet_cloth.cl specialised, its split shape (its rows and steps shapes write in
    # place: ping-pong): the same reads, pos_out and pos_prev_out written
    "soa": 13,
    # float4 state, the chapter's ping-pong (OpenCL's generic kernel, the GL textures, CUDA's
    # --transfer copy): pos, prev read, both outputs written
    "float4": 16,
    # float4 state in place (glsl-compute, CUDA's default swap): pos, prev read, x(t+dt)
    # written over x(t-dt)
    "float4-in-place": 12,
}
BOUND_LAYOUT = "ping-pong"
NORMAL_ELEMENTS = 3  # normal_out x y z
# Operations counted from kernels/verlet_cloth.cl's specialised interior kernel
# (docs/bounds.md has the line-by-line count). Strict: every add and multiply separate,
# sqrt and '/' (kernels/verlet_cloth.c does the same). Fast: mul+add contracted to one FMA,
# one rsqrt per spring, the damping folded into the integration (the c kernel's 1/sqrt is
# a sqrt and a division: more work, so this count is a floor for it too).
COUNTS = {
    True: dict(
        particle=Ops(fp=24, div=3),  # vel (3 sub, 3 div), b*vel (3 mul), integrate (18)
        spring=Ops(fp=19, sqrt=1, div=1),  # d 3, L2 5, L-rest 1, k* 1, s*d 3, -bv 3, force+ 3
        sphere=Ops(fp=14, sqrt=1, div=1),
        cylinder=Ops(fp=42, sqrt=1, div=1),
        box=Ops(fp=28),  # docs/semantics.md, "Box": d 3, three dot3 15, depths 3, push 7
        plane=Ops(fp=14),
        face=Ops(fp=23, sqrt=1, div=3),  # normals: one face of the ring
        normal=Ops(fp=5, sqrt=1, div=3),  # normals: the sum made a unit vector
    ),
    False: dict(
        particle=Ops(fp=15),
        spring=Ops(fp=10, rsqrt=1),
        sphere=Ops(fp=9, sqrt=1, div=1),
        cylinder=Ops(fp=32, sqrt=1, div=1),
        box=Ops(fp=19),  # the dot3s and the push contracted to FMAs
        plane=Ops(fp=9),
        face=Ops(fp=18, sqrt=1, div=3),
        normal=Ops(fp=3, sqrt=1, div=3),
    ),
}
PRECISION_BYTES = {"f32": 4, "f64": 8}


def step_count(
    scene, precision: str = "f32", *, strict: bool = False, normals: bool = False, layout: str = BOUND_LAYOUT
) -> Ops:
    """Bytes streamed and operations done by one Verlet step of `scene` with the state in
    `layout` (LAYOUT_ELEMENTS). float64 has only the strict arithmetic (the numpy
    reference): its count is the strict one."""
    if precision not in PRECISION_BYTES:
        raise ClothbenchError(f"precision must be one of {', '.join(PRECISION_BYTES)}, got {precision!r}")
    if layout not in LAYOUT_ELEMENTS:
        raise ClothbenchError(f"layout must be one of {', '.join(LAYOUT_ELEMENTS)}, got {layout!r}")
    c = COUNTS[strict or precision == "f64"]
    n, particles = scene.grid, scene.particles
    elements = LAYOUT_ELEMENTS[layout] + (NORMAL_ELEMENTS if normals else 0)
    per_particle = (
        c["particle"]
        + sum((c[kind.name] * len(getattr(scene, kind.plural)) for kind in KINDS), Ops())
        + (c["normal"] if normals else Ops())
    )
    total = Ops(bytes=elements * PRECISION_BYTES[precision] * particles) + per_particle * particles
    total = total + c["spring"] * scene.springs  # each spring seen from both ends, as the kernel does
    if normals:
        total = total + c["face"] * (6 * (n - 1) ** 2)  # 2(n-1)^2 triangles, each seen from its 3 corners
    return total


# PBD and VBD (docs/bounds.md, "PBD and VBD"): counted from kernels/pbd_cloth.cl and
# kernels/vbd_cloth.cl as the Verlet step is, per unit of work. Strict: every operation of
# the kernel's CLOTH_STRICT lines; fast: its rsqrt lines with mul+add contracted. Work a kernel
# may hoist out of the iterations (a particle's constraint count and relax / count, VBD's
# count * bh) and selects and negations are not counted: a floor. A fast division is counted
# as a reciprocal (kernels/fast_math.cl's fast_recip: an estimate and a Newton step, off the
# divider).
ITERATIVE_COUNTS = {
    True: dict(
        predict=Ops(fp=9),  # pbd: v + g h 3, x + v h 6; vbd: (x + v h) + g h^2 9
        pbd_update=Ops(fp=6, div=3),  # (xs - x) / h 3 sub 3 div, * damp 3
        vbd_update=Ops(fp=3, div=3),  # (xs - x) / h
        # per directed constraint: d 3, L2 5, denom 2, L - rest 1, at*lam 1, - 1, / denom,
        # w*dl 1, / L, corr += d*s 6, lam + dl*scale 2
        jacobi=Ops(fp=22, sqrt=1, div=2),
        jacobi_particle=Ops(fp=6),  # x + corr * scale
        # per constraint, both ends moved: d 3, L2 5, denom 2, L - rest 1, at*lam 1, - 1,
        # / denom, w_i*dlam 1, / L, x_i + d*s 6, w_j*dlam 1, / L, x_j - d*s 6, lam + dlam 1
        coloured=Ops(fp=28, sqrt=1, div=3),
        # per directed spring of a free particle: d 3, L2 5, rest / sqrt, 1 - 1, k* 1, f + d*s 6,
        # k - a 1, / L2, b*d 3, diagonal a + b*d 9, off-diagonal 6
        vbd_spring=Ops(fp=35, sqrt=1, div=2),
        # per free particle: f = (x - y) mh2 + (x - x0) cb 15; LDL^T 20 fp and 6 div; x - p 3
        vbd_particle=Ops(fp=38, div=6),
        chebyshev_particle=Ops(fp=9),  # omega (x - before) + before
        chebyshev_lambda=Ops(fp=3),  # jacobi: the same for each directed multiplier
    ),
    False: dict(
        predict=Ops(fp=6),  # the multiply-adds contracted
        pbd_update=Ops(fp=6),  # (xs - x) * (damp / h): / h by a uniform, folded
        vbd_update=Ops(fp=6),
        # d 3, L2 3, denom 2, rest - L2*inv_L - at*lam 2, / denom, w*dl*inv_L 2, corr 3 FMA, lam 1
        jacobi=Ops(fp=16, rsqrt=1, recip=1),
        jacobi_particle=Ops(fp=3),
        # d 3, L2 3, denom 2, numerator 2, / denom, dlam*inv_L 1, two ends (w*s 1, 3 FMA) 8, lam 1
        coloured=Ops(fp=20, rsqrt=1, recip=1),
        # d 3, L2 3, k (1 - rest*rsqrt) 2, f 3 FMA, k - a 1, / L2, b*d 3, diagonal 6, off 3
        vbd_spring=Ops(fp=24, rsqrt=1, recip=1),
        vbd_particle=Ops(fp=25, recip=6),  # f 12, LDL^T 10 (a - b*c: one FMA), x - p 3
        chebyshev_particle=Ops(fp=6),
        chebyshev_lambda=Ops(fp=2),
    ),
}
# What an iteration holds and streams once that no longer fits the caches
# (MachineBounds.cache_bytes), the least any kernel moves, in elements: (held a particle,
# streamed a particle); every method also holds its multipliers, read and written once an
# iteration (not read in the first: they start at 0). Jacobi reads the iterate (x 3, w 1) and
# writes the next (3) beside it, one multiplier per directed constraint updated in place;
# coloured reads and writes the positions once (its batches in turn touch every particle; the
# rows a batch reaches are cache hits), one multiplier per constraint; VBD reads x 3 + w 1, the
# inertial target y 3 and the substep's start x0 3, and writes x 3 in place. Neither a
# constraint's index pair nor a colour's particle list is counted: a kernel can compute them
# from the grid, as the vector kernels do.
ITERATION_ELEMENTS = {"jacobi": (7, 7), "coloured": (4, 7), "vbd": (10, 13)}
STEP_ELEMENTS = 13  # the step's state read (x 3, v 3, w 1) and written (x 3, v 3) once


def _free_springs(scene) -> int:
    """Directed springs from free particles: what a VBD sweep evaluates."""
    n, degree = scene.grid, 0
    for i in scene.pinned():
        r, c = divmod(int(i), n)
        degree += sum(0 <= r + dr < n and 0 <= c + dc < n for dr, dc in OFFSETS)
    return scene.springs - degree


def iterative_count(scene, solver, precision: str = "f32", *, strict: bool = False, cache: int = 0) -> Ops:
    """Bytes streamed and operations done by one PBD (Jacobi or coloured) or VBD step of
    `scene`: solver.substeps substeps of predict, solver.iterations iterations, colliders and
    update. An iteration's arrays count as streamed only where they exceed `cache` bytes (0:
    unknown, taken to fit); the step's state is streamed once."""
    if precision not in PRECISION_BYTES:
        raise ClothbenchError(f"precision must be one of {', '.join(PRECISION_BYTES)}, got {precision!r}")
    c = ITERATIVE_COUNTS[strict or precision == "f64"]
    colliders = COUNTS[strict or precision == "f64"]
    per_particle = sum((colliders[kind.name] * len(getattr(scene, kind.plural)) for kind in KINDS), Ops())
    particles, size = scene.particles, PRECISION_BYTES[precision]
    free = particles - len(scene.pinned())
    iterations, chebyshev = solver.iterations, solver.chebyshev_rho > 0
    extrapolated = iterations - 1 if chebyshev else 0  # Chebyshev from the second iteration on
    if solver.name == "vbd":
        method, multipliers = "vbd", 0
        iteration = c["vbd_particle"] * free + c["vbd_spring"] * _free_springs(scene)
        substep = c["predict"] * free + c["vbd_update"] * particles + per_particle * particles
        substep = substep + c["chebyshev_particle"] * (free * extrapolated)
    else:
        method = solver.method
        if method == "jacobi":
            multipliers = scene.springs  # one per directed constraint: each end keeps its own
            iteration = c["jacobi"] * scene.springs + c["jacobi_particle"] * particles
            cheb = c["chebyshev_particle"] * particles + c["chebyshev_lambda"] * scene.springs
        else:
            multipliers = scene.springs // 2
            iteration = c["coloured"] * multipliers
            cheb = Ops()  # the coloured sweep has no extrapolation
        substep = c["predict"] * free + c["pbd_update"] * particles + per_particle * particles
        substep = substep + cheb * extrapolated
    held_elements, streamed_elements = ITERATION_ELEMENTS[method]
    iterations_bytes = 0.0
    if cache and (held_elements * particles + multipliers) * size > cache:  # streamed each iteration
        iterations_bytes = (streamed_elements * particles * iterations + multipliers * (2 * iterations - 1)) * size
    per_substep = substep + iteration * iterations + Ops(bytes=iterations_bytes)
    return Ops(bytes=STEP_ELEMENTS * size * particles) + per_substep * solver.substeps


def _bound(work: Ops, precision: str, bounds: MachineBounds) -> dict:
    """bound_ms and its parts for `work` on `bounds`' machine (docs/bounds.md: the formula)."""
    r = bounds.rates(precision)
    memory_ms = work.bytes / (bounds.bandwidth_gb_s * 1e9) * 1e3
    # sqrt and division may share one unit (measured pairs show it): whatever they share, the
    # step takes at least each one alone and at least its min(sqrt, div) pairs at the pair rate
    divider_ms = max(work.sqrt / r.sqrt, work.div / r.div, min(work.sqrt, work.div) / r.sqrt_div) * 1e3
    # the estimates (an rsqrt and a reciprocal may share a unit too: the larger, a floor; a rate
    # not measured, 0, bounds nothing)
    rsqrt_ms = max(work.rsqrt / r.rsqrt if r.rsqrt else 0.0, work.recip / r.recip if r.recip else 0.0) * 1e3
    # the add/multiply pipes: the counted fp and the estimates' Newton steps, which run there
    newton_ms = (work.rsqrt * r.rsqrt_newton_fp + work.recip * r.recip_newton_fp) / r.fp * 1e3
    fp_ms = work.fp / r.fp * 1e3 + newton_ms
    arithmetic_ms = max(divider_ms, rsqrt_ms, fp_ms)  # the busiest unit: all may overlap
    return dict(
        bound_ms=max(memory_ms, arithmetic_ms),
        bound_kind="memory" if memory_ms >= arithmetic_ms else "arithmetic",
        memory_ms=memory_ms,
        arithmetic_ms=arithmetic_ms,
        divider_ms=divider_ms,
        rsqrt_ms=rsqrt_ms,
        fp_ms=fp_ms,
        newton_ms=newton_ms,
        bytes=work.bytes,
        fp=work.fp,
        sqrt=work.sqrt,
        div=work.div,
        rsqrt=work.rsqrt,
        recip=work.recip,
    )


def step_bound_ms(
    scene,
    precision: str,
    bounds: MachineBounds | None,
    *,
    strict: bool = False,
    normals: bool = False,
    solver=None,
    layout: str = BOUND_LAYOUT,
) -> dict | None:
    """The lower bound on one step's wall time on this machine, in ms, with its parts; None
    without measured bounds. A pbd or vbd `solver` is counted by iterative_count, a Verlet
    one (or none) by step_count."""
    if bounds is None:
        return None
    if solver is not None and solver.name in ITERATIVE:
        return _bound(
            iterative_count(scene, solver, precision, strict=strict, cache=bounds.cache_bytes), precision, bounds
        )
    return _bound(step_count(scene, precision, strict=strict, normals=normals, layout=layout), precision, bounds)


# --- CSV cells -------------------------------------------------------------------------


def bound_columns(
    scene,
    precision: str,
    ms_median,
    solver=None,
    *,
    strict: bool = False,
    normals: bool = False,
    bounds: MachineBounds | None = None,
    layout: str = BOUND_LAYOUT,
) -> dict[str, str]:
    """The row's bound_ms, bound_kind and bound_fraction cells ('' where there is no bound).
    `strict` counts the strict arithmetic (the default is the fast count); `layout` the bytes
    of one kernel's state rather than the least any moves (LAYOUT_ELEMENTS). `bounds` defaults
    to this process's measure_machine() (measured on first use)."""
    if bounds is None:
        bounds = machine_or_reason()[0]
    result = step_bound_ms(scene, precision, bounds, strict=strict, normals=normals, solver=solver, layout=layout)
    if result is None:
        return dict.fromkeys(BOUND_COLUMN_DOCS, "")
    try:
        ms = float(ms_median)
    except (TypeError, ValueError):
        ms = math.nan
    fraction = result["bound_ms"] / ms if math.isfinite(ms) and ms > 0 else None
    return {"bound_ms": fmt(result["bound_ms"]), "bound_kind": result["bound_kind"], "bound_fraction": fmt(fraction)}


def machine_columns(bounds: MachineBounds | None = None) -> dict[str, str]:
    """The machine's measured limits as CSV cells ('' each where they could not be measured)."""
    if bounds is None:
        bounds = machine_or_reason()[0]
    if bounds is None:
        return dict.fromkeys(MACHINE_COLUMN_DOCS, "")
    return {
        "bandwidth_gb_s": fmt(bounds.bandwidth_gb_s),
        "triad_gb_s": fmt(bounds.triad_gb_s),
        "copy_gb_s": fmt(bounds.copy_gb_s),
        "triad_pass_gb_s": fmt(bounds.triad_pass_gb_s),
        "sqrt_gops": fmt(bounds.f32.sqrt / 1e9),
        "div_gops": fmt(bounds.f32.div / 1e9),
        "fp_gops": fmt(bounds.f32.fp / 1e9),
        "rsqrt_gops": fmt(bounds.f32.rsqrt / 1e9),
        "bound_threads": str(bounds.threads),
    }


def _main(argv: list[str]) -> int:
    """python -m clothbench.harness.bounds [--threads N] [--array-mib M] [--json]: measure
    here and print what was measured (--json: the one line measure_machine reads)."""
    import argparse

    parser = argparse.ArgumentParser(prog="python -m clothbench.harness.bounds")
    parser.add_argument("--threads", type=int, default=0, help="threads (default: every CPU this process may use)")
    parser.add_argument("--array-mib", type=int, default=ARRAY_MIB, help="MiB per streamed array")
    parser.add_argument("--json", action="store_true", help="one JSON line (what measure_machine reads)")
    args = parser.parse_args(argv)
    from clothbench import environment

    threads = args.threads or environment.cores() or 1
    try:
        if args.threads < 0 or args.array_mib < 1:
            raise ClothbenchError(f"--threads must be >= 0 and --array-mib >= 1, got {args.threads}, {args.array_mib}")
        t0 = time.perf_counter()
        result = measure_here(threads, args.array_mib)
        result["seconds"] = time.perf_counter() - t0
    except ClothbenchError as e:
        print(json.dumps({"error": str(e)}) if args.json else f"error: {e}")
        return 0 if args.json else 2
    print(json.dumps(result) if args.json else MachineBounds.from_dict(result).what())
    return 0


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
