"""What a sweep is asked to measure (SweepSettings), checked before anything runs; apart from
harness/sweep.py, which runs it, so the settings can be built and checked without the runner."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from clothbench.backends import BackendOptions
from clothbench.backends.base import MESH_COLLISIONS
from clothbench.errors import ClothbenchError
from clothbench.harness.executor import DEFAULT_ROW_TIMEOUT
from clothbench.harness.plan import scene_variants
from clothbench.model.scene import Setup


@dataclass
class SweepSettings:
    setup: Setup  # the scene file; grid and run length are set per row
    grids: list[int]
    steps: int  # per chunk
    repeats: int
    base: BackendOptions = field(default_factory=BackendOptions)
    local_sizes: tuple[int, ...] = ()
    solvers: tuple[str, ...] = ("verlet",)  # solver specs (solver.SOLVER_SPECS)
    generic: str = "no"  # no | yes | both (plan.GENERIC_CHOICES)
    isolate: bool = True  # each row in a worker process (harness/executor.py)
    row_timeout: float | None = DEFAULT_ROW_TIMEOUT  # seconds, per row (isolated rows only)
    row_budget: float | None = None  # seconds of timed run per row; slower rows run fewer steps
    bounds: bool = True  # measure the machine's limits once and give every row its bound
    # sweep dimensions of a scene with meshes or motion (harness/plan.py): mesh algorithms
    # (MESH_COLLISIONS; none: each backend's default), triangle counts of its built-in
    # shapes (none: the file's), motion on/off (none: the file's)
    mesh_collisions: tuple[str, ...] = ()
    mesh_triangles: tuple[int, ...] = ()
    motion: tuple[str, ...] = ()
    self_collision: tuple[str, ...] = ()  # the [self_collision] pass on/off (none: the file's)

    def __post_init__(self):
        if self.row_timeout is not None and not self.row_timeout > 0:
            raise ClothbenchError(f"--row-timeout must be > 0 seconds, got {self.row_timeout}")
        if self.row_budget is not None and not self.row_budget > 0:
            raise ClothbenchError(f"--row-budget must be > 0 seconds, got {self.row_budget}")
        if self.steps < 1:
            raise ClothbenchError(f"--steps must be >= 1 (steps per timed chunk), got {self.steps}")
        if self.repeats < 1:
            raise ClothbenchError(f"--repeat must be >= 1 (timed chunks per row), got {self.repeats}")
        if not self.grids:
            raise ClothbenchError("no grid size given (e.g. --grids 32,64,128,256)")
        # every grid and solver is checked now, before anything is measured
        self.solver_settings = [self.setup.solver_for(spec) for spec in self.solvers]
        scene = self.setup.scene
        if self.mesh_collisions and not scene.meshes:
            raise ClothbenchError(f"--mesh-collision: scene {scene.name} has no [[mesh]] collider")
        bad = [a for a in self.mesh_collisions if a not in MESH_COLLISIONS]
        if bad:
            takes = ", ".join(MESH_COLLISIONS)
            raise ClothbenchError(f"--mesh-collision takes {takes} (comma-separated), got {bad[0]!r}")
        # (variant, scene, notes): what each row's scene is, checked now
        self.scene_variants = scene_variants(scene, self.mesh_triangles, self.motion, self.self_collision)
        self.notes = [n for _, _, notes in self.scene_variants for n in notes]
        self.setups = {
            (g, sv): dataclasses.replace(self.setup, scene=s).replace(grid=g, steps=self.steps * self.repeats)
            for g in self.grids
            for sv, s, _ in self.scene_variants
        }
