"""Taichi (peer): the step as one `@ti.kernel` over a `ti.Vector.field(4, ti.f32)`.

docs/semantics.md, written as Taichi users write it: a parallel loop over `ti.ndrange(n, n)`,
vector arithmetic, the scene's constants as Python values compiled into the kernel, the
stencil and the scene's colliders (spheres, cylinders, boxes, planes) unrolled with `ti.static`.
Ping-pong without copies: both states live in one field of shape (2, n, n) and the kernel
takes the index of the current one; particle (row, col) reads its own previous position
only itself, so it writes x_new over it, and the roles swap.

Fast mode is Taichi's default, `fast_math=True`: every operation is marked `reassoc ninf
nsz` for LLVM, which may then re-associate. Strict mode is `fast_math=False`, which is
bit-exact with the NumPy float32 reference except for subnormals: Taichi sets flush-to-zero
for its threads, so a result below 1.2e-38 becomes 0 where NumPy keeps it (values of
~1e-37 m near an axis; tests/test_peers.py asserts both). ti.init sets it on the calling
thread too; this module puts that thread's floating-point environment back, so that NumPy
in the same process (the reference included) keeps its subnormals.

Taichi's runtime is process-wide (one `ti.init`, which fixes arch and fast_math), so every
instance shares it and a different mode can only start once the others are closed. Each
instance allocates its field in an SNode tree of its own and frees it on close(), and
defines its own kernel, compiled on the first advance (the harness's warm-up) and kept
in Taichi's offline cache.
"""

# no `from __future__ import annotations`: Taichi reads the kernel's annotations as objects
import contextlib
import ctypes
import ctypes.util
import io
import os

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import VerletConstants, collider_rows

_INSTALL = "pip install 'clothbench[peers]'"
_ARCHS = ("cpu", "cuda")


def _import_taichi():
    # no banner on stdout (it would corrupt --json) and no phoning home for a version check
    os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
    os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
    import taichi as ti

    return ti


def probe() -> Availability:
    try:
        ti = _import_taichi()
    except ModuleNotFoundError as e:
        if e.name == "taichi":
            return Availability(False, f"taichi not installed ({_INSTALL})")
        return Availability(False, f"taichi does not import: {e}")
    except Exception as e:  # e.g. a taichi build that does not match this NumPy or Python
        return Availability(False, f"taichi does not import: {type(e).__name__}: {e}")
    version = ".".join(map(str, ti.__version__))
    return Availability(True, device=f"taichi {version} ({_default_arch()})")


def _default_arch() -> str:
    """CUDA where a device exists, else the CPU (not Taichi's 'gpu', which may pick llvmpipe)."""
    return "cuda" if _cuda_devices() > 0 else "cpu"


def _cuda_devices() -> int:
    """CUDA devices, asked of the driver: Taichi cannot say without initialising, and its
    own check (`with_cuda`) prints a warning to stderr wherever libcuda is missing."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if cuda.cuInit(0) != 0 or cuda.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return count.value


@contextlib.contextmanager
def _same_fp_environment():
    """Restore this thread's floating-point environment (x86 MXCSR: rounding, FTZ, DAZ)."""
    try:
        libm = ctypes.CDLL(ctypes.util.find_library("m"))
        saved = ctypes.create_string_buffer(64)  # fenv_t is 32 bytes on x86-64 glibc
        if libm.fegetenv(saved) != 0:
            libm = None
    except (OSError, AttributeError, TypeError):
        libm = None
    try:
        yield
    finally:
        if libm is not None:
            libm.fesetenv(saved)


class _Runtime:
    """The one Taichi runtime of this process: (re)initialised only while no instance is alive."""

    config: tuple[str, bool] | None = None  # (arch, fast_math) of the current ti.init
    live = 0  # TaichiBackend instances not yet closed

    @classmethod
    def acquire(cls, ti, arch: str, fast_math: bool) -> None:
        if cls.config != (arch, fast_math):
            if cls.live:
                raise ClothbenchError(
                    f"taichi is already running as {cls.config[0]} with fast_math={cls.config[1]} "
                    f"in this process; close the other taichi backend before asking for "
                    f"{arch} with fast_math={fast_math} (ti.init is process-wide)"
                )
            # ti.init prints "[Taichi] Starting on arch=..." and sets flush-to-zero and
            # denormals-are-zero on the calling thread, which would change NumPy's results
            # (the reference included) for the rest of the process: keep ours
            with contextlib.redirect_stdout(io.StringIO()), _same_fp_environment():
                ti.init(arch=getattr(ti, arch), default_fp=ti.f32, fast_math=fast_math, log_level=ti.ERROR)
            cls.config = (arch, fast_math)
        cls.live += 1

    @classmethod
    def release(cls) -> None:
        cls.live -= 1


