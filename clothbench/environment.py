"""Where a measurement was taken: the machine, the software, the commit, the clock.

Recorded with every sweep row, so a CSV read months later (or next to one from another
machine) still says what produced it. Nothing here raises: an unknown is written as
"unknown".
"""

from __future__ import annotations

import os
import platform
import subprocess
from datetime import datetime, timezone
from functools import lru_cache
from importlib import metadata
from pathlib import Path

# Distributions whose version can change a timing or a result, in the order written.
PACKAGES = (
    "clothbench",
    "numpy",
    "pyopencl",
    "pocl-binary-distribution",
    "moderngl",
    "glcontext",
    "cupy-cuda12x",
    "cupy-cuda11x",
    "cupy",
    "taichi",
    "warp-lang",
    "numba",
)

# Environment variables that change how a driver runs (threads, device choice).
ENV_VARS = ("LP_NUM_THREADS", "GALLIUM_DRIVER", "OMP_NUM_THREADS", "PYOPENCL_CTX", "CUDA_VISIBLE_DEVICES")
ENV_PREFIXES = ("POCL_",)


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


def python_version() -> str:
    return f"{platform.python_implementation()} {platform.python_version()}"


def package_versions() -> str:
    """'name=version' for every installed distribution in PACKAGES, space-separated."""
    found = []
    for name in PACKAGES:
        try:
            found.append(f"{name}={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            continue
    return " ".join(found)


def driver_env() -> str:
    """The driver environment variables that are set, as 'NAME=value' separated by spaces."""
    names = sorted(
        k for k in os.environ if k in ENV_VARS or any(k.startswith(p) for p in ENV_PREFIXES)
    )
    return " ".join(f"{k}={os.environ[k]}" for k in names)


def git_commit() -> str:
    """Short commit of the clothbench checkout, '+dirty' if tracked files changed; else 'unknown'."""
    root = Path(__file__).resolve().parents[2]
    if not (root / ".git").exists():
        return "unknown"
    env = dict(os.environ, GIT_OPTIONAL_LOCKS="0")  # never take the index lock from under a user

    def git(*args: str) -> str:
        out = subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10, env=env
        )
        if out.returncode != 0:
            raise RuntimeError(out.stderr.strip())
        return out.stdout.strip()

    try:
        commit = git("rev-parse", "--short=12", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, RuntimeError, subprocess.SubprocessError):
        return "unknown"
    return commit + ("+dirty" if dirty else "")


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
