"""How busy the machine was while something was measured: other processes' CPU time and the
hypervisor's steal, from two snapshots of /proc/stat and of this process's own CPU time.

A timing taken while other processes ran is a timing of the machine's load as much as of the
kernel; a tuner that keeps the fastest of several shapes then keeps whichever shape the load
happened to hurt least (backends/tuning.py). This module says, from two snapshots, what share
of the machine other processes used during the window, how much the hypervisor stole, and
whether that makes the window `busy`. It is layer 0 so that any layer may record the same
signals (a tuning choice now; a benchmark row later).

The readers (clock, /proc/stat, own CPU time, sleep) are injectable so that tests give
recorded numbers and never read real time. Where /proc/stat cannot be read (not Linux), the
verdict is unknown (busy None), never a guess.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass
from typing import Callable

# Other processes' CPU, in cores' worth averaged over the window, from which it is busy. A
# kernel split over every core waits at each step for its slowest thread, so one other process
# holding even half a core keeps a thread of the widest shape descheduled half the time, enough
# to make a busy tuning keep the wrong shape (docs/timing.md, "Kernel shapes chosen on a busy
# machine"). A quiet machine's background (daemons, a terminal) stays well under a tenth of a core.
BUSY_CORES = 0.5
# Steal (the hypervisor running another guest on our vCPUs) as a share of the machine from which
# it is busy: that load is invisible to /proc's process accounting, and a quiet host steals ~0.
BUSY_STEAL = 0.05
# Shortest window a verdict is given for: /proc/stat counts in ticks of 1/100 s per CPU, and both
# snapshots round, so a window needs ~25 ticks per core before half a core stands out of it.
MIN_WINDOW_S = 0.25


@dataclass(frozen=True)
class Snapshot:
    wall_s: float  # the monotonic clock
    busy_ticks: int | None  # every CPU's user+nice+system+irq+softirq ticks; None: unreadable
    steal_ticks: int | None
    total_ticks: int | None  # every CPU's ticks of any kind (idle included)
    own_cpu_s: float  # this process's CPU time, its threads and reaped children included


@dataclass(frozen=True)
class Load:
    """What the machine did besides us between two snapshots."""

    window_s: float
    cores: int
    other_cores: float | None  # other processes' CPU time / wall time (None: not measured)
    other_share: float | None  # the same as a share of the machine (other_cores / cores)
    steal_share: float | None
    busy: bool | None  # None: not measured, or a window too short to tell
    why: str

    def as_dict(self) -> dict:
        out = asdict(self)
        for name in ("window_s", "other_cores", "other_share", "steal_share"):
            if out[name] is not None:
                out[name] = round(out[name], 3)
        return out


def read_proc_stat() -> str | None:
    try:
        with open("/proc/stat") as f:
            return f.readline()  # the first line sums every CPU
    except OSError:
        return None


def own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _ticks_per_second() -> int:
    try:
        return os.sysconf("SC_CLK_TCK")
    except (ValueError, OSError, AttributeError):
        return 100


def parse_cpu_line(line: str | None) -> tuple[int, int, int] | None:
    """(busy, steal, total) ticks of /proc/stat's first line, or None if it is not one:
    `cpu user nice system idle iowait irq softirq steal guest guest_nice`. guest and
    guest_nice are already inside user and nice, so they are not added again."""
    if not line:
        return None
    fields = line.split()
    if not fields or fields[0] != "cpu" or len(fields) < 8:
        return None
    try:
        v = [int(x) for x in fields[1:9]] + [0] * (9 - len(fields[1:9]))
    except ValueError:
        return None
    user, nice, system, idle, iowait, irq, softirq, steal = v[:8]
    busy = user + nice + system + irq + softirq
    return busy, steal, busy + idle + iowait + steal


class LoadSampler:
    """Snapshots and the load between two of them; every reader may be replaced (tests)."""

    def __init__(
        self,
        read_stat: Callable[[], str | None] = read_proc_stat,
        clock: Callable[[], float] = time.monotonic,
        own_cpu: Callable[[], float] = own_cpu_seconds,
        cores: int | None = None,
        sleep: Callable[[float], None] = time.sleep,
        ticks_per_s: int | None = None,
    ):
        self.read_stat, self.clock, self.own_cpu, self.sleep = read_stat, clock, own_cpu, sleep
        self.cores = cores or os.cpu_count() or 1
        self.ticks_per_s = ticks_per_s or _ticks_per_second()

    def snapshot(self) -> Snapshot:
        parsed = parse_cpu_line(self.read_stat())
        busy, steal, total = parsed if parsed else (None, None, None)
        return Snapshot(self.clock(), busy, steal, total, self.own_cpu())

    def between(self, a: Snapshot, b: Snapshot) -> Load:
        window = b.wall_s - a.wall_s
        if None in (a.busy_ticks, b.busy_ticks):
            return Load(window, self.cores, None, None, None, None, "load not measured (no /proc/stat)")
        if window < MIN_WINDOW_S:
            return Load(window, self.cores, None, None, None, None, f"window {window:.2f} s too short to tell")
        tick = 1.0 / self.ticks_per_s
        total_s = max((b.total_ticks - a.total_ticks) * tick, 1e-9)
        other_s = max(0.0, (b.busy_ticks - a.busy_ticks) * tick - (b.own_cpu_s - a.own_cpu_s))
        steal = max(0.0, (b.steal_ticks - a.steal_ticks) * tick) / total_s
        other_share = min(1.0, other_s / total_s)
        other_cores = other_share * self.cores  # capacity from the ticks: wall clocks drift
        busy = other_cores >= BUSY_CORES or steal >= BUSY_STEAL
        why = f"other processes {other_cores:.2f} of {self.cores} cores, steal {steal:.0%} over {window:.2f} s"
        return Load(window, self.cores, other_cores, other_share, steal, busy, why)

    def start(self) -> "Window":
        return Window(self, self.snapshot())

    def sample(self, seconds: float = MIN_WINDOW_S) -> Load:
        """The load over the next `seconds` while this process sleeps."""
        window = self.start()
        self.sleep(seconds)
        return window.stop()


class Window:
    """A measurement window opened by LoadSampler.start()."""

    def __init__(self, sampler: LoadSampler, first: Snapshot):
        self.sampler, self.first = sampler, first

    def stop(self, min_window_s: float = 0.0) -> Load:
        """The load since start(); with min_window_s, first sleep until the window is that long,
        so that a short measurement still gets a verdict (the sleep sees only the others)."""
        left = min_window_s - (self.sampler.clock() - self.first.wall_s)
        if left > 0:
            self.sampler.sleep(left)
        return self.sampler.between(self.first, self.sampler.snapshot())


def threads_left_free(threads: int, cores: int) -> tuple[int, Load | None]:
    """The threads a split step should run on now: `threads`, or, where a quarter of a second's
    watch finds the machine busy, the cores the other processes leave free (at least one).

    A thread of a split step waits at every step's barrier for the slowest, and a core another
    process holds keeps one descheduled: the whole step waits with it (docs/c.md, "Under load").
    Also returns the load it saw (None where `threads` is 1: nothing to watch for)."""
    if threads <= 1:
        return threads, None
    load = LoadSampler().sample(MIN_WINDOW_S)
    if not load.busy or load.other_cores is None:
        return threads, load
    return min(threads, max(1, cores - math.ceil(load.other_cores - 0.25))), load


def allowed_cpus() -> list[int]:
    """The logical CPUs this process may run on (its affinity), in order."""
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


def cpu_context(sys_root: str = "/sys") -> str:
    """Where this process runs, for a row's load column: the CPUs its affinity allows and their
    clock now where /sys has it ('clock not readable' in most VMs)."""
    cpus = allowed_cpus()
    khz = []
    for cpu in cpus:
        try:
            with open(f"{sys_root}/devices/system/cpu/cpu{cpu}/cpufreq/scaling_cur_freq") as f:
                khz.append(int(f.read().strip()))
        except (OSError, ValueError):
            continue
    clock = f"clock {sum(khz) / len(khz) / 1e6:.2f} GHz" if khz else "clock not readable"
    return f"CPUs {','.join(map(str, cpus))}, {clock}"


__all__ = [
    "BUSY_CORES",
    "BUSY_STEAL",
    "MIN_WINDOW_S",
    "Load",
    "LoadSampler",
    "Snapshot",
    "Window",
    "allowed_cpus",
    "cpu_context",
    "parse_cpu_line",
    "threads_left_free",
]
