"""The `c` backend: kernels/verlet_cloth.c, built per scene with the system C compiler
(clothbench.native.build_library) and called through ctypes.

Host code only; the step is in the kernel file and docs/semantics.md. The kernel is
specialised per scene with -D options (grid side, collider counts, precision, arithmetic),
so each shape is a separate cached library. The state lives in two aligned buffers of three
planes each that the library steps in place and ping-pongs (the kernel's header says how);
advance(steps) is one ctypes call that runs every step inside one OpenMP parallel region.
A scene with [self_collision] builds the pass in (-DCLOTH_SELF) and gives it a third buffer,
which rotates with the other two, and the search's work space; any other scene builds none of it.

Arithmetics (docs/c.md has the flags):
  strict  the documented operation order, no contraction, no fast math: NumPy float32 (and,
          with --precision f64, NumPy float64) bit for bit.
  fast    contraction, one 1/sqrt per spring, the damping summed once: within float32's own
          error of the float64 reference.
Threads are its kernel shape (backends/tuning.py), named in the mode as threads=T:
OMP_NUM_THREADS when set, else chosen by measurement among every core this process may run
on, half of them, ... down to one (where meeting the other threads at every step's barrier
costs more than they save). The default, untuned shape is every core.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

from clothbench import environment
from clothbench.model.colliders.kinds import kinds_in
from clothbench.errors import ClothbenchError
from clothbench.native import build_library, compiler, no_compiler_reason
from clothbench.model.scene import Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.model.kernel_inputs import SelfCollisionConstants, VerletConstants, collider_rows
from clothbench.backends.tuning import median_seconds, turn_steps
from clothbench.kernel_source import kernel_hash

KERNEL_FILE = "verlet_cloth.c"
THREADS_ENV = "OMP_NUM_THREADS"
SELF_FLAG = "-DCLOTH_SELF"  # the [self_collision] pass, compiled in only for a scene that has it
ALIGN = 64  # bytes: a cache line, and one AVX-512 vector
# Values between a state buffer's planes, and between where one buffer and the next start:
# without them the planes of a power-of-two grid, and the buffers NumPy gives page-aligned,
# share their low 12 address bits, column for column (docs/c.md, "Planes apart": 20-28% of
# the step at 1024^2 and 2048^2 on the Zen 4). The Verlet kernel takes the pad as
# -DCLOTH_PLANE_PAD; VBD keeps its planes n*n apart and its buffers unstaggered (staggered, it
# gained 4 % at 1024^2, within its spread: compute-bound).
PLANE_PAD = 32
BUFFER_STAGGER = 112

# Both arithmetics: optimised for this CPU; no errno from sqrt (so it is one instruction) and
# no FP traps assumed (so selects may compute both sides). Neither changes a rounded value.
COMMON_FLAGS = ("-std=gnu11", "-O3", "-march=native", "-fopenmp", "-fno-math-errno", "-fno-trapping-math")
# Strict: every operation rounded on its own. No -ffast-math/-funsafe-math-optimizations in
# either mode: GCC then links crtfastmath.o, whose constructor turns on flush-to-zero in the
# loading thread, i.e. for NumPy and every other backend in this process.
STRICT_FLAGS = ("-ffp-contract=off",)
FAST_FLAGS = ("-ffp-contract=fast",)  # 512-bit vectors measured slower here (docs/c.md)


def probe() -> Availability:
    if compiler() is None:
        return Availability(False, no_compiler_reason())
    try:
        omp_num_threads()
    except ClothbenchError as e:  # a bad OMP_NUM_THREADS: say so as the reason, in one line
        return Availability(False, str(e))
    return Availability(True, device=environment.cpu_model(), driver=compiler_driver())


def compiler_driver() -> str:
    """The compiler that builds the step, with its version, and OpenMP: what probe() and
    CBackend.driver name as the driver; '' without a compiler."""
    cc = compiler()
    return f"{cc.version}, OpenMP" if cc else ""


def omp_num_threads() -> int | None:
    """OMP_NUM_THREADS (its first level) when set, else None."""
    value = os.environ.get(THREADS_ENV, "").strip()
    if not value:
        return None
    try:
        count = int(value.split(",")[0])
    except ValueError:
        count = 0
    if count < 1:
        raise ClothbenchError(f"{THREADS_ENV} must be a positive integer, got {value!r}")
    return count


def thread_count(shape: str) -> int:
    """The T of a shape named threads=T."""
    return int(shape.removeprefix("threads="))


def build_flags(scene: Scene, precision: str, strict: bool) -> tuple[str, ...]:
    """The library for this scene's shape: what the kernel folds as constants (-D), the
    arithmetic (native.build_library keys its cache by the CPU too)."""
    defines = [
        f"-DCLOTH_N={scene.grid}",
        *(f"-D{kind.count_name('c')}={len(getattr(scene, kind.plural))}" for kind in kinds_in("c")),
    ]
    defines += ["-DCLOTH_DOUBLE"] * (precision == "f64") + ["-DCLOTH_STRICT"] * strict
    defines += [SELF_FLAG] * (scene.self_collision is not None)
    return (*COMMON_FLAGS, *(STRICT_FLAGS if strict else FAST_FLAGS), *defines)


_LIBRARIES: dict[tuple[str, ...], ctypes.CDLL] = {}


class _OpenMP:
    """Whether this process may start OpenMP threads. GNU libgomp hangs in a child forked
    after its parent ran a parallel region (measured: the child's first region never
    returns), so such a child steps on one thread, through the kernel's serial path: the same
    bits, more slowly. A sweep times this backend in fresh processes, never in such a child.
    Another library's use of libgomp (Numba's OpenMP layer) breaks it the same way, so a
    child forked while libgomp is loaded at all counts as broken too."""

    ran = False  # this process has run a parallel region
    broken = False  # this process was forked after its parent had, or with libgomp loaded

    @classmethod
    def after_fork_in_child(cls) -> None:
        cls.broken = cls.broken or cls.ran or _libgomp_loaded()


def _libgomp_loaded() -> bool:
    try:
        with open("/proc/self/maps") as f:
            return any("libgomp" in line for line in f)
    except OSError:
        return False


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_OpenMP.after_fork_in_child)


def load_library(flags: tuple[str, ...]) -> ctypes.CDLL:
    """The built library for `flags`, loaded once per process, its entry points typed."""
    lib = _LIBRARIES.get(flags)
    if lib is None:
        lib = build_library(KERNEL_FILE, flags)
        p = ctypes.c_void_p
        lib.cloth_advance.argtypes = [p, p, p, p, p, ctypes.c_int, ctypes.c_int]
        if SELF_FLAG in flags:  # the third buffer, the pass's numbers, exclude2, the work space
            lib.cloth_advance.argtypes += [p, p, ctypes.c_longlong, p]
            lib.cloth_contact_ints.restype = ctypes.c_int
        lib.cloth_advance.restype = ctypes.c_int
        lib.cloth_grid.restype = lib.cloth_plane.restype = lib.cloth_real_bytes.restype = ctypes.c_int
        _LIBRARIES[flags] = lib
    return lib


def aligned(count: int, dtype, offset: int = 0) -> np.ndarray:
    """A zeroed 1-D array of `count` values whose data starts `offset` values after an
    ALIGN-byte boundary."""
    itemsize = np.dtype(dtype).itemsize
    raw = np.zeros(count + ALIGN // itemsize + offset, dtype)
    start = (-raw.ctypes.data % ALIGN) // itemsize + offset
    return raw[start : start + count]


def state_buffers(count: int, n2: int, dtype) -> tuple[list[np.ndarray], np.ndarray]:
    """`count` state buffers of three planes PLANE_PAD apart, and the inverse-mass plane: each
    starts BUFFER_STAGGER values after the one before it, off the 4 KiB boundary the others
    start on (docs/c.md, "Planes apart")."""
    size = 3 * (n2 + PLANE_PAD)
    return [aligned(size, dtype, k * BUFFER_STAGGER) for k in range(count)], aligned(n2, dtype, count * BUFFER_STAGGER)


class CBackend(Backend):
    name = "c"
    device_timer = ""  # host code: the wall clock is its only clock
    capabilities = Capabilities(
        precisions=("f32", "f64"),
        strict=True,
        shapes=True,  # the thread count
        sweep_variants=({"strict": True}, {"strict": False}),  # f32 unless the sweep asks for f64
        boxes=("verlet",),
        self_collision=("verlet",),
    )

    kernel_file = KERNEL_FILE  # with what it includes: the tuning key's "kernel"
    layout_key = {"planes": f"pad={PLANE_PAD}/stagger={BUFFER_STAGGER}"}  # the layout the threads were timed on

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        t = self.dtype = options.dtype
        self.n2 = scene.particles
        self.flags = (*build_flags(scene, options.precision, options.strict), f"-DCLOTH_PLANE_PAD={PLANE_PAD}")
        self._lib = load_library(self.flags)
        self.pitch = self.n2 + PLANE_PAD  # values from one plane of a state buffer to the next
        named = (self._lib.cloth_grid(), self._lib.cloth_plane(), self._lib.cloth_real_bytes())
        if named != (scene.grid, self.pitch, np.dtype(t).itemsize):
            raise ClothbenchError(f"c: the cached library for {self.flags} is not the one it names; clear its cache")
        c = VerletConstants.of(scene, solver, t)  # rounded once, docs/semantics.md
        self._numbers = np.array((c.k, c.b, c.dt, c.dt2, *c.g, *c.rest), dtype=t)
        rows = collider_rows(scene, t)
        table = [rows[kind.plural].reshape(-1) for kind in kinds_in("c")]  # the kernel's order
        self._colliders = np.concatenate([*table, np.zeros(1, t)])  # never empty: a valid pointer
        # the state buffers, x|y|z planes: _state[0] holds x(t), _state[1] x(t - dt), and with
        # [self_collision] _state[2] the pass's output, the next x(t + dt)
        self._contact = self._contact_args(scene, t)
        self._state, self._w = state_buffers(3 if self._contact else 2, self.n2, t)
        self._w_prev = self._w  # the prev state's w as uploaded, until a step writes pos's w
        self.threads = thread_count(self.pick_shape(self._tuning_key(), self._time_shape))
        self.run_note = self._fewer_threads_if_busy()

    def _contact_args(self, scene: Scene, t) -> tuple:
        """cloth_advance's arguments after the spare buffer for [self_collision]: its numbers
        (rounded once, docs/semantics.md), exclude2, the search's work space; () without the pass."""
        if scene.self_collision is None:
            return ()
        sc = SelfCollisionConstants.of(scene, t)
        numbers = np.array((sc.thickness, sc.thickness2, sc.relax, sc.inv_cell), dtype=t)
        # a long long: any E above the grid's largest dr^2 + dc^2 excludes every pair alike
        exclude2 = min(sc.exclude2, 2 * scene.grid * scene.grid)
        cells = np.zeros(self._lib.cloth_contact_ints(), dtype=np.int32)
        return numbers, exclude2, cells

    def _fewer_threads_if_busy(self) -> str:
        """On a busy machine, the threads the others leave free for this run, not the tuned
        count (tuning.threads_for_this_run): there fewer threads run faster (docs/c.md,
        "Under load"). The count is the user's with OMP_NUM_THREADS or --shape."""
        from clothbench.backends.tuning import threads_for_this_run

        user = self.options.shape is not None or omp_num_threads() is not None
        free, why = threads_for_this_run(self.threads, user)
        if not why:
            return ""
        tuned, self.threads = self.threads, free
        self.shape = f"threads={free}"
        return f"threads={free} for this run, not the tuned {tuned}: {why}"

    @classmethod
    def kernel_shapes(cls, scene: Scene, options: BackendOptions, solver=None) -> tuple[str, ...]:
        """threads=T: OMP_NUM_THREADS alone where set (one thread in a child forked after
        OpenMP ran, see _OpenMP), else every core, then halving down to one."""
        if _OpenMP.broken:
            return ("threads=1",)
        chosen = omp_num_threads()
        if chosen is not None:
            return (f"threads={chosen}",)
        counts = [max(1, environment.cores())]
        while counts[-1] > 1:
            counts.append(counts[-1] // 2)
        return tuple(f"threads={count}" for count in counts)

    def _tuning_key(self) -> dict[str, str]:
        s, cc = self.scene, compiler()
        return {
            "cpu": environment.cpu_model(),
            "cores": str(environment.cores()),
            "compiler": cc.version if cc else "",
            "kernel": kernel_hash(self.kernel_file),
            **self.layout_key,
            "grid": str(s.grid),
            "colliders": "/".join(str(len(getattr(s, kind.plural))) for kind in kinds_in("c")),
            "precision": self.options.precision,
            "arithmetic": "strict" if self.options.strict else "fast",
        } | ({"self_collision": "on"} if s.self_collision is not None else {})

    def _time_shape(self, name: str) -> float:
        """Seconds per step of `name` on the scene's start: a few ms of steps, median of 5."""
        self.threads = thread_count(name)
        self.upload(*self.initial_state())  # the harness uploads its own state afterwards
        steps = turn_steps(self.n2)
        return median_seconds(lambda: self.advance(steps), lambda: None) / steps

    @property
    def device(self) -> str:
        return environment.cpu_model()

    @property
    def driver(self) -> str:
        return compiler_driver()

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if np.shape(pos) != expected or np.shape(prev) != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {np.shape(pos)} and {np.shape(prev)}")
        for buf, state in zip(self._state, (pos, prev)):
            self._planes(buf)[:] = np.asarray(state, self.dtype)[:, :3].T
        self._w[:] = np.asarray(pos, self.dtype)[:, 3]
        self._w_prev = np.asarray(prev, self.dtype)[:, 3].copy()

    def advance(self, steps: int) -> None:
        if steps <= 0:
            return
        if self._state[0].size == 0:
            raise ClothbenchError("c: advance after close")
        a, b = self._state[:2]
        contact = ()
        if self._contact:
            numbers, exclude2, cells = self._contact
            contact = (self._state[2].ctypes.data, numbers.ctypes.data, exclude2, cells.ctypes.data)
        rotated = self._lib.cloth_advance(
            a.ctypes.data,
            b.ctypes.data,
            self._w.ctypes.data,
            self._numbers.ctypes.data,
            self._colliders.ctypes.data,
            int(steps),
            self._threads_now(),
            *contact,
        )
        if rotated:  # the library wrote x(t) into buffer -rotated (two buffers: the second)
            self._state = self._state[-rotated:] + self._state[:-rotated]
        self._w_prev = self._w  # prev now carries pos's inverse mass

    def _threads_now(self) -> int:
        """The threads to step on, recorded as run (the VBD class steps this way too)."""
        if _OpenMP.broken:  # built before a fork, stepped after it: the same bits on one thread
            self.threads = 1
        _OpenMP.ran = _OpenMP.ran or self.threads > 1
        return self.threads

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self._rows(self._state[0], self._w), self._rows(self._state[1], self._w_prev)

    def _planes(self, buf: np.ndarray) -> np.ndarray:
        """The (3, n*n) x, y, z planes of a state buffer, a view past its pads."""
        return buf.reshape(3, self.pitch)[:, : self.n2]

    def _rows(self, buf: np.ndarray, w: np.ndarray) -> np.ndarray:
        out = np.empty((self.n2, 4), self.dtype)
        out[:, :3] = self._planes(buf).T
        out[:, 3] = w
        return out

    def close(self) -> None:
        self._state = [np.zeros(0, self.dtype)] * len(self._state)
