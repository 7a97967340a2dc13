"""Timed runs, the same for every backend.

What is inside the timed region: only `advance(chunk)` between two `synchronize()` calls,
so the clock sees the steps and nothing else. The upload of the initial state and the
readback after each chunk (used for the blow-up check) are outside it. A backend whose
transfer mode uploads every step (the chapter's OpenCL variant) does that inside
`advance`, so its cost is timed, as it should be. A strict run on a driver that flushes
subnormal floats has a NumPy float32 run stepped beside it, outside the timed region too
(strict_watch.py).

Warm-up: the backend is built (kernel compiled) and advanced WARMUP_STEPS steps on a
throwaway run before the timed run restarts from the initial state. What it is for is
everything a backend does once, on its first step, and must not be timed: a kernel compiled
or a program linked at its first launch, a JIT's first call, a thread pool started, the first
touch of every buffer (the upload writes one state buffer, the step the other), the first
readback's staging memory. One step does all of that; more would only take time (at 2048^2 a
float64 NumPy step takes seconds). A per-row time budget then times one more synchronised step
(_one_step_s), past all of it, to size the run.

Beside the wall clock, each chunk also takes the device's own time of the same advance()
where the backend has a device clock it trusts (backend.device_elapsed_ms): CUDA events, GL
timestamps, OpenCL profiling events. What each includes is DEVICE_TIMERS (docs/timing.md);
the wall clock includes all of it and the host's side: launches, and the synchronize.
"""

from __future__ import annotations

import statistics
import time
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from clothbench.errors import BlowUp
from clothbench.model.scene import Scene
from clothbench.model.solver import Solver
from clothbench.harness.energy import fast_impact_warning
from clothbench.harness.health import max_penetration, self_contact, state_problem
from clothbench.harness.strict_watch import StrictWatch, needs_watch

WARMUP_STEPS = 1  # the module's doc: what a warm-up is for, and why one step does it

# What a row says of a backend that reports device times without naming its clock
# (Backend.device_elapsed_ms's contract: the device's own profiling events).
UNNAMED_DEVICE_TIMER = "device-events"
# The device clocks a row's device_timer names, and what the device time of one advance()
# covers with each (docs/timing.md).
DEVICE_TIMERS = {
    "cuda-events": "CUDA events recorded on the stream before the first launch and after the last: the kernels, "
    "the device copies of --transfer copy, and any time the GPU waited for the host to launch the next kernel",
    "gl-timer-query": "GL timestamps (glQueryCounter) before the first draw or dispatch and after the last: the "
    "shaders and barriers, and any time the GPU waited for the host to submit the next one",
    "opencl-events": "each kernel's profiling events, start to end, summed: the kernels only, not the gaps between "
    "them nor the transfers of --transfer per-step",
    UNNAMED_DEVICE_TIMER: "the backend's own profiling events of its advance(); it does not name them",
}


@dataclass
class RunResult:
    backend: str
    device: str
    mode: str
    scene: Scene
    solver: Solver
    steps: int
    driver: str = ""  # Backend.driver: which runtime (of several for one device) ran it, and its version
    chunk_ms_per_step: list[float] = field(default_factory=list)  # one per timed chunk
    device_ms_per_step: list[float] = field(default_factory=list)  # the device's clock, if any
    device_timer: str = ""  # which device clock measured device_ms_per_step (DEVICE_TIMERS); '' none
    warmup_s: float = 0.0  # build/compile plus the warm-up steps
    pos: np.ndarray | None = None
    prev: np.ndarray | None = None
    blowup: BlowUp | None = None
    warnings: list[str] = field(default_factory=list)  # one line each, said once
    chunk: int = 0  # steps per timed chunk, as run (a time budget can make it smaller)
    budget_cut: bool = False  # the time budget shortened the run (steps and chunk say what ran)
    # --strict on a driver that flushes subnormals: the first step it parts from NumPy f32
    strict_divergence: str | None = None

    @property
    def ms_per_step(self) -> float:
        return statistics.median(self.chunk_ms_per_step) if self.chunk_ms_per_step else float("nan")

    @property
    def finite(self) -> bool:
        return self.pos is not None and bool(np.isfinite(self.pos[:, :3]).all())

    @property
    def max_penetration(self) -> float:
        return max_penetration(self.pos, self.scene) if self.pos is not None else float("nan")

    @property
    def self_contact(self) -> tuple[int, float] | None:
        """(pairs closer than the thickness, smallest distance) at the end; None without
        [self_collision] (harness/health.py)."""
        return self_contact(self.pos, self.scene) if self.pos is not None else None

    def spread(self) -> dict[str, float]:
        """min, max and inter-quartile range of the per-chunk ms/step."""
        xs = sorted(self.chunk_ms_per_step)
        if not xs:
            return {"min": float("nan"), "max": float("nan"), "iqr": float("nan")}
        q = np.percentile(xs, [25, 75])
        return {"min": xs[0], "max": xs[-1], "iqr": float(q[1] - q[0])}


