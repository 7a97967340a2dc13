"""Rows on a Dask distributed cluster (`--scheduler tcp://HOST:PORT` or $CLOTHBENCH_SCHEDULER).

Each task runs on a worker inside its own child process with the row's time limit (as
harness/executor.py runs it here), and comes back as an Outcome carrying the worker's host
name. A timed task asks for the worker resource `timing=1`: start each worker machine's one
worker with `--resources timing=1` and no two timed rows ever share a machine; error-only
tasks ask for nothing and run anywhere. A worker that dies mid-task (killed, its machine
gone) has its tasks rescheduled by the scheduler on another worker; the client alone writes
the CSV, from results only, so every row is written once.

Workers must be allowed child processes: start them with DASK_DISTRIBUTED__WORKER__DAEMON=False
(README, "Sweeps on several machines"); a daemonic worker runs each task in its own process
(no crash isolation beyond the worker's own restart by its nanny).
"""

from __future__ import annotations

from concurrent.futures import Executor

from clothbench.errors import ClothbenchError
from clothbench.harness.executor import DEFAULT_ROW_TIMEOUT, Outcome, run_isolated, start_method


def run_on_worker(fn, args, kwargs, timeout, method) -> Outcome:
    """The task as a worker runs it: in a child process where the worker may have one."""
    import multiprocessing

    from clothbench.environment import host_name

    if multiprocessing.current_process().daemon:
        try:
            outcome = Outcome("ok", fn(*args, **kwargs))
        except MemoryError as e:
            outcome = Outcome("crashed", note=f"out of memory: {e}")
    else:
        outcome = run_isolated(fn, args, kwargs, timeout=timeout, method=method)
    outcome.host = host_name()
    return outcome


class DaskExecutor(Executor):
    """submit(fn, *args, timing=, timeout=, fork_safe=, **kwargs) -> a Dask future of an Outcome."""

    where = "dask"

    def __init__(self, scheduler: str, timeout: float | None = DEFAULT_ROW_TIMEOUT, client=None):
        try:
            from distributed import Client
        except ImportError:
            raise ClothbenchError(
                "--scheduler needs Dask distributed: pip install 'clothbench[cluster]' (or 'dask[distributed]')"
            ) from None
        self.timeout = timeout
        self.scheduler = scheduler
        if client is not None:
            self.client = client
        else:
            try:
                self.client = Client(scheduler, timeout=30)
            except OSError as e:
                raise ClothbenchError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
        self._own = client is None

    def submit(
        self, fn, /, *args, timing: bool = False, timeout: float | None = -1.0, fork_safe: bool = True, **kwargs
    ):
        limit = self.timeout if timeout == -1.0 else timeout
        method = start_method(fork_safe=False)  # a worker's process holds threads and sockets: a clean child
        return self.client.submit(
            run_on_worker, fn, args, kwargs, limit, method,
            resources={"timing": 1} if timing else None, pure=False,
        )  # fmt: skip

    @staticmethod
    def as_completed(futures):
        from distributed import as_completed

        return as_completed(futures)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if self._own:
            self.client.close()

    def kill_all(self) -> None:
        pass

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            try:
                self.client.cancel(list(self.client.futures.values()) if hasattr(self.client, "futures") else [])
            except Exception:
                pass
        self.shutdown()
        return False
