"""Checks made before any work, so a bad output path or a grid the machine cannot hold never
costs a finished run: every output path writable, the memory a grid needs against what the
machine has available."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable

from clothbench.errors import ClothbenchError

# n*n float4 arrays of the working precision a row holds at its peak (state, ping-pong copy,
# the step's temporaries: numpy forms the 12 neighbours' differences at once), as measured:
# the peak RSS of `clothbench run --grid 512` over that of --grid 8 is 83 MiB in f32 (the
# temporaries are partly float64) and 105 MiB in f64; the estimate rounds up (96, 104).
ARRAYS = {"f32": 24, "f64": 13}
REFERENCE_ARRAYS = 13  # the float64 run a sweep row is compared with
ITEMSIZE = {"f32": 4, "f64": 8}
HEADROOM = 0.9  # of the available memory a run may plan to use


def check_writable(path: str | os.PathLike, what: str = "output") -> Path:
    """`path` can be written (its folder made if need be), checked by creating it and, when
    it did not exist, removing it again: the same error now that the write would give later."""
    path = Path(path)
    if path.is_dir():
        raise ClothbenchError(f"{what} {path} is a directory: name a file")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        existed = path.exists()
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.close(fd)
        if not existed:
            path.unlink()
    except OSError as e:
        raise ClothbenchError(f"cannot write {what} {path}: {e.strerror}") from None
    return path


def available_memory() -> int | None:
    """Bytes the machine can give a new allocation now (MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def row_bytes(grid: int, precision: str = "f32", reference: bool = True) -> int:
    """A simple, honest estimate of the host memory one row on an n x n grid needs at its peak."""
    cells = grid * grid * 4
    need = cells * ITEMSIZE.get(precision, 8) * ARRAYS.get(precision, 24)
    return need + (cells * 8 * REFERENCE_ARRAYS if reference else 0)


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check_memory(
    grids: Iterable[int], precisions: Iterable[str] = ("f32",), jobs: int = 1, available: int | None = None,
    reference: bool = True,
) -> None:
    """Refuse, in one line, a grid whose rows (`jobs` of them at once) need more memory than
    the machine has available; reference=False: rows with no float64 run beside them (render, view)."""
    available = available_memory() if available is None else available
    if not available:
        return
    precisions = tuple(precisions) or ("f32",)
    for grid in grids:
        need = max(row_bytes(grid, p, reference) for p in precisions) * max(1, jobs)
        if need > HEADROOM * available:
            at_once = f" ({jobs} rows at once)" if jobs > 1 else ""
            raise ClothbenchError(
                f"grid {grid} needs about {_gib(need)} of memory{at_once}, and this machine has "
                f"{_gib(available)} available: use a smaller grid" + (" or fewer --jobs" if jobs > 1 else "")
            )
