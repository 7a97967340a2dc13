"""Rows in worker processes: a crash, an out-of-memory kill or a hang costs one row, not the
run; and the executor (the `concurrent.futures` interface) that runs many rows.

`run_isolated(fn, ...)` runs one call in a fresh child process with a time limit and returns
an Outcome: the value, or `crashed` (the child died: a signal, an abort, the kernel's
out-of-memory killer) or `timeout` (it ran past the limit and was killed), with what
happened in one line. A KeyboardInterrupt in the child, or a Ctrl-C / SIGTERM in the parent,
kills the child and raises KeyboardInterrupt in the parent: nothing half-done comes back.

`LocalExecutor(jobs)` is a `concurrent.futures.Executor` whose every task runs through
run_isolated. A task submitted with `timing=True` runs alone (no other task, timed or not,
shares the machine while it runs); other tasks (error-only work: references, bisections,
accuracy runs) run `jobs` at a time. `executor_for(scheduler, jobs)` is that, or the Dask
distributed one, `DaskExecutor`, for `--scheduler tcp://HOST:PORT` (or $CLOTHBENCH_SCHEDULER).

On Dask, each task runs on a worker inside its own child process with the row's time limit
(run_isolated, as here), and comes back as an Outcome carrying the worker's host name. A timed
task asks for the worker resource `timing=1`: start each worker machine's one worker with
`--resources timing=1` and no two timed rows ever share a machine; error-only tasks ask for
nothing and run anywhere. A worker that dies mid-task (killed, its machine gone) has its tasks
rescheduled by the scheduler on another worker; the client alone writes the CSV, from results
only, so every row is written once.

Workers must be allowed child processes: start them with DASK_DISTRIBUTED__WORKER__DAEMON=False
(README, "Sweeps on several machines"); a daemonic worker runs each task in its own process
(no crash isolation beyond the worker's own restart by its nanny).
"""

from __future__ import annotations

import faulthandler
import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import Executor, Future
from dataclasses import dataclass
from typing import Any, Callable

from clothbench.environment import host_name
from clothbench.errors import ClothbenchError, signal_name
from clothbench.harness import faults
from clothbench.harness.preflight import signals_held

DEFAULT_ROW_TIMEOUT = 3600.0  # seconds; --row-timeout
SCHEDULER_ENV = "CLOTHBENCH_SCHEDULER"
START_METHOD_ENV = "CLOTHBENCH_START_METHOD"


@dataclass
class Outcome:
    status: str  # ok | crashed | timeout
    value: Any = None
    note: str = ""
    wall_s: float = 0.0
    host: str = ""  # where it ran (set by executors that run tasks elsewhere)

    @property
    def ok(self) -> bool:
        return self.status == "ok"


class RowError(Exception):
    """What the child raised, re-raised in the parent (the original when it pickles)."""


def crash_note(exitcode: int | None) -> str:
    if exitcode is None:
        return "the worker process vanished"
    if exitcode < 0:
        name = signal_name(-exitcode)
        hint = {
            "SIGKILL": " (the kernel's out-of-memory killer sends this when the machine runs out of memory)",
            "SIGABRT": " (an abort in native code: a driver or library assertion)",
            "SIGSEGV": " (a segmentation fault in native code)",
            "SIGBUS": " (a bus error in native code)",
        }.get(name, "")
        return f"the worker process was killed by {name}{hint}"
    return f"the worker process exited with status {exitcode} before returning a result"


# --- one call in a child ----------------------------------------------------------------------


def start_method(fork_safe: bool = True) -> str:
    """'fork' where the parent holds no driver state a child could inherit half-made (the
    child then sees everything the parent registered), else 'forkserver' (a clean process)."""
    chosen = os.environ.get(START_METHOD_ENV)
    methods = multiprocessing.get_all_start_methods()
    if chosen:
        return chosen
    if "fork" not in methods:
        return "spawn"
    return "fork" if fork_safe else "forkserver"


def fork_safe(backend: str, solver: str = "verlet") -> bool:
    """Whether a forked child can run `backend` (its registry entry says; every solver of a
    backend shares it): one that touches no driver state the parent may hold. Any other gets a
    clean process. A solver the backend lacks is refused, as backend_class() refuses it."""
    from clothbench.backends import check_name

    entry = check_name(backend)
    if solver not in entry.solvers():
        raise ClothbenchError(f"{backend} has no {solver} solver (it has: {', '.join(entry.solvers())})")
    return entry.fork_safe


