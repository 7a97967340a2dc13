"""JAX (peer): the step as a pure function of (3, n, n) component planes under `jax.jit`, and
k steps as one jitted `lax.fori_loop`, as JAX users write a time loop; float32, on JAX's
default device (a GPU where jaxlib has one, else the CPU).

docs/semantics.md, operation for operation in the NumPy reference's order
(backends/numpy/verlet.py): the 12 springs as whole-grid slices added with `.at[].add`, the
colliders as `jnp.where` selections (a jitted function has no data-dependent branch), the
constants device arrays passed as arguments.

Strict mode is the same code made IEEE, which XLA's CPU compiler allows only in two ways
(docs/peers.md has the measurements): dt is divided as a full array, since XLA rewrites a
division by a broadcast scalar as a multiplication by its reciprocal; and the CPU client
runs without FMA instructions (XLA_FLAGS=--xla_cpu_max_isa=AVX), since XLA contracts a*b + c
into an FMA whatever its per-compilation options say. That flag is read once, when JAX
starts in a process: a strict backend sets it if JAX has not started yet and refuses in one
line if it started without it; fast runs in such a process say `no-fma` in their mode.
Strict is bit-exact except for subnormals, which XLA's CPU threads flush to zero. The flag
is the CPU's: whether XLA's GPU code gives NumPy's bits is for the GPU check to find.
"""

from __future__ import annotations

import os

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Verlet
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities, import_failure
from clothbench.model.kernel_inputs import VerletConstants
from clothbench.backends.numpy.verlet import neighbour_regions
from clothbench.peers.array_colliders import COLLIDE, collider_tensors, dot3

_INSTALL = "pip install 'clothbench[peers]'"
NO_FMA = "--xla_cpu_max_isa=AVX"  # the newest x86 ISA XLA can target without FMA instructions
jnp = lax = None  # jax.numpy and jax.lax, imported on first use: clothbench imports without jax


def _import_jax():
    global jnp, lax
    import jax
    import jax.numpy
    import jax.lax

    jnp, lax = jax.numpy, jax.lax
    return jax


def probe() -> Availability:
    """Imports JAX without starting it: its CPU client reads XLA_FLAGS once, when it starts,
    and a strict backend may still need to set them (module docstring)."""
    try:
        jax = _import_jax()
    except Exception as e:  # not installed, or e.g. a jaxlib that does not match this jax
        return import_failure(e, "jax", _INSTALL, packages=("jax", "jaxlib"))
    return Availability(True, device=f"jax {jax.__version__}")


def _started() -> bool:
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def _cpu_without_fma() -> bool:
    """Whether this process's XLA_FLAGS keep FMA instructions from XLA's CPU code."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    return any(f in (NO_FMA, "--xla_cpu_max_isa=SSE4_2") for f in flags)


def _require_cpu_without_fma() -> None:
    if _cpu_without_fma():
        return
    if _started():
        raise ClothbenchError(
            "jax --strict needs JAX started without FMA contraction, and this process started it "
            f"with it: run jax --strict in a process of its own, or set XLA_FLAGS={NO_FMA}"
        )
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {NO_FMA}".strip()


def step(pos, prev, w, c: dict, springs, colliders):
    """x(t + dt) from x(t) = pos and x(t - dt) = prev, (3, n, n) planes (docs/semantics.md).
    `springs` (slices) and the colliders' kinds are static; every number is an argument."""
    free = w != 0
    # Listing 22.1 step 3: velocity from the two positions; damping uses it per spring
    vel = (pos - prev) / c["dt"]
    bv = c["b"] * vel
    force = jnp.zeros_like(pos)
    for (i, j), rest in zip(springs, c["rest"]):  # step 5: the 12 neighbours, in OFFSETS order
        d = pos[j] - pos[i]
        length2 = dot3(d, d)
        length = jnp.sqrt(length2)
        s = (c["k"] * (length - rest)) / length
        s = jnp.where(length2 == 0, jnp.float32(0), s)  # coincident particles: no direction, no spring force
        force = force.at[i].add(s * d - bv[i])
    # step 6: Verlet, acceleration = gravity + force * inverse mass
    acc = force * w + c["g"]
    new = (2 * pos - prev) + acc * c["dt2"]
    new = jnp.where(free, new, pos)  # pinned particles do not move
    for kind, k in zip(colliders, c["colliders"]):  # spheres, cylinders, boxes, then planes
        new = COLLIDE[kind](new, free, jnp, jnp.sqrt, **k)
    return new


