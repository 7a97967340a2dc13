"""Where a measurement was taken: the machine, the software, the commit, the clock.

Recorded with every sweep row, so a CSV read months later (or next to one from another
machine) still says what produced it. Nothing here raises: an unknown is written as
"unknown".

hatch_build.py loads this file on its own at build time, in the build's environment, to record
the commit a wheel is built from (checkout_commit): imports at the top stay the standard
library's; clothbench's own are made inside the functions that need them.
"""

from __future__ import annotations

import os
import platform
import shlex
import socket
import subprocess
from datetime import datetime, timezone
from functools import lru_cache
from importlib import metadata
from pathlib import Path

# CuPy's wheels for each CUDA major, and a source build ("cupy"): which one is imported
CUPY_PACKAGES = ("cupy-cuda13x", "cupy-cuda12x", "cupy-cuda11x", "cupy")
# Distributions whose version can change a timing or a result, in the order written.
PACKAGES = (
    "clothbench",
    "numpy",
    "pyopencl",
    "pocl-binary-distribution",
    "moderngl",
    "glcontext",
    *CUPY_PACKAGES,
    "taichi",
    "warp-lang",
    "numba",
    "numba-cuda",
    "torch",
    "jax",
    "jaxlib",
    "newton",
    "trimesh",
)

# Environment variables that change how a library or driver runs (thread pools, device
# choice, JIT and compiler settings), by exact name or by prefix: OpenMP (and Intel's and
# GNU's runtimes), Numba, MKL, OpenBLAS, llvmpipe, Mesa, PoCL, the OpenCL ICD loader,
# pyopencl, CUDA's device list, CuPy, Taichi, Warp, XLA (jax: XLA_FLAGS changes its arithmetic),
# PyTorch's own switches.
ENV_VARS = ("GALLIUM_DRIVER", "CUDA_VISIBLE_DEVICES")
ENV_PREFIXES = (
    "OMP_",
    "KMP_",
    "GOMP_",
    "NUMBA_",
    "MKL_",
    "OPENBLAS_",
    "LP_",
    "MESA_",
    "POCL_",
    "OCL_ICD_",
    "PYOPENCL_",
    "CUPY_",
    "TI_",
    "WARP_",
    "XLA_",
    "TORCH",
)
# Set by clothbench itself (peers/taichi.py, to keep Taichi from phoning home), and no
# change to any result: not recorded, so a row does not depend on which probe ran first.
ENV_IGNORED = frozenset({"TI_SKIP_VERSION_CHECK"})


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def cores() -> int:
    """Logical CPUs this process may run on (what a CPU driver can use)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 0


def host_name() -> str:
    return socket.gethostname() or "unknown"


def cpu_mhz() -> int | None:
    """The CPU's clock in MHz: its maximum where the kernel says (cpufreq), else what
    /proc/cpuinfo reports now; None where neither is readable."""
    try:
        return int(Path("/sys/devices/system/cpu/cpu0/cpufreq/cpuinfo_max_freq").read_text()) // 1000
    except (OSError, ValueError):
        pass
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("cpu MHz"):
                    return round(float(line.split(":", 1)[1]))
    except (OSError, ValueError):
        pass
    return None


def cpu_scaling_enabled() -> bool | None:
    """Whether CPU 0's frequency governor may change its clock (anything but 'performance'),
    as Google Benchmark reports it; None where there is no cpufreq (e.g. a VM)."""
    try:
        governor = Path("/sys/devices/system/cpu/cpu0/cpufreq/scaling_governor").read_text().strip()
    except OSError:
        return None
    return governor != "performance"


def _count_cpus(cpu_list: str) -> int:
    """How many CPUs a kernel CPU list such as '0-3,8' names."""
    count = 0
    for part in filter(None, cpu_list.strip().split(",")):
        first, _, last = part.partition("-")
        count += int(last or first) - int(first) + 1
    return count


def caches() -> list[dict]:
    """CPU 0's caches as Google Benchmark lists them (type, level, size in bytes, how many
    logical CPUs share it); [] where sysfs does not say."""
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    found = []
    for index in sorted(Path("/sys/devices/system/cpu/cpu0/cache").glob("index*")):
        try:
            size = (index / "size").read_text().strip()
            found.append(
                {
                    "type": (index / "type").read_text().strip(),
                    "level": int((index / "level").read_text()),
                    "size": int(size[:-1]) * units[size[-1]] if size[-1:] in units else int(size),
                    "num_sharing": _count_cpus((index / "shared_cpu_list").read_text()),
                }
            )
        except (OSError, ValueError):
            continue
    return found


def python_version() -> str:
    return f"{platform.python_implementation()} {platform.python_version()}"


def package_versions() -> str:
    """'name=version' for every installed distribution in PACKAGES, space-separated; clothbench's
    is the running code's (__version__), which a checkout on PYTHONPATH has without being installed
    and which an installed distribution of another checkout would misstate."""
    from clothbench import __version__

    found = []
    for name in PACKAGES:
        try:
            found.append(f"{name}={__version__ if name == 'clothbench' else metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return " ".join(found)


def driver_env() -> str:
    """The set variables of ENV_VARS and ENV_PREFIXES as 'NAME=value' in name order, separated
    by spaces, each value shell-quoted (shlex.split reads them back, spaces in a value included)."""
    names = sorted(k for k in os.environ if k not in ENV_IGNORED and (k in ENV_VARS or k.startswith(ENV_PREFIXES)))
    return " ".join(f"{k}={shlex.quote(os.environ[k])}" for k in names)


# Where clothbench runs from: a checkout's root (git can say its commit), or site-packages.
CHECKOUT = Path(__file__).resolve().parents[1]  # clothbench/environment.py -> the folder above


def checkout_commit(root: Path) -> str | None:
    """Short commit of the git checkout at `root`, '+dirty' if tracked files changed; None where
    `root` is no checkout (its own .git: not a repository further up) or git cannot say."""
    if not (root / ".git").exists():
        return None
    env = dict(os.environ, GIT_OPTIONAL_LOCKS="0")  # never take the index lock from under a user

    def git(*args: str) -> str:
        out = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, env=env)
        if out.returncode != 0:
            raise RuntimeError(out.stderr.strip())
        return out.stdout.strip()

    try:
        commit = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, RuntimeError, subprocess.SubprocessError):
        return None
    return commit + ("+dirty" if dirty else "")


def git_commit() -> str:
    """The clothbench commit that is running. A checkout's is git's, live ('unknown' where git
    cannot say). An installed copy has no repository to ask: its commit is the one its wheel was
    built from (clothbench/_build_info.py, written by hatch_build.py), with its version, as in
    'abc123456789 (version 0.1.0)'; 'unknown (version 0.1.0)' where it was built from no checkout."""
    if (CHECKOUT / ".git").exists():
        return checkout_commit(CHECKOUT) or "unknown"
    from clothbench import __version__

    try:
        from clothbench._build_info import COMMIT as built_from
    except ImportError:
        built_from = "unknown"
    return f"{built_from} (version {__version__})"


def timestamp() -> str:
    """Now, UTC, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


