"""NVIDIA Newton (peer): the scene through Newton's XPBD solver, as Newton users build it.

Newton is the physics engine Warp's cloth solvers moved into (`pip install newton`); on a
machine without CUDA it runs its Warp kernels on the CPU. This peer builds the same particles
and the same 12-neighbour springs as clothbench (docs/newton.md says why springs, not
Newton's own triangle-and-bending cloth grid), the colliders as static shapes, and steps it
with `SolverXPBD`: `substeps` solver steps of h = dt / substeps a step, `iterations` each.

It is Newton's model, not docs/pbd.md: its Jacobi sums every constraint's full correction
(no averaging, no relaxation on springs), contacts are constraints solved inside the
iterations from contact points found once a substep, and there is no velocity drag (the
scene's b is not represented). So it is compared with clothbench by physics (the hanging
sheet's sag and extent, pins, penetration: tests/test_newton_peer.py), never bit for bit;
the [pbd] method (jacobi or coloured) names the clothbench model a row is compared with and
does not change what Newton runs.

Its VBD class (NewtonVbdBackend, issue 33 item 3) is the same scene stepped by `SolverVBD`:
the same springs, particles coloured by Newton's builder (`ModelBuilder.color()`), `iterations`
per substep. Newton's VBD is implicit Euler too (docs/vbd.md is clothbench's), with its own
contact model and, again, no drag: compared by physics, not bit for bit.
"""

from __future__ import annotations

import numpy as np

from clothbench.errors import ClothbenchError
from clothbench.model.scene import OFFSET_KIND, OFFSETS, Scene
from clothbench.model.solver import Pbd, Vbd
from clothbench.backends.base import Availability, Backend, BackendOptions, Capabilities, import_failure
from clothbench.model.kernel_inputs import rest_by_kind
from clothbench.peers.warp import import_warp, init_quietly

_INSTALL = "pip install 'clothbench[peers]'"
# Where a particle's contact with a shape is looked for, beyond touching (m): the largest
# distance a free particle moves in one substep at the speeds of these scenes (~3 m/s at
# 1/60 s) must fit, or a fast particle passes a collider between two contact searches.
CONTACT_GAP = 0.06


def _import_newton():
    wp = import_warp()  # the same quiet Warp the warp peer runs (no banner on stdout)
    init_quietly(wp)
    import newton

    return wp, newton


def probe() -> Availability:
    try:
        wp, newton = _import_newton()
    except Exception as e:  # not installed, or e.g. a newton built for another warp
        return import_failure(e, "newton", _INSTALL, packages=("newton", "warp"))
    device = "cuda" if wp.is_cuda_available() else "cpu"
    return Availability(True, device=f"newton {newton.__version__} xpbd, warp {wp.__version__} ({device})")


def stencil_springs(n: int) -> list[tuple[int, int, int]]:
    """(i, j, kind) of every undirected spring of an n x n grid, i < j: the stencil's
    offsets (scene.OFFSETS) taken forwards only, so each spring once."""
    springs = []
    for (dr, dc), kind in zip(OFFSETS, OFFSET_KIND):
        if (dr, dc) <= (0, 0):  # the backward half of the stencil: the same springs again
            continue
        for r in range(max(0, -dr), min(n, n - dr)):
            for c in range(max(0, -dc), min(n, n - dc)):
                springs.append((r * n + c, (r + dr) * n + (c + dc), kind))
    return springs


