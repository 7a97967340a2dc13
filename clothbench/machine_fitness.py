"""Is this machine fit to benchmark now, and if not, what to do: `clothbench machine`, and the
verdict `sweep` prints at its start and records in its rows (as `pyperf system show` does).

It reads what a timing depends on besides the kernel: the cores this process may run on and
whether they share a physical core (SMT siblings), how busy the machine is over a short window
(machine_load: other processes' CPU time and the hypervisor's steal), which processes use it,
the frequency governor and turbo where /sys has them (a VM often has neither: then it says
'not readable', never a guess), and the load average.

Every reader takes a root folder (tests give a fake /proc and /sys) and a LoadSampler (tests give
recorded /proc/stat lines and a fake clock), so nothing here needs the real machine's state.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from clothbench import machine_load
from clothbench.machine_load import Load, LoadSampler, allowed_cpus

# The window the load is sampled over: long enough for /proc/stat's 1/100 s ticks to show half
# a core on two cores (machine_load.MIN_WINDOW_S is the shortest), short enough not to be a wait.
WINDOW_S = 1.0
# A process using this many cores' worth over the window is named among the heavy ones.
HEAVY_CORES = 0.1


@dataclass(frozen=True)
class HeavyProcess:
    pid: int
    name: str
    cores: float  # CPU time over the window / the window


@dataclass(frozen=True)
class Problem:
    what: str  # what makes the machine unfit now, e.g. 'busy (other processes 1.2 of 2 cores, ...)'
    fix: str  # what to do about it

    def __str__(self) -> str:
        return f"{self.what}: {self.fix}"


@dataclass
class Fitness:
    """The machine's state now, and the verdict."""

    cpus: list[int]  # the logical CPUs this process may run on
    smt_shared: list[tuple[int, ...]]  # groups of those CPUs that are siblings of one core
    load: Load
    heavy: list[HeavyProcess]
    governors: dict[str, int]  # governor -> how many of our CPUs have it; {} not readable
    turbo: bool | None  # None: not readable
    loadavg: str | None
    problems: list[Problem] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # facts worth knowing that do not make it unfit

    @property
    def fit(self) -> bool | None:
        """True: fit; False: a problem; None: the load could not be measured and nothing else
        is wrong (not Linux, or /proc unreadable)."""
        if self.problems:
            return False
        return None if self.load.busy is None else True

    @property
    def verdict(self) -> str:
        """One line (what a sweep row records): 'quiet (...)', 'unknown (...)', or what each
        problem is, '; '-joined."""
        if self.fit:
            return f"quiet ({self.load.why})"
        if self.fit is None:
            return f"unknown ({self.load.why})"
        return "; ".join(p.what for p in self.problems)

    def as_dict(self) -> dict:
        return {
            "fit": self.fit,
            "verdict": self.verdict,
            "cpus": self.cpus,
            "smt_shared": [list(g) for g in self.smt_shared],
            "load": self.load.as_dict(),
            "heavy_processes": [{"pid": h.pid, "name": h.name, "cores": round(h.cores, 2)} for h in self.heavy],
            "governors": self.governors,
            "turbo": self.turbo,
            "loadavg": self.loadavg,
            "problems": [{"what": p.what, "fix": p.fix} for p in self.problems],
            "notes": self.notes,
        }


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


def parse_cpu_list(text: str) -> list[int]:
    """'0-3,8' -> [0, 1, 2, 3, 8] (the kernel's cpulist format)."""
    out: list[int] = []
    for part in text.strip().split(","):
        if not part:
            continue
        lo, _, hi = part.partition("-")
        out += range(int(lo), int(hi or lo) + 1)
    return out


def smt_groups(cpus: list[int], sys_root: Path) -> list[tuple[int, ...]]:
    """The groups of `cpus` that are hyperthreads of one physical core (two threads of a kernel
    on one core share its units: a thread count measured there says little of another machine)."""
    groups = set()
    for cpu in cpus:
        text = _read(sys_root / f"devices/system/cpu/cpu{cpu}/topology/thread_siblings_list")
        if text is None:
            continue
        siblings = tuple(c for c in parse_cpu_list(text) if c in cpus)
        if len(siblings) > 1:
            groups.add(siblings)
    return sorted(groups)