def _step_kernel(ti, state, scene: Scene, solver: Verlet):
    """The step for one scene and one state field. Like most Taichi code, it reads the
    constants as Python values, which Taichi compiles in as f32 literals: here the values
    kernel_inputs rounded once from float64, as exact Python floats, and nothing to pass at
    each launch."""
    vec3 = ti.types.vector(3, ti.f32)
    n = scene.grid
    consts = VerletConstants.of(scene, solver)
    dt, dt2, k, b = float(consts.dt), float(consts.dt2), float(consts.k), float(consts.b)
    gx, gy, gz = map(float, consts.g)
    rest = tuple(float(consts.rest[kind]) for kind in OFFSET_KIND)  # by offset
    rows = collider_rows(scene)  # .tolist(): the float32 values as exact Python floats
    spheres = rows["spheres"].tolist()
    # cylinders: start a, unit axis u, length, radius, radial_r (kernel_inputs.collider_rows)
    cylinders = [
        (tuple(a[:3]), tuple(u[:3]), a[3], u[3], tuple(radial_r[:3]))
        for a, u, radial_r in rows["cylinders"].reshape(-1, 3, 4).tolist()
    ]
    # boxes: centre, then per axis (unit axis, half extent) (kernel_inputs.collider_rows)
    boxes = [
        (tuple(c[:3]), *((tuple(a[:3]), a[3]) for a in axes)) for c, *axes in rows["boxes"].reshape(-1, 4, 4).tolist()
    ]
    planes = [(tuple(p[:3]), tuple(nrm[:3])) for p, nrm in rows["planes"].reshape(-1, 2, 4).tolist()]

    @ti.func
    def dot3(a, b):
        """(a.x*b.x + a.y*b.y) + a.z*b.z, the association every kernel uses."""
        return (a.x * b.x + a.y * b.y) + a.z * b.z

    @ti.kernel
    def step(cur: ti.i32):
        """state[cur] is x(t), state[1 - cur] is x(t - dt) and receives x(t + dt)."""
        old = 1 - cur
        g = vec3(gx, gy, gz)
        for row, col in ti.ndrange(n, n):
            p = state[cur, row, col]
            x, w = p.xyz, p.w
            xp = state[old, row, col].xyz
            # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
            vel = (x - xp) / dt
            bv = b * vel
            force = vec3(0.0)
            for o in ti.static(range(len(OFFSETS))):  # step 5: the 12 neighbours, in order
                r, c = row + ti.static(OFFSETS[o][0]), col + ti.static(OFFSETS[o][1])
                if 0 <= r < n and 0 <= c < n:  # outside the grid: no spring
                    d = state[cur, r, c].xyz - x
                    l2 = d.norm_sqr()
                    s = 0.0
                    if l2 > 0:  # coincident particles: no direction, no spring force
                        length = ti.sqrt(l2)
                        s = (k * (length - ti.static(rest[o]))) / length
                    force += s * d - bv
            x_new = x
            if w != 0:  # pinned particles do not move
                # step 6: Verlet, acceleration = gravity + force * inverse mass
                acc = g + force * w
                x_new = (2.0 * x - xp) + acc * dt2
                for m in ti.static(range(len(spheres))):  # colliders, in scene order
                    center = vec3(spheres[m][0], spheres[m][1], spheres[m][2])
                    radius = ti.static(spheres[m][3])
                    e = x_new - center
                    l2 = e.norm_sqr()
                    length = ti.sqrt(l2)
                    if length < radius:
                        if l2 > 0:
                            x_new = center + e * (radius / length)
                        else:  # exactly at the centre: straight up
                            x_new = center + vec3(0.0, radius, 0.0)
                for m in ti.static(range(len(cylinders))):  # then cylinders, in scene order
                    a = vec3(cylinders[m][0][0], cylinders[m][0][1], cylinders[m][0][2])
                    u = vec3(cylinders[m][1][0], cylinders[m][1][1], cylinders[m][1][2])
                    cyl_len = ti.static(cylinders[m][2])
                    radius = ti.static(cylinders[m][3])
                    radial_r = vec3(cylinders[m][4][0], cylinders[m][4][1], cylinders[m][4][2])
                    e = x_new - a
                    t = dot3(e, u)  # axial coordinate (m) from the start cap
                    q = u * t
                    rv = e - q  # radial vector
                    rho2 = dot3(rv, rv)
                    rho = ti.sqrt(rho2)
                    if t > 0 and t < cyl_len and rho < radius:
                        # push out the shortest way: through the side, or the nearer cap
                        side = radius - rho
                        to_end = cyl_len - t
                        if side <= t and side <= to_end:
                            if rho2 > 0:
                                x_new = (a + q) + rv * (radius / rho)
                            else:  # on the axis
                                x_new = (a + q) + radial_r
                        elif t <= to_end:
                            x_new = x_new - q
                        else:
                            x_new = x_new + u * to_end
                for m in ti.static(range(len(boxes))):  # then boxes, in scene order
                    e = x_new - vec3(*boxes[m][0])
                    ax0, ax1, ax2 = vec3(*boxes[m][1][0]), vec3(*boxes[m][2][0]), vec3(*boxes[m][3][0])
                    h0, h1, h2 = ti.static(boxes[m][1][1], boxes[m][2][1], boxes[m][3][1])
                    l0, l1, l2 = dot3(e, ax0), dot3(e, ax1), dot3(e, ax2)  # the box's own coordinates
                    p0, p1, p2 = h0 - ti.abs(l0), h1 - ti.abs(l1), h2 - ti.abs(l2)  # depth through each face pair
                    if p0 > 0 and p1 > 0 and p2 > 0:  # strictly inside: out through the least deep face
                        u, lk, hk, pk = ax0, l0, ti.cast(h0, ti.f32), p0
                        if p1 < pk:  # ties go to the lower axis
                            u, lk, hk, pk = ax1, l1, h1, p1
                        if p2 < pk:
                            u, lk, hk = ax2, l2, h2
                        x_new = x_new + u * (ti.select(lk >= 0, hk, -hk) - lk)  # the face on its side
                for m in ti.static(range(len(planes))):  # then planes, in scene order
                    p0 = vec3(planes[m][0][0], planes[m][0][1], planes[m][0][2])
                    nrm = vec3(planes[m][1][0], planes[m][1][1], planes[m][1][2])
                    dist = dot3(x_new - p0, nrm)
                    if dist < 0:
                        x_new = x_new - nrm * dist
            state[old, row, col] = ti.Vector([x_new.x, x_new.y, x_new.z, w])

    return step