class NewtonPbdBackend(Backend):
    name = "newton"
    kind = "xpbd"  # Newton's solver, as the device line names it
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    # one mode (Newton's kernels, no strict form of docs/pbd.md); --device picks Warp's device
    capabilities = Capabilities(strict=False, device=True)

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        unmapped = [kind for kind in ("cylinders", "meshes", "frames") if getattr(scene, kind, ())]
        if unmapped:  # moving colliders and meshes are not mapped either: static spheres and planes only
            raise ClothbenchError(
                f"newton peer: {', '.join(unmapped)} are not mapped (static spheres and planes are); use another scene"
            )
        wp, newton = self._wp, self._newton = _import_newton()
        name = options.device or ("cuda" if wp.is_cuda_available() else "cpu")
        try:
            self._device = wp.get_device(name)
        except Exception as e:
            raise ClothbenchError(f"newton has no device {name!r} here ({e}); try cpu") from None
        self.model = self._build(scene, solver)
        self.h = solver.dt / solver.substeps
        self.newton_solver = self._newton_solver(newton, solver)
        self.state_0, self.state_1 = self.model.state(), self.model.state()
        self.control = self.model.control()
        self.pipeline = newton.CollisionPipeline(self.model, soft_contact_gap=CONTACT_GAP)
        self.contacts = self.pipeline.contacts()

    def _newton_solver(self, newton, solver: Pbd):
        return newton.solvers.SolverXPBD(self.model, iterations=solver.iterations)

    def _compliance(self, scene: Scene, solver: Pbd) -> tuple[float, float, float]:
        return solver.compliance_for(scene)

    def _before_finalize(self, builder) -> None:
        """What the solver needs of the builder before the model is made (VBD: its colours)."""

    def _build(self, scene: Scene, solver: Pbd):
        wp, newton = self._wp, self._newton
        builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=tuple(scene.gravity))
        pos, _ = scene.initial_state(np.float64)
        for p in pos:  # pinned particles: mass 0, which Newton keeps where they are
            builder.add_particle(tuple(p[:3]), (0.0, 0.0, 0.0), scene.mass if p[3] != 0 else 0.0, radius=0.0)
        compliance = self._compliance(scene, solver)
        rest = rest_by_kind(scene, np.float32)
        for i, j, kind in stencil_springs(scene.grid):
            # XPBD compliance 1/ke, as clothbench's; no spring damping (clothbench's drag is not along springs)
            builder.add_spring(i, j, ke=1.0 / compliance[kind] if compliance[kind] > 0 else 1e30, kd=0.0, control=0.0)
            builder.spring_rest_length[-1] = float(rest[kind])  # the scene's rest lengths, not re-measured
        frictionless = newton.ModelBuilder.ShapeConfig(mu=0.0)  # clothbench's colliders project, no friction
        for s in scene.spheres:
            builder.add_shape_sphere(
                -1, xform=wp.transform(wp.vec3(*s.center), wp.quat_identity()), radius=s.radius, cfg=frictionless
            )
        for pl in scene.planes:
            nx, ny, nz = pl.unit_normal
            d = -(nx * pl.point[0] + ny * pl.point[1] + nz * pl.point[2])
            builder.add_shape_plane((nx, ny, nz, d), width=0.0, length=0.0, cfg=frictionless)
        self._before_finalize(builder)
        model = builder.finalize(device=self._device)
        model.soft_contact_mu = 0.0
        return model

    @property
    def device(self) -> str:
        d = self._device
        where = "1 thread" if d.is_cpu else d.name
        return f"newton {self.kind}, warp {d.alias} ({where})"

    @property
    def driver(self) -> str:
        return f"newton {self._newton.__version__}, warp {self._wp.__version__}"

    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        wp = self._wp
        x = np.ascontiguousarray(pos[:, :3], dtype=np.float32)
        v = ((pos[:, :3].astype(np.float64) - prev[:, :3]) / self.solver.dt).astype(np.float32)
        v[pos[:, 3] == 0] = 0.0
        self.w = np.asarray(pos[:, 3], dtype=np.float32)
        for state in (self.state_0, self.state_1):
            state.particle_q.assign(wp.array(x, dtype=wp.vec3, device=self._device))
            state.particle_qd.assign(wp.array(v, dtype=wp.vec3, device=self._device))

    def advance(self, steps: int) -> None:
        for _ in range(steps * self.solver.substeps):
            self.state_0.clear_forces()
            self.pipeline.collide(self.state_0, self.contacts)
            self.newton_solver.step(self.state_0, self.state_1, self.control, self.contacts, self.h)
            self.state_0, self.state_1 = self.state_1, self.state_0

    def synchronize(self) -> None:
        self._wp.synchronize_device(self._device)

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        x = self.state_0.particle_q.numpy().astype(np.float32)
        v = self.state_0.particle_qd.numpy().astype(np.float32)
        pos = np.concatenate([x, self.w[:, None]], axis=1)
        prev = pos.copy()
        prev[:, :3] = x - v * np.float32(self.solver.dt)  # the state's velocity as (pos - prev) / dt
        return pos, prev

    def close(self) -> None:
        self.state_0 = self.state_1 = self.contacts = None


class NewtonVbdBackend(NewtonPbdBackend):
    """The same scene through Newton's SolverVBD (docs/newton.md): the springs' stiffness is the
    scene's k (VBD takes stiffness, not compliance)."""

    kind = "vbd"
    device_timer = ""  # no device clock read: a peer is timed as a user would time it
    capabilities = NewtonPbdBackend.capabilities  # the same one mode and --device

    def _newton_solver(self, newton, solver: Vbd):
        return newton.solvers.SolverVBD(self.model, iterations=solver.iterations)

    def _compliance(self, scene: Scene, solver: Vbd) -> tuple[float, float, float]:
        if scene.stiffness == 0:
            raise ClothbenchError("newton vbd needs stiffness > 0 (its springs take ke = stiffness)")
        return (1.0 / scene.stiffness,) * 3

    def _before_finalize(self, builder) -> None:
        builder.color()  # SolverVBD solves particles colour by colour
