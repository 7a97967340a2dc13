"""PyTorch (peer): the step as tensor code over (3, n, n) component planes, as PyTorch users
write it: whole-grid slicing for the 12 springs, like the NumPy reference, on the torch device
(cuda where a GPU is visible, else cpu); fast mode is the same function under `torch.compile`.

docs/semantics.md, operation for operation in the NumPy reference's order
(backends/numpy/verlet.py). Colliders are `torch.where` selections with no data-dependent
branch, as GPU PyTorch code avoids host syncs (and `torch.compile` graph breaks); choosing
the pushed value where a particle is inside gives the same bits as NumPy's `copyto(where=)`.
The constants are 0-d float32 tensors on the device, not Python floats: PyTorch's CUDA
division by a CPU scalar multiplies by its reciprocal, which is not the IEEE quotient.

Strict mode is eager PyTorch, one kernel per operation and nothing to contract, with the
square root taken in float64 and rounded once (torch.sqrt's float32 CPU path is not
correctly rounded): bit-exact with the NumPy float32 reference (the contract asserts it).
Fast mode is `torch.compile` (Inductor: C++ on the CPU, which needs a C++ compiler; Triton
on CUDA, which may contract to FMA) with torch.sqrt; where compiling fails, fast mode runs
eager and its mode and driver say so. docs/peers.md has what was measured.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities
from clothbench.backends.kernel_inputs import VerletConstants, collider_rows
from clothbench.backends.numpy.verlet import ARGUMENTS, neighbour_regions

_INSTALL = "pip install 'clothbench[peers]'"
torch = None  # the torch module, imported on first use: clothbench imports without it


def _import_torch():
    global torch
    import torch as module

    torch = module
    return module


def probe() -> Availability:
    try:
        _import_torch()
    except ModuleNotFoundError as e:
        if e.name == "torch":
            return Availability(False, f"torch not installed ({_INSTALL})")
        return Availability(False, f"torch does not import: {e}")
    except Exception as e:  # e.g. a CUDA build whose libraries are missing here
        return Availability(False, f"torch does not import: {type(e).__name__}: {e}")
    return Availability(True, device=f"torch {torch.__version__} ({_default_device(torch)})")


def _default_device(torch) -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def dot3(a, b):
    """(a.x*b.x + a.y*b.y) + a.z*b.z, the association every kernel uses."""
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


def exact_sqrt(a):
    """float32 sqrt correctly rounded, which torch.sqrt's vectorised CPU float32 path is not
    (docs/peers.md): the float64 root rounded once to float32 is, as 53 >= 2 * 24 + 2 bits
    leave no double-rounding error."""
    return torch.sqrt(a.double()).float()


def step(pos, prev, w, free, c: dict, springs, colliders, sqrt):
    """x(t + dt) from x(t) = pos and x(t - dt) = prev, (3, n, n) planes (docs/semantics.md);
    `sqrt` is torch.sqrt (fast) or exact_sqrt (strict)."""
    # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
    vel = (pos - prev) / c["dt"]
    bv = c["b"] * vel
    force = torch.zeros_like(pos)
    for i, j, rest in springs:  # step 5: the 12 neighbours, in OFFSETS order
        d = pos[j] - pos[i]
        length2 = dot3(d, d)
        length = sqrt(length2)
        s = (c["k"] * (length - rest)) / length
        s = torch.where(length2 == 0, 0.0, s)  # coincident particles: no direction, no spring force
        force[i] += s * d - bv[i]
    # step 6: Verlet, acceleration = gravity + force * inverse mass
    acc = force * w + c["g"]
    new = (2 * pos - prev) + acc * c["dt2"]
    new = torch.where(free, new, pos)  # pinned particles do not move
    for kind, k in colliders:  # spheres, cylinders, boxes, then planes
        new = COLLIDE[kind](new, free, sqrt, **k)
    return new


def _collide_sphere(x, free, sqrt, c, r, top):
    d = x - c
    length2 = dot3(d, d)
    length = sqrt(length2)
    inside = (length < r) & free
    pushed = c + d * (r / length)
    pushed = torch.where(length2 == 0, top, pushed)  # exactly at the centre: straight up
    return torch.where(inside, pushed, x)


def _collide_cylinder(x, free, sqrt, a, u, length, r, radial_r):
    d = x - a
    t = dot3(d, u)  # axial coordinate (m) from the start cap
    q = u * t
    p = d - q  # radial vector
    rho2 = dot3(p, p)
    rho = sqrt(rho2)
    inside = (t > 0) & (t < length) & (rho < r) & free
    # push out the shortest way: through the side, or through the nearer cap
    side = r - rho
    to_end = length - t
    through_side = (side <= t) & (side <= to_end)
    through_start = ~through_side & (t <= to_end)
    pushed_side = torch.where(rho2 == 0, (a + q) + radial_r, (a + q) + p * (r / rho))  # on the axis: radial_r
    pushed = torch.where(through_side, pushed_side, torch.where(through_start, x - q, x + u * to_end))
    return torch.where(inside, pushed, x)


def _collide_box(x, free, sqrt, c, ax0, ax1, ax2, h0, h1, h2):
    d = x - c
    l0, l1, l2 = dot3(d, ax0), dot3(d, ax1), dot3(d, ax2)  # the box's own coordinates
    p0, p1, p2 = h0 - torch.abs(l0), h1 - torch.abs(l1), h2 - torch.abs(l2)  # depth through each face pair
    inside = (p0 > 0) & (p1 > 0) & (p2 > 0) & free
    # out through the face of least penetration, ties to the lower axis, on the particle's side
    take1 = p1 < p0
    take2 = p2 < torch.where(take1, p1, p0)
    lk = torch.where(take2, l2, torch.where(take1, l1, l0))
    hk = torch.where(take2, h2, torch.where(take1, h1, h0))
    axis = torch.where(take2, ax2, torch.where(take1, ax1, ax0))
    return torch.where(inside, x + axis * (torch.where(lk >= 0, hk, -hk) - lk), x)


def _collide_plane(x, free, sqrt, p0, nrm):
    dist = dot3(x - p0, nrm)
    return torch.where((dist < 0) & free, x - nrm * dist, x)


COLLIDE = {"sphere": _collide_sphere, "cylinder": _collide_cylinder, "box": _collide_box, "plane": _collide_plane}


def collider_tensors(scene: Scene, tensor) -> list[tuple[str, dict]]:
    """(kind, constants) of every collider in the order the step applies them, from
    kernel_inputs.collider_rows (float32, rounded once), as `tensor` makes them."""
    rows = collider_rows(scene)

    def vec(row):
        return tensor(row[:3].reshape(3, 1, 1))

    out = []
    for s in rows["spheres"]:
        top = s[:3].copy()
        top[1] = top[1] + s[3]  # c + (0, r, 0) in float32, as the reference adds it
        out.append(("sphere", {"c": vec(s), "r": tensor(s[3]), "top": vec(top)}))
    for a, u, radial_r in rows["cylinders"].reshape(-1, 3, 4):  # (start, length), (axis, r), (radial_r, 0)
        out.append(
            (
                "cylinder",
                {"a": vec(a), "u": vec(u), "length": tensor(a[3]), "r": tensor(u[3]), "radial_r": vec(radial_r)},
            )
        )
    for block in rows["boxes"].reshape(-1, 4, 4):  # (centre, 0), (axis i, half extent i): as the reference takes them
        out.append(("box", {name: tensor(value) for name, value in ARGUMENTS["box"](*block).items()}))
    for p, nrm in rows["planes"].reshape(-1, 2, 4):
        out.append(("plane", {"p0": vec(p), "nrm": vec(nrm)}))
    return out


def _compiler_missing(torch, device) -> str:
    """Why torch.compile cannot build here ('' where it can): Inductor needs a C++ compiler
    for the CPU and Triton for CUDA."""
    if device.type == "cuda":
        try:
            from torch.utils._triton import has_triton
        except ImportError:  # a release that moved it: the first step's fallback still says why
            return ""
        return "" if has_triton() else "no Triton for torch.compile on CUDA"
    try:
        from torch._inductor.cpp_builder import get_cpp_compiler
    except ImportError:  # a release that moved it: the first step's fallback still says why
        return ""
    try:
        get_cpp_compiler()
    except Exception as e:
        return f"no C++ compiler for torch.compile ({type(e).__name__}: {e})"
    return ""


class TorchBackend(Backend):
    name = "torch"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    capabilities = Capabilities(device=True, boxes=("verlet",), sweep_variants=({"strict": False}, {"strict": True}))

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        self._torch = _import_torch()
        name = options.device or _default_device(torch)
        try:
            self._device = torch.device(name)
            torch.zeros(1, device=self._device)
        except Exception as e:
            why = (str(e).strip().splitlines() or [""])[0]
            raise ClothbenchError(f"torch has no device {name!r} here ({type(e).__name__}: {why}); try cpu") from None

        def tensor(a):
            return torch.tensor(np.asarray(a, dtype=np.float32), device=self._device)

        n = scene.grid
        c = VerletConstants.of(scene, solver)
        self._c = {"dt": tensor(c.dt), "dt2": tensor(c.dt2), "k": tensor(c.k), "b": tensor(c.b)}
        self._c["g"] = tensor(np.array(c.g, dtype=np.float32).reshape(3, 1, 1))
        self._springs = [
            (*neighbour_regions(n, dr, dc), tensor(c.rest[kind])) for (dr, dc), kind in zip(OFFSETS, OFFSET_KIND)
        ]
        self._colliders = collider_tensors(scene, tensor)
        self.pos = self.prev = torch.zeros((3, n, n), device=self._device)
        self.w = torch.zeros((n, n), device=self._device)
        self.free = self.w != 0
        self._step, self._sqrt = step, exact_sqrt if options.strict else torch.sqrt
        self._compile_failure = ""
        if not options.strict:
            self._compile_failure = _compiler_missing(torch, self._device)
            if not self._compile_failure:
                # a fresh graph per grid and collider set (no dynamic shapes), and room for a
                # sweep's many of them: past dynamo's recompile limit it would run eager silently
                config = torch._dynamo.config
                limit = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"  # before 2.6
                setattr(config, limit, max(getattr(config, limit), 64))
                self._step = torch.compile(step, dynamic=False)
            self.mode_suffix = "/eager" if self._compile_failure else "/compiled"

    @property
    def device(self) -> str:
        torch, d = self._torch, self._device
        if d.type == "cuda":
            return f"torch {d} ({torch.cuda.get_device_name(d)})"
        return f"torch {d.type} ({torch.get_num_threads()} threads)"

    @property
    def driver(self) -> str:
        torch = self._torch
        cuda = f", CUDA {torch.version.cuda}" if self._device.type == "cuda" else ""
        failed = f"; torch.compile failed, ran eager: {self._compile_failure}" if self._compile_failure else ""
        return f"torch {torch.__version__}{cuda}{failed}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        torch, n = self._torch, self.scene.grid

        def planes(state):
            xyz = np.ascontiguousarray(state[:, :3].T.reshape(3, n, n), dtype=np.float32)
            return torch.tensor(xyz, device=self._device)

        self.pos, self.prev = planes(pos), planes(prev)
        self.w = torch.tensor(np.ascontiguousarray(pos[:, 3].reshape(n, n), dtype=np.float32), device=self._device)
        self.free = self.w != 0

    def advance(self, steps: int) -> None:
        for _ in range(steps):
            self.pos, self.prev = self._next(), self.pos

    def _next(self):
        args = (self.pos, self.prev, self.w, self.free, self._c, self._springs, self._colliders, self._sqrt)
        try:
            return self._step(*args)
        except Exception as e:  # torch.compile builds on the first call (the warm-up): say why, run eager
            if self._step is step:
                raise
            self._compile_failure = f"{type(e).__name__}: {(str(e).strip().splitlines() or [''])[0]}"
            self._step, self.mode_suffix = step, "/eager"
            return step(*args)

    def synchronize(self) -> None:
        if self._device.type == "cuda":
            self._torch.cuda.synchronize(self._device)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        n2 = self.scene.particles
        w = self.w.cpu().numpy().reshape(n2)

        def rows(planes):
            a = np.empty((n2, 4), dtype=np.float32)
            a[:, :3] = planes.cpu().numpy().reshape(3, n2).T
            a[:, 3] = w
            return a

        return rows(self.pos), rows(self.prev)

    def close(self) -> None:
        self.pos = self.prev = self.w = self.free = None
        self._springs, self._colliders, self._c = [], [], {}