def _die_with_parent() -> None:
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except Exception:  # not Linux: a child outlives a parent killed by SIGKILL, nothing worse
        pass


def _child(conn, fn, args, kwargs, progress: bool) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C is the parent's to handle
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent()
    faulthandler.disable()  # a crash is the row's note, not a stack dump on the terminal
    if progress:
        kwargs = dict(kwargs, on_progress=lambda done: conn.send(("progress", done)))
    try:
        faults.arm()
        value = fn(*args, **kwargs)
    except KeyboardInterrupt:
        conn.send(("interrupt", None))
        return
    except BaseException as e:
        try:
            conn.send(("raise", e))
        except Exception:
            conn.send(("raise", RowError(f"{type(e).__name__}: {e}")))
        return
    conn.send(("ok", value))


def _kill(process) -> None:
    if process.pid is None:  # never started (its start failed)
        return
    if process.is_alive():
        process.kill()
    process.join(5)


def run_isolated(
    fn: Callable,
    args: tuple = (),
    kwargs: dict | None = None,
    timeout: float | None = DEFAULT_ROW_TIMEOUT,
    on_progress: Callable[[int], None] | None = None,
    method: str | None = None,
    live: "_LiveWorkers | None" = None,
) -> Outcome:
    """fn(*args, **kwargs) in a child process (see the module's doc). `on_progress`, when
    given, is passed to fn as its on_progress keyword, and called here with what it reports."""
    ctx = multiprocessing.get_context(method or start_method())
    if ctx.get_start_method() == "forkserver" and fn.__module__.startswith("clothbench."):
        # the server, started by the first such call, imports fn's module once (0.2 s for the
        # sweep's: clothbench, numpy), which every child it forks then has: a sweep starts a
        # child per row (38 rows at 32-64^2: 62 and 58 s before, 59 and 52 after). None of a
        # driver: a backend imports its own in the child, on use. clothbench's modules only:
        # the server dies on any import error but ImportError, and a test module may skip
        ctx.set_forkserver_preload([fn.__module__])
    receive, send = ctx.Pipe(duplex=False)
    process = ctx.Process(target=_child, args=(send, fn, args, kwargs or {}, on_progress is not None), daemon=True)
    t0 = time.monotonic()
    try:
        # A Ctrl-C or SIGTERM is held while the child starts, and raised once it has: a fork
        # runs the parent's at-fork hooks (logging's lock among them), and Python reports a
        # KeyboardInterrupt raised inside one as ignored, so the run went on as if no signal had
        # come, waiting on its row (a hung one: for ever), with logging's lock still held
        with signals_held():
            process.start()
        send.close()
        if live is not None:
            live.add(process)
        while True:
            left = None if timeout is None else timeout - (time.monotonic() - t0)
            if left is not None and left <= 0:
                _kill(process)
                return Outcome(
                    "timeout", note=f"ran past the {timeout:g} s limit and was killed", wall_s=time.monotonic() - t0
                )
            if not receive.poll(left if left is None else min(left, 1.0)):
                if not process.is_alive() and not receive.poll(0):
                    process.join()
                    return Outcome("crashed", note=crash_note(process.exitcode), wall_s=time.monotonic() - t0)
                continue
            try:
                kind, value = receive.recv()
            except EOFError:  # the child died without a word
                process.join(5)
                return Outcome("crashed", note=crash_note(process.exitcode), wall_s=time.monotonic() - t0)
            if kind == "progress":
                if on_progress is not None:
                    on_progress(value)
                continue
            process.join(5)
            if kind == "interrupt":
                raise KeyboardInterrupt
            if kind == "raise":
                raise value
            return Outcome("ok", value, wall_s=time.monotonic() - t0)
    finally:
        _kill(process)
        receive.close()
        if live is not None:
            live.discard(process)


# --- many calls -------------------------------------------------------------------------------


class _TimingLock:
    """Timed tasks exclusive, untimed tasks shared (a readers-writer lock, writers first)."""

    def __init__(self):
        self._cond = threading.Condition()
        self._shared = 0
        self._exclusive = False
        self._waiting = 0

    def acquire(self, exclusive: bool) -> None:
        with self._cond:
            if exclusive:
                self._waiting += 1
                self._cond.wait_for(lambda: not self._exclusive and self._shared == 0)
                self._waiting -= 1
                self._exclusive = True
            else:
                self._cond.wait_for(lambda: not self._exclusive and self._waiting == 0)
                self._shared += 1

    def release(self, exclusive: bool) -> None:
        with self._cond:
            if exclusive:
                self._exclusive = False
            else:
                self._shared -= 1
            self._cond.notify_all()


