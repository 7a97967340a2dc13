"""The harness: timed runs, health checks, references, the plan of variants and sweeps,
the same for every backend."""

from clothbench.harness.health import max_penetration, state_problem
from clothbench.harness.simulate import position_error, reference, simulate
from clothbench.harness.timing import RunResult, run_timed, warm_up

__all__ = [
    "simulate",
    "reference",
    "position_error",
    "RunResult",
    "run_timed",
    "warm_up",
    "state_problem",
    "max_penetration",
]