@lru_cache(maxsize=1)
def machine() -> dict[str, str]:
    """Everything but the timestamp, collected once per process."""
    return {
        "cpu": cpu_model(),
        "cores": str(cores()),
        "python": python_version(),
        "packages": package_versions(),
        "env": driver_env(),
        "git_commit": git_commit(),
    }


def collect() -> dict[str, str]:
    """The environment columns of a sweep row, timestamped now."""
    return {**machine(), "timestamp": timestamp()}


COLUMNS = ("cpu", "cores", "python", "packages", "env", "git_commit", "timestamp")  # collect()'s keys, in order


def with_columns(row_class=None, *, after: tuple[str, ...] = ()):
    """A row class given COLUMNS as its last fields (str, '' where unknown): where and when its
    row was measured, as a sweep row has them. Put it under @dataclass, which then takes them
    as fields declared after the class's own, so the CSV's columns keep that order. `after`
    names fields of the class's own that go after them (columns added since, last so that an
    older file lacks only its final columns): `@with_columns(after=("a", "b"))`."""

    def declare(cls):
        annotations = cls.__annotations__
        moved = {name: annotations.pop(name) for name in after}
        for name in COLUMNS:
            annotations[name] = "str"  # as `from __future__ import annotations` spells a type
            setattr(cls, name, "")
        annotations.update(moved)
        return cls

    return declare(row_class) if row_class is not None else declare