class _LiveWorkers:
    """The worker processes running now, and whether the run is closing. One lock over both: a
    worker whose row thread was starting it while an interrupt killed the others is killed as it
    is added, rather than left to run (a hung row then held the command up to its row timeout)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._processes: set = set()
        self.closing = False

    def add(self, process) -> None:
        with self._lock:
            self._processes.add(process)
            if self.closing:
                process.kill()

    def discard(self, process) -> None:
        with self._lock:
            self._processes.discard(process)

    def kill_all(self) -> None:
        with self._lock:
            self.closing = True
            for process in self._processes:
                if process.is_alive():
                    process.kill()


class LocalExecutor(Executor):
    """Tasks in child processes on this machine: `jobs` untimed at a time, timed ones alone.

    submit(fn, *args, **kwargs) returns a Future of an Outcome (never of fn's exception
    for a crash or a timeout: those are Outcomes; an exception fn raised is the Future's).
    Keywords `timing` (bool), `timeout` (seconds) and `fork_safe` are the executor's own.
    """

    where = "local"

    def __init__(self, jobs: int = 1, timeout: float | None = DEFAULT_ROW_TIMEOUT):
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        from concurrent.futures import ThreadPoolExecutor

        self.jobs = jobs
        self.timeout = timeout
        self._lock = _TimingLock()
        self._pool = ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="clothbench-row")
        self._live = _LiveWorkers()

    def submit(
        self, fn, /, *args, timing: bool = False, timeout: float | None = -1.0, fork_safe: bool = True, **kwargs
    ) -> Future:
        limit = self.timeout if timeout == -1.0 else timeout
        method = start_method(fork_safe)

        def task():
            self._lock.acquire(timing)
            try:
                if self._live.closing:
                    return Outcome("crashed", note="the run was interrupted before this task started")
                return run_isolated(fn, args, kwargs, timeout=limit, method=method, live=self._live)
            finally:
                self._lock.release(timing)

        return self._pool.submit(task)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)

    @staticmethod
    def as_completed(futures):
        from concurrent.futures import as_completed

        return as_completed(futures)

    def kill_all(self) -> None:
        """An interrupt: no task starts now, every worker process running is killed."""
        self._live.kill_all()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is not None:
            self.kill_all()
            self.shutdown(wait=True, cancel_futures=True)
            return False
        self.shutdown(wait=True)
        return False


def run_on_worker(fn, args, kwargs, timeout, method) -> Outcome:
    """The task as a worker runs it: in a child process where the worker may have one."""
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
            run_on_worker,
            fn,
            args,
            kwargs,
            limit,
            method,
            resources={"timing": 1} if timing else None,
            pure=False,
        )

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


def runner(executor: Executor | None):
    """run(fn, *args, fork_safe=, **kwargs) -> a callable giving (status, value or note):
    fn called here at once without an executor, else submitted as the executor's error-only
    task (in parallel over its jobs; None keywords are dropped)."""

    def run(fn, *args, fork_safe: bool = True, **kwargs):
        if executor is None:
            value = fn(*args, **kwargs)
            return lambda: ("ok", value)
        kwargs = {k: v for k, v in kwargs.items() if v is not None}
        future = executor.submit(fn, *args, timing=False, fork_safe=fork_safe, **kwargs)

        def get():
            outcome = future.result()
            return (outcome.status, outcome.value if outcome.ok else outcome.note)

        return get

    return run


def executor_for(scheduler: str | None = None, jobs: int = 1, timeout: float | None = DEFAULT_ROW_TIMEOUT) -> Executor:
    """The executor a command runs its rows on: Dask distributed at `scheduler` (or
    $CLOTHBENCH_SCHEDULER), else local processes."""
    scheduler = scheduler or os.environ.get(SCHEDULER_ENV) or None
    if scheduler:
        return DaskExecutor(scheduler, timeout=timeout)
    return LocalExecutor(jobs, timeout=timeout)


__all__ = [
    "DEFAULT_ROW_TIMEOUT",
    "DaskExecutor",
    "LocalExecutor",
    "Outcome",
    "RowError",
    "crash_note",
    "executor_for",
    "fork_safe",
    "run_isolated",
    "runner",
    "start_method",
]
