"""What the GPU backends of the solvers that keep a velocity share: DeviceSolverBackend, the
host side of a substep made of launches apart from the device calls, and its two plans,
PbdDeviceBackend (docs/pbd.md: opencl/pbd.py, gl/compute_pbd.py) and VbdDeviceBackend
(docs/vbd.md: gl/compute_vbd.py).

One substep is a fixed list of launches, each seeing the previous one's writes. PBD's:
predict, then `iterations` Jacobi passes ping-ponging two buffers (or 12 coloured batches per
iteration), collide (or the self-collision pass, which collides after it), update. VBD's: predict, then per iteration one sweep launch per vertex
colour (and with Chebyshev an extrapolation), collide (or the self-collision pass), update. This module plans that list,
converts the state to and from velocity, advances and profiles by stage; a subclass makes
each launch for its device.
"""

from __future__ import annotations

import numpy as np

from clothbench.model.constraints import VERTEX_COLOURS, coloured_batches, vertex_colours
from clothbench.errors import ClothbenchError
from clothbench.model.scene import Scene
from clothbench.model.solver import Pbd, Solver, Vbd
from clothbench.backends.base import Backend, BackendOptions
from clothbench.model.kernel_inputs import PbdConstants, VbdConstants


def velocity_state(pos: np.ndarray, prev: np.ndarray, dt) -> tuple[np.ndarray, np.ndarray]:
    """(x, v) of an uploaded (pos, prev), float32 rows of four: v = (x - xp) / dt, once, in
    float32 as the references do it (docs/pbd.md, docs/vbd.md: the solvers that keep velocities)."""
    x = np.array(pos, dtype=np.float32)
    v = np.zeros_like(x)
    v[:, :3] = (x[:, :3] - np.asarray(prev, dtype=np.float32)[:, :3]) / dt
    return x, v


def position_state(x: np.ndarray, v: np.ndarray, dt) -> tuple[np.ndarray, np.ndarray]:
    """(pos, prev) of a device's (x, v), as read() gives it: prev = x - v dt."""
    prev = x.copy()
    prev[:, :3] = x[:, :3] - v[:, :3] * dt
    return x, prev


def batch_stage_name(batch) -> str:
    """The profile's name of a coloured batch: its direction and parity."""
    dr, dc = batch.direction
    return f"batch ({dr},{dc:+d}) parity {batch.parity}"