class TaichiBackend(Backend):
    name = "taichi"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    capabilities = Capabilities(device=True, boxes=("verlet",), sweep_variants=({"strict": False}, {"strict": True}))
    flushes_subnormals = True  # its threads run with flush-to-zero (module docstring)

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        ti = self._ti = _import_taichi()
        arch = options.device or _default_arch()
        if arch not in _ARCHS:
            raise ClothbenchError(f"taichi device must be one of {', '.join(_ARCHS)}, got {arch!r}")
        # fast (Taichi's default): fast_math=True; strict: IEEE arithmetic
        _Runtime.acquire(ti, arch, fast_math=not options.strict)
        self._closed, self._tree = False, None
        try:
            self._allocate(ti)
        except BaseException:
            self.close()
            raise
        cfg = ti.lang.impl.current_cfg()
        self._arch_name, self._threads = cfg.arch.name, cfg.cpu_max_num_threads

    def _allocate(self, ti) -> None:
        """This instance's field, in an SNode tree of its own (destroyed by close())."""
        n = self.scene.grid
        builder = ti.FieldsBuilder()
        self.state = ti.Vector.field(4, ti.f32)  # [0 or 1, row, col]: x(t) and x(t - dt)
        builder.dense(ti.ijk, (2, n, n)).place(self.state)
        self._tree = builder.finalize()
        self._step = _step_kernel(ti, self.state, self.scene, self.solver)
        self.cur = 0

    @property
    def device(self) -> str:
        if self._arch_name in ("x64", "arm64"):
            return f"taichi {self._arch_name} (CPU, {self._threads} threads)"
        return f"taichi {self._arch_name} (GPU)"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        n = self.scene.grid
        both = np.stack([pos, prev]).astype(np.float32).reshape(2, n, n, 4)
        self.cur = 0
        self.state.from_numpy(both)

    def advance(self, steps: int) -> None:
        for _ in range(steps):
            self._step(self.cur)
            self.cur = 1 - self.cur

    def synchronize(self) -> None:
        self._ti.sync()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        both = self.state.to_numpy().reshape(2, -1, 4)
        return both[self.cur].copy(), both[1 - self.cur].copy()

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if self._tree is not None:
                self._tree.destroy()
            _Runtime.release()