def default_chunk(steps: int) -> int:
    """About ten timed chunks, each at least one step."""
    return max(1, steps // 10)


def warm_up(backend) -> float:
    """Compile and run a few steps; seconds taken."""
    t0 = time.perf_counter()
    backend.upload(*backend.initial_state())
    backend.advance(WARMUP_STEPS)
    backend.synchronize()
    backend.read()
    return time.perf_counter() - t0


MIN_BUDGET_CHUNKS = 3  # a budget never leaves fewer timed chunks than this: a median needs them


def fit_budget(steps: int, chunk: int, step_s: float, budget_s: float) -> tuple[int, int]:
    """(steps, chunk) that fit `budget_s` seconds at `step_s` a step: the chunk shrinks first
    (the same number of chunks, so the spread means the same), then the chunks, never below
    MIN_BUDGET_CHUNKS chunks of one step. Unchanged when the run fits."""
    if step_s * steps <= budget_s:
        return steps, chunk
    chunks = max(1, -(-steps // chunk))
    chunk = max(1, int(budget_s / (step_s * chunks)))
    if chunk == 1:
        chunks = min(chunks, max(MIN_BUDGET_CHUNKS, int(budget_s / step_s)))
    return chunk * chunks, chunk


def run_timed(
    backend,
    steps: int,
    chunk: int | None = None,
    on_progress: Callable[[int], None] | None = None,
    raise_on_blowup: bool = True,
    build_s: float = 0.0,
    budget_s: float | None = None,
    warming: AbstractContextManager = nullcontext(),
) -> RunResult:
    """Run `steps` steps of the backend's scene and solver from the solver's start in timed
    chunks, checking health after each. With `budget_s`, one synchronised step timed after the
    warm-up sets how many steps fit in that many seconds of timed run, and a run that would
    not fit is shortened (fit_budget; result.steps and result.chunk say what ran). `warming` is
    entered around the warm-up alone (`clothbench run`'s terminal line naming the wait), never
    around anything timed."""
    chunk = chunk or default_chunk(steps)
    scene, solver = backend.scene, backend.solver
    result = RunResult(backend.name, backend.device, backend.mode, scene, solver, steps, backend.driver)
    with warming:
        result.warmup_s = build_s + warm_up(backend)
    if budget_s is not None:
        fitted = fit_budget(steps, chunk, _one_step_s(backend), budget_s)
        result.budget_cut = fitted != (steps, chunk)
        steps, chunk = fitted
        result.steps = steps
    result.chunk = chunk

    pos, prev = backend.initial_state()
    backend.upload(pos, prev)
    with StrictWatch(backend, pos, prev) if needs_watch(backend) else nullcontext() as watch:
        done = 0
        while done < steps:
            c = min(chunk, steps - done)
            backend.synchronize()
            t0 = time.perf_counter()
            backend.advance(c)
            backend.synchronize()
            elapsed = time.perf_counter() - t0
            result.chunk_ms_per_step.append(1e3 * elapsed / c)
            dev = backend.device_elapsed_ms()
            if dev is not None:
                result.device_ms_per_step.append(dev / c)
                result.device_timer = backend.device_timer or UNNAMED_DEVICE_TIMER  # declared by every class
            new_pos, new_prev = backend.read()
            problem = state_problem(new_pos, new_prev, scene, solver, done + c)
            if problem is not None:
                step, what = _pinpoint(backend, pos, prev, done, c)
                result.pos, result.prev = new_pos, new_prev
                result.blowup = BlowUp(step, what or problem)
                if raise_on_blowup:
                    raise result.blowup
                return result
            pos, prev = new_pos, new_prev
            divergence = watch.check(done, c, pos, prev) if watch is not None else None
            if divergence is not None:
                result.strict_divergence = divergence
                result.warnings.append(divergence)
            warning = fast_impact_warning(pos, prev, scene, solver.dt)
            if warning and warning.split(":")[0] not in {w.split(":")[0] for w in result.warnings}:
                result.warnings.append(warning)
            done += c
            if on_progress:
                on_progress(done)
    result.pos, result.prev = pos, prev
    return result


def _one_step_s(backend) -> float:
    """Seconds of one synchronised step, after the warm-up (it is past compilation)."""
    backend.synchronize()
    t0 = time.perf_counter()
    backend.advance(1)
    backend.synchronize()
    return time.perf_counter() - t0


def _pinpoint(backend, pos, prev, done, chunk) -> tuple[int, str | None]:
    """Replay a failed chunk one step at a time from its start to name the first bad step."""
    backend.upload(pos, prev)
    for s in range(1, chunk + 1):
        backend.advance(1)
        p, q = backend.read()
        problem = state_problem(p, q, backend.scene, backend.solver, done + s)
        if problem is not None:
            return done + s, problem
    return done + chunk, None  # not reproduced step by step: report the chunk's end
