"""Substeps against iterations at equal cost (Macklin et al. 2019, "Small steps in physics
simulation"): the PBD error of each (substeps, iterations) pair whose product is a given
cost, against one converged float64 reference, and what each pair costs per frame.

The reference is the converged float64 mass-spring (Verlet) answer of the same scene
(analysis/convergence.converged_reference), not PBD at many iterations: it is what the
coloured form converges to as dt shrinks (docs/pbd.md), it is the same for both methods and
every pair, and it does not depend on the setting being measured. docs/pbd-study.md says why,
and why the study runs undamped by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from clothbench.analysis.convergence import F64, Reference, converged_reference, steps_for, structural_strain
from clothbench.backends import BackendOptions, create_backend
from clothbench.environment import cpu_model
from clothbench.harness.simulate import position_error, simulate
from clothbench.harness.timing import run_timed
from clothbench.machine_load import MIN_WINDOW_S, LoadSampler
from clothbench.model.scene import Scene
from clothbench.model.solver import Pbd, Verlet

FRAME_DT = 1 / 60  # the frame PBD is stepped at: what it is used for
REFERENCE_DT = FRAME_DT / 32  # Verlet's finest measured dt (under its 2 ms limit at k = 1000), halved below
COST_BACKENDS = ("numpy", "opencl")  # float32, where ms/step is measured
PEER_METHODS = ("newton",)  # a --methods entry that runs a peer's own PBD instead of clothbench's


def pairs_at(cost: int) -> list[tuple[int, int]]:
    """(substeps, iterations) with substeps * iterations == cost, fewest substeps first."""
    return [(s, cost // s) for s in range(1, cost + 1) if cost % s == 0]


@dataclass
class PbdStudyRow:
    scene: str
    grid: int
    damping: float
    time_s: float
    frame_dt: float
    method: str
    substeps: int
    iterations: int
    cost: int  # substeps * iterations: constraint passes per frame
    status: str = "ok"
    rms: float = float("nan")  # m, against the converged reference
    max: float = float("nan")
    strain: float = float("nan")  # mean structural strain at time_s (the reference's is ref_strain)
    ref_strain: float = float("nan")
    ref_model: str = "verlet f64 converged"
    ref_dt: float = float("nan")
    ref_converged: bool = False
    ref_uncertainty: float = float("nan")  # m, max norm
    ms_numpy: float = float("nan")  # ms per frame step, float32, median of chunks
    ms_opencl: float = float("nan")
    ms_newton: float = float("nan")  # method "newton" only: the peer's own run, which the error is of
    device_opencl: str = ""
    driver_opencl: str = ""  # which OpenCL runtime timed ms_opencl ('' in files older than the column)
    cpu: str = ""
    # whether other processes were busy while the ms were timed (clothbench/machine_load.py, as a
    # sweep row's `busy`); None: nothing timed, too short to tell, or a file older than the column
    busy: bool | None = None
    load: str = ""  # what the load was, over how long

    def as_dict(self) -> dict:
        return dict(self.__dict__)


def study_reference(scene: Scene, time_s: float, on_level: Callable[[int, float], None] | None = None) -> Reference:
    """The converged float64 mass-spring state of `scene` at `time_s` (rest start)."""
    return converged_reference(scene, Verlet(dt=REFERENCE_DT), time_s, REFERENCE_DT, on_level=on_level)


def _time(backend: str, scene: Scene, solver: Pbd, steps: int) -> tuple[float, str, str]:
    """(median ms per step, device, driver) of `backend` in float32, or (nan, why, '') where it
    cannot run."""
    try:
        with create_backend(backend, scene, solver, BackendOptions()) as b:
            result = run_timed(b, steps, raise_on_blowup=False)
            return result.ms_per_step, result.device, result.driver
    except Exception as e:  # a backend that cannot run this pair is a row saying so, not a dead study
        return float("nan"), f"not run: {type(e).__name__}: {e}", ""


def measure_pair(
    scene: Scene,
    method: str,
    substeps: int,
    iterations: int,
    time_s: float,
    ref: Reference,
    cost_backends=COST_BACKENDS,
    frame_dt: float = FRAME_DT,
) -> PbdStudyRow:
    """One pair: its float64 error against `ref` and its float32 cost per frame. Method
    "newton" is the Newton XPBD peer (peers/newton.py): its one float32 run gives both."""
    peer = method in PEER_METHODS
    solver = Pbd(dt=frame_dt, method="coloured" if peer else method, substeps=substeps, iterations=iterations)
    steps = steps_for(time_s, frame_dt)
    row = PbdStudyRow(
        scene.name,
        scene.grid,
        scene.damping,
        time_s,
        frame_dt,
        method,
        substeps,
        iterations,
        substeps * iterations,
        ref_dt=ref.dt,
        ref_converged=ref.converged,
        ref_uncertainty=ref.uncertainty,
        ref_strain=structural_strain(ref.pos, scene),
        cpu=cpu_model(),
    )
    if peer:
        return _measure_peer(row, method, scene, solver, steps, ref)
    pos, _ = simulate("numpy", scene, solver, steps, F64)
    if not math.isfinite(float(abs(pos[:, :3]).max())):
        row.status = "unstable"
    else:
        row.rms, row.max = position_error(pos, ref.pos)
        row.strain = structural_strain(pos, scene)
    if cost_backends:
        watch = LoadSampler().start()
        for backend in cost_backends:
            ms, device, driver = _time(backend, scene, solver, steps)
            setattr(row, f"ms_{backend}", ms)
            if backend == "opencl":
                row.device_opencl, row.driver_opencl = device, driver
        _record_load(row, watch)
    return row


def _record_load(row: PbdStudyRow, window) -> None:
    # a pair's timing at a small grid can be shorter than a verdict needs: the window is then
    # made up to MIN_WINDOW_S by sleeping, which sees only the other processes (machine_load)
    load = window.stop(min_window_s=MIN_WINDOW_S)
    row.busy, row.load = load.busy, load.why


def how_busy(rows: list[PbdStudyRow]) -> str:
    """How busy the machine was while the rows' ms were timed, in a phrase for a figure's title:
    'how busy not recorded' where no row knows (files older than the column), else how many
    were timed on a busy machine."""
    known = [r for r in rows if r.busy is not None]
    if not known:
        return "how busy not recorded"
    busy = sum(r.busy for r in known)
    if not busy and len(known) == len(rows):
        return "the machine quiet throughout"
    if not busy:
        return f"the machine quiet for {len(known)} of {len(rows)} runs, not recorded for the rest"
    return f"{busy} of {len(rows)} runs timed on a busy machine"


def _measure_peer(row: PbdStudyRow, backend: str, scene: Scene, solver: Pbd, steps: int, ref: Reference):
    try:
        with create_backend(backend, scene, solver, BackendOptions()) as b:
            watch = LoadSampler().start()
            result = run_timed(b, steps, raise_on_blowup=False)
            _record_load(row, watch)
    except Exception as e:  # a peer that cannot run is a row saying so
        row.status = " ".join(f"error: {type(e).__name__}: {e}".split())
        return row
    setattr(row, f"ms_{backend}", result.ms_per_step)
    if result.blowup is not None:
        row.status = f"unstable at step {result.blowup.step}"
    else:
        row.rms, row.max = position_error(result.pos, ref.pos)
        row.strain = structural_strain(result.pos, scene)
    return row


def best_per_cost(rows: list[PbdStudyRow]) -> dict[tuple[str, str, int], PbdStudyRow]:
    """(scene, method, cost) -> the pair with the smallest RMS error at that cost."""
    best: dict[tuple[str, str, int], PbdStudyRow] = {}
    for r in rows:
        if r.status != "ok":
            continue
        key = (r.scene, r.method, r.cost)
        if key not in best or r.rms < best[key].rms:
            best[key] = r
    return best


__all__ = [
    "FRAME_DT",
    "REFERENCE_DT",
    "COST_BACKENDS",
    "PEER_METHODS",
    "pairs_at",
    "PbdStudyRow",
    "study_reference",
    "measure_pair",
    "best_per_cost",
    "how_busy",
]