class DeviceSolverBackend(Backend):
    """What the GPU solver backends share. A subclass sets `self.constants` (its solver's, with
    `dt`), plans one substep (_substep_plan) and builds `self.launches` from it, one substep as
    [(stage name, launch)]; it says how to enqueue a launch, time one on its own, wait for them
    all (synchronize), and move the (x, v) state to and from the device. It declares its
    capabilities: no transfer modes, no --generic (the kernels are always specialised to the
    scene), no normals."""

    constants: PbdConstants | VbdConstants

    def __init__(self, scene: Scene, solver: Solver, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.strict = options.strict
        self.n = scene.grid
        self.n2 = scene.particles
        self.launches: list[tuple[str, object]] = []  # one substep: (stage, launch)
        # what profile_stages() times, where advance() runs fused launches (None: the same)
        self.stage_launches: list[tuple[str, object]] | None = None
        self.substeps_done = 0  # since the last upload(): the clock of moving bodies

    # --- what a subclass supplies ------------------------------------------------------
    def _write_state(self, x: np.ndarray, v: np.ndarray) -> None:
        raise NotImplementedError

    def _read_state(self) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _enqueue(self, launch) -> None:
        raise NotImplementedError

    def _timed(self, launch) -> float:
        """Run one launch on its own, synchronised; its time in seconds."""
        raise NotImplementedError

    # --- moving bodies: per-substep constants (docs/pbd.md, "Colliders, motion and attached pins")
    def _motion_block(self) -> int:
        """Substeps whose poses and pin targets one upload holds; 0: the scene does not move."""
        return 0

    def _upload_motion(self, first: int, count: int) -> None:
        """Upload the poses and pin targets of substeps first .. first + count - 1 (counted
        from the last upload(); substep j's at the end of it, (j + 1) * dt / substeps)."""

    def _use_substep(self, j: int) -> None:
        """Point the next substep's launches at entry j of the last _upload_motion()."""

    def _blocks(self, steps: int):
        """The substeps of `steps` steps as counts of consecutive substeps, each yielded after
        its per-substep constants are uploaded (one block where the scene does not move)."""
        total = steps * self.solver.substeps
        moving = self._motion_block()
        block = moving or max(total, 1)
        for done in range(0, total, block):
            count = min(block, total - done)
            if moving:
                self._upload_motion(self.substeps_done, count)
            yield count
            self.substeps_done += count

    # --- the substep as launches -------------------------------------------------------
    def _substep_plan(self, *args) -> list[tuple]:
        """One substep as steps (stage, what, ...) in launch order."""
        raise NotImplementedError

    def _launches_of(self, step) -> list:
        """The launches (one or more) of one step of the plan."""
        raise NotImplementedError

    def _plan_launches(self, *args) -> list[tuple[str, object]]:
        plan = self._substep_plan(*args)
        return [(self.stage_of(step), launch) for step in plan for launch in self._launches_of(step)]

    def stage_of(self, step) -> str:
        return step[0]

    # --- Backend interface ---------------------------------------------------------------
    def upload(self, pos: np.ndarray, prev: np.ndarray) -> None:
        expected = (self.n2, 4)
        if pos.shape != expected or prev.shape != expected:
            raise ClothbenchError(f"state must be two {expected} arrays, got {pos.shape} and {prev.shape}")
        self.substeps_done = 0  # the uploaded state is at t = 0: moving bodies start over
        self._write_state(*velocity_state(pos, prev, self.constants.dt))

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return position_state(*self._read_state(), self.constants.dt)

    def advance(self, steps: int) -> None:
        enqueue = self._enqueue
        for count in self._blocks(steps):
            for j in range(count):
                self._use_substep(j)
                for _, launch in self.launches:
                    enqueue(launch)

    def profile_stages(self, steps: int) -> dict[str, float]:
        """Advance `steps` steps with a synchronisation after every launch; ms per step of
        each stage (a stage's launches summed over iterations and substeps)."""
        self.synchronize()
        totals: dict[str, float] = {}
        launches = self.launches if self.stage_launches is None else self.stage_launches
        for count in self._blocks(steps):
            for j in range(count):
                self._use_substep(j)
                for stage, launch in launches:
                    totals[stage] = totals.get(stage, 0.0) + self._timed(launch)
        return {stage: 1e3 * seconds / max(steps, 1) for stage, seconds in totals.items()}


class PbdDeviceBackend(DeviceSolverBackend):
    """The PBD solver's plan (docs/pbd.md): Jacobi passes or coloured batches."""

    def __init__(self, scene: Scene, solver: Pbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.constants = PbdConstants.of(scene, solver)
        self.jacobi = solver.method == "jacobi"
        self.chebyshev = self.jacobi and solver.chebyshev_rho > 0  # Jacobi only (docs/pbd.md)
        self.batches = [] if self.jacobi else coloured_batches(self.n)
        # lambda: 12 per particle (Jacobi) or one per constraint (coloured)
        self.lambda_count = 12 * self.n2 if self.jacobi else sum(len(b.i) for b in self.batches)
        # coloured: every batch's (i, j) pairs, concatenated (uploaded once), and where each starts
        self.batch_pairs = self.batch_offsets = None
        if not self.jacobi:
            pairs = np.concatenate([np.stack([b.i, b.j], axis=1) for b in self.batches])
            self.batch_pairs = np.ascontiguousarray(pairs.astype(np.int32))
            self.batch_offsets = np.cumsum([0] + [len(b.i) for b in self.batches])[:-1]

    # --- the substep as launches -------------------------------------------------------
    def _substep_plan(self, coloured_sweep: bool = False):
        """One substep as (stage, what, ...) in launch order: ("predict",), ("jacobi",
        iteration, source index, target index), ("coloured", iteration, batch index) or, with
        `coloured_sweep`, ("coloured sweep", iteration) for all 12 batches in one launch,
        ("collide", buffer index), ("update", buffer index), where a buffer index names one
        of the two predicted-position buffers (predict writes 0). With [self_collision],
        ("self collision", source index, target index) takes collide's place: the pass (and
        the colliders after it) from the last iterate into the other buffer, which update reads."""
        plan = [("predict",)]
        for it in range(self.solver.iterations):
            if self.jacobi:
                plan.append(("jacobi", it, it % 2, 1 - it % 2))
            elif coloured_sweep:
                plan.append(("coloured sweep", it))
            else:
                plan += [("coloured", it, b) for b in range(len(self.batches))]
        final = self.solver.iterations % 2 if self.jacobi else 0
        if self.scene.self_collision is not None:
            return plan + [("self collision", final, 1 - final), ("update", 1 - final)]
        if self.scene.colliders or self.scene.meshes:
            plan.append(("collide", final))
        plan.append(("update", final))
        return plan

    def stage_of(self, step) -> str:
        if step[0] == "jacobi":
            return "project (jacobi)"
        if step[0] == "coloured sweep":
            return "project (coloured)"
        if step[0] == "coloured":
            return batch_stage_name(self.batches[step[2]])
        return step[0]


class VbdDeviceBackend(DeviceSolverBackend):
    """The VBD solver's plan (docs/vbd.md): per iteration the 4 vertex colours in order, each
    launch one Newton step for every particle of its colour (a range of `colour_order`)."""

    def __init__(self, scene: Scene, solver: Vbd, options: BackendOptions):
        super().__init__(scene, solver, options)
        self.constants = VbdConstants.of(scene, solver)
        self.chebyshev = solver.chebyshev_rho > 0  # rho = 0: no extrapolation at all, as NumPy's
        colour = vertex_colours(self.n)
        # every particle, by colour (the sweep's order); where each colour starts, and how many
        self.colour_order = np.argsort(colour, kind="stable").astype(np.int32)
        self.colour_counts = np.bincount(colour, minlength=VERTEX_COLOURS)
        self.colour_starts = np.cumsum([0, *self.colour_counts])[:-1]

    def _substep_plan(self) -> list[tuple]:
        """One substep as ("predict",), ("sweep", iteration, colour), ("chebyshev", iteration)
        for the extrapolation after sweep `iteration` (iteration -1: the predicted iterate,
        kept as the first sweep's input), ("collide",), ("update",), in launch order. With
        [self_collision], ("self collision",) takes collide's place: the pass (and the colliders
        after it) from the final iterate into y (no longer read), which update then reads."""
        plan: list[tuple] = [("predict",)]
        if self.chebyshev:
            plan.append(("chebyshev", -1))
        for it in range(self.solver.iterations):
            plan += [("sweep", it, colour) for colour in range(VERTEX_COLOURS) if self.colour_counts[colour]]
            if self.chebyshev:
                plan.append(("chebyshev", it))
        if self.scene.self_collision is not None:
            return plan + [("self collision",), ("update",)]
        if self.scene.colliders or self.scene.meshes:
            plan.append(("collide",))
        plan.append(("update",))
        return plan