class JaxBackend(Backend):
    name = "jax"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    # a sweep times fast only: a strict row after a fast one in the same process is refused
    # (JAX started with FMA), and a fast row after a strict one would not be JAX's default
    capabilities = Capabilities(device=True, boxes=("verlet",), sweep_variants=({"strict": False},))

    def __init__(self, scene: Scene, solver: Verlet, options: BackendOptions):
        super().__init__(scene, solver, options)
        jax = self._jax = _import_jax()
        if options.strict:
            _require_cpu_without_fma()  # before JAX starts (it starts on the first device asked for)
        try:
            self._device = jax.devices(options.device)[0] if options.device else jax.devices()[0]
        except Exception as e:
            why = (str(e).strip().splitlines() or [""])[0]
            raise ClothbenchError(
                f"jax has no device {options.device!r} here ({type(e).__name__}: {why}); try cpu"
            ) from None
        # XLA's CPU runtime flushes subnormal results to zero on its threads (docs/peers.md;
        # --xla_cpu_ftz=false does not stop it), so a strict run says where it parts from NumPy
        # (harness/strict_watch.py)
        self.flushes_subnormals = self._device.platform == "cpu"
        if self._device.platform == "cpu" and _cpu_without_fma() and not options.strict:
            self.mode_suffix = "/no-fma"  # a strict run started JAX here: fast runs without FMA too

        def tensor(a):
            return jax.device_put(np.asarray(a, dtype=np.float32), self._device)

        n = scene.grid
        c = VerletConstants.of(scene, solver)
        springs = tuple(neighbour_regions(n, dr, dc) for dr, dc in OFFSETS)
        colliders = collider_tensors(scene, tensor)
        self._c = {
            "dt": tensor(c.dt),
            "dt2": tensor(c.dt2),
            "k": tensor(c.k),
            "b": tensor(c.b),
            "g": tensor(np.array(c.g, dtype=np.float32).reshape(3, 1, 1)),
            "rest": [tensor(c.rest[kind]) for kind in OFFSET_KIND],
            "colliders": [k for _, k in colliders],
        }
        if options.strict:
            # XLA rewrites a division by a broadcast scalar as a multiplication by its
            # reciprocal (not the IEEE quotient); a full array of dt is divided by element
            self._c["dt"] = tensor(np.full((3, n, n), c.dt))
        kinds = tuple(kind for kind, _ in colliders)

        def many(pos, prev, w, consts, steps):
            def body(_, state):
                pos, prev = state
                return step(pos, prev, w, consts, springs, kinds), pos

            return lax.fori_loop(0, steps, body, (pos, prev))

        # steps is traced: one compilation for every chunk length, one step included
        self._many = jax.jit(many)
        self.pos = self.prev = self.w = tensor(np.zeros((3, n, n)))

    @property
    def device(self) -> str:
        d = self._device
        return f"jax {d.platform} ({getattr(d, 'device_kind', d.platform)})"

    @property
    def driver(self) -> str:
        import jaxlib

        return f"jax {self._jax.__version__}, jaxlib {jaxlib.__version__}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        n, put = self.scene.grid, self._jax.device_put

        def planes(state):
            return put(np.ascontiguousarray(state[:, :3].T.reshape(3, n, n), dtype=np.float32), self._device)

        self.pos, self.prev = planes(pos), planes(prev)
        self.w = put(np.ascontiguousarray(pos[:, 3].reshape(n, n), dtype=np.float32), self._device)

    def advance(self, steps: int) -> None:
        if steps > 0:
            self.pos, self.prev = self._many(self.pos, self.prev, self.w, self._c, steps)

    def synchronize(self) -> None:
        self.pos.block_until_ready()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        n2 = self.scene.particles
        w = np.asarray(self.w).reshape(n2)

        def rows(planes):
            a = np.empty((n2, 4), dtype=np.float32)
            a[:, :3] = np.asarray(planes).reshape(3, n2).T
            a[:, 3] = w
            return a

        return rows(self.pos), rows(self.prev)

    def close(self) -> None:
        self.pos = self.prev = self.w = None
        self._c = {}
