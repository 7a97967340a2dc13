"""The harness: timed runs, health checks, and (later) sweeps, shared by every backend."""

from .health import max_penetration, state_problem
from .simulate import position_error, reference, simulate
from .timing import RunResult, run_timed, warm_up

__all__ = [
    "simulate",
    "reference",
    "position_error",
   "RunResult", "run_timed", "warm_up", "state_problem", "max_penetration"]