def governors(cpus: list[int], sys_root: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    for cpu in cpus:
        text = _read(sys_root / f"devices/system/cpu/cpu{cpu}/cpufreq/scaling_governor")
        if text is not None:
            found[text.strip()] = found.get(text.strip(), 0) + 1
    return found


def turbo(sys_root: Path) -> bool | None:
    """Whether turbo/boost is on: intel_pstate's no_turbo, else cpufreq's boost; None unreadable."""
    no_turbo = _read(sys_root / "devices/system/cpu/intel_pstate/no_turbo")
    if no_turbo is not None and no_turbo.strip() in ("0", "1"):
        return no_turbo.strip() == "0"
    boost = _read(sys_root / "devices/system/cpu/cpufreq/boost")
    if boost is not None and boost.strip() in ("0", "1"):
        return boost.strip() == "1"
    return None


def process_cpu_ticks(proc_root: Path) -> dict[int, tuple[str, int]]:
    """pid -> (name, utime + stime ticks) of every process /proc shows now."""
    out = {}
    for entry in proc_root.iterdir() if proc_root.is_dir() else ():
        if not entry.name.isdigit():
            continue
        text = _read(entry / "stat")
        if not text or ")" not in text:
            continue
        name = text[text.index("(") + 1 : text.rindex(")")]
        fields = text[text.rindex(")") + 2 :].split()
        try:  # fields 14 and 15 of stat(5), counted from the state (field 3)
            out[int(entry.name)] = (name, int(fields[11]) + int(fields[12]))
        except (IndexError, ValueError):
            continue
    return out


def heavy_processes(before: dict, after: dict, window_s: float, ticks_per_s: int, own_pid: int) -> list[HeavyProcess]:
    """The processes other than `own_pid` that used HEAVY_CORES or more over the window."""
    heavy = []
    for pid, (name, ticks) in after.items():
        if pid == own_pid or pid not in before:
            continue
        cores = (ticks - before[pid][1]) / ticks_per_s / max(window_s, 1e-9)
        if cores >= HEAVY_CORES:
            heavy.append(HeavyProcess(pid, name, cores))
    return sorted(heavy, key=lambda h: -h.cores)


def check(
    sampler: LoadSampler | None = None,
    window_s: float = WINDOW_S,
    proc_root: Path = Path("/proc"),
    sys_root: Path = Path("/sys"),
    cpus: list[int] | None = None,
) -> Fitness:
    """The machine's fitness to benchmark, over a window of `window_s` (this process sleeps)."""
    sampler = sampler or machine_load.LoadSampler()
    cpus = allowed_cpus() if cpus is None else cpus
    procs_before = process_cpu_ticks(proc_root)
    load = sampler.sample(window_s)
    procs_after = process_cpu_ticks(proc_root)
    heavy = heavy_processes(procs_before, procs_after, load.window_s, sampler.ticks_per_s, os.getpid())
    avg = _read(proc_root / "loadavg")
    f = Fitness(
        cpus=cpus,
        smt_shared=smt_groups(cpus, sys_root),
        load=load,
        heavy=heavy,
        governors=governors(cpus, sys_root),
        turbo=turbo(sys_root),
        loadavg=" ".join(avg.split()[:3]) if avg else None,
    )
    if load.busy:
        names = ", ".join(f"{h.name} (pid {h.pid}, {h.cores:.1f} cores)" for h in heavy[:3])
        fix = f"wait for {names} to finish, or stop them" if names else "wait until the machine is quiet"
        f.problems.append(Problem(f"busy ({load.why})", fix + ", before benchmarking"))
    slow_governors = sorted(g for g in f.governors if g not in ("performance",))
    if slow_governors:
        f.problems.append(
            Problem(
                f"frequency governor {', '.join(slow_governors)}",
                "the clock follows the load, so a short row runs slower than a long one; set it to performance "
                "(cpupower frequency-set -g performance)",
            )
        )
    if f.turbo:
        f.notes.append(
            "turbo boost is on: clock rates follow temperature and the other cores' load, so runs vary "
            "more; pyperf system tune turns it off"
        )
    if f.smt_shared:
        groups = ", ".join("+".join(map(str, g)) for g in f.smt_shared)
        f.notes.append(f"logical CPUs {groups} are hyperthreads of one core: two threads there share its units")
    if len(f.cpus) < (os.cpu_count() or len(f.cpus)):
        f.notes.append(f"this process may run on CPUs {','.join(map(str, f.cpus))} only (its affinity)")
    if not f.governors:
        f.notes.append("frequency governor not readable here (no cpufreq in /sys: a VM's host sets it)")
    return f


__all__ = ["HEAVY_CORES", "WINDOW_S", "Fitness", "HeavyProcess", "Problem", "check", "parse_cpu_list"]
