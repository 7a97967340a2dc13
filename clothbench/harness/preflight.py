"""Checks made before any work, so a bad output path or a grid the machine cannot hold never
costs a finished run: every output path writable, the memory a grid needs against what the
machine has available."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from pathlib import Path
from typing import Iterable

from clothbench.errors import ClothbenchError

# n*n float4 arrays of the working precision a row holds at its peak (state, ping-pong copy,
# the step's temporaries: numpy forms the 12 neighbours' differences at once): the measured
# peak, rounded up (docs/bounds.md, "The memory a row needs").
ARRAYS = {"f32": 24, "f64": 13}
REFERENCE_ARRAYS = 13  # the float64 run a sweep row is compared with
ITEMSIZE = {"f32": 4, "f64": 8}
HEADROOM = 0.9  # of the available memory a run may plan to use


def check_writable(
    path: str | os.PathLike, what: str = "output", new_folder: bool = False, make_folders: bool = False
) -> Path:
    """`path` can be written, checked by creating it and, when it did not exist, removing it
    again: the same error now that the write would give later. Its folder must exist: a
    command that writes one file makes no folders (a typo would plant them anywhere, the
    filesystem root included); new_folder: the folder is itself the output (render's
    frames/), made here if its own folder exists, and removed again if it was made;
    make_folders: a command's default path (results/...), whose folders it makes itself."""
    path = Path(path)
    if path.is_dir():
        raise ClothbenchError(f"{what} {path} is a directory: name a file")
    folder = path.parent
    above = _nearest_existing(folder)
    if above is not None and not above.is_dir():
        raise ClothbenchError(f"cannot write {what} {path}: {above} is a file, not a folder")
    base = folder.parent if new_folder else folder
    if make_folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise ClothbenchError(f"cannot write {what} {path}: {e.strerror}") from None
    elif not base.is_dir():
        raise ClothbenchError(f"cannot write {what} {path}: there is no folder {base} (make it first)")
    made = new_folder and not folder.exists()
    # a Ctrl-C or SIGTERM between creating the probe and removing it would leave an empty file
    # (or folder) behind an interrupted command: both wait until the probe is gone
    with signals_held():
        try:
            if made:
                folder.mkdir()
            existed = path.exists()
            fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
            os.close(fd)
            if not existed:
                path.unlink()
        except OSError as e:
            raise ClothbenchError(f"cannot write {what} {path}: {e.strerror}") from None
        finally:
            if made and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()
    return path


def check_folder(folder: str | os.PathLike, what: str = "output folder") -> Path:
    """`folder` is one this process can write in, or can make with its parents, checked
    without making it (a command that draws for seconds first must not learn it at the end):
    its nearest existing ancestor is a folder, writable."""
    folder = Path(folder)
    above = _nearest_existing(folder)
    if above is not None and not above.is_dir():
        raise ClothbenchError(f"cannot create {what} {folder}: {above} is a file, not a folder")
    if above is not None and not os.access(above, os.W_OK | os.X_OK):
        raise ClothbenchError(f"cannot create {what} {folder}: {above} is not writable")
    return folder


def _nearest_existing(folder: Path) -> Path | None:
    """`folder` or its nearest parent that exists (a file there means no folder can be made)."""
    return next((above for above in (folder, *folder.parents) if above.exists()), None)


@contextlib.contextmanager
def signals_held(signals=(signal.SIGINT, signal.SIGTERM)):
    """SIGINT and SIGTERM held back inside the block and raised again as it ends, so their
    handlers (KeyboardInterrupt) run after it, never half way through it. Held by a handler that
    only notes the signal, not by the thread's signal mask: numpy's BLAS threads do not block
    it, and the kernel hands a process its signal through any thread that does not. Only the
    main thread runs Python's signal handlers; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received = []
    before = {sig: signal.signal(sig, lambda signum, frame: received.append(signum)) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
        for sig in dict.fromkeys(received):
            signal.raise_signal(sig)


def check_float32_motion(scene, solver) -> None:
    """What float32 positions cannot carry, refused in one line (as dt^2 underflow is, in
    solver.py): a cloth so far from 0 that the g*h^2 a free particle falls in its first
    (sub)step is at most half the float32 spacing of its coordinates (np.spacing), so that
    2x - x_prev + a h^2 rounds back to x and the cloth never moves (height 1e4 at dt 5e-4:
    tests/hard_cases/test_far_from_origin.py); a fall of one to two spacings still moves, coarsely. And a size
    whose springs' squared lengths and forces overflow float32 (inf, then NaN, at step 1).
    For float32 runs only: float64 holds both."""
    import math

    import numpy as np

    from clothbench.model.solver import FLOAT32_MAX

    h = solver.dt / getattr(solver, "substeps", 1)
    g = [abs(c) for c in scene.gravity]
    axis = max(range(3), key=g.__getitem__)
    fall = g[axis] * h * h
    extent = (scene.size, abs(scene.height), scene.size)  # x and z span the sheet, y is its height
    where = ("size", "height", "size")[axis]
    ulp = float(np.spacing(np.float32(extent[axis])))
    if fall > 0 and fall <= ulp / 2:
        raise ClothbenchError(
            f"{where} {extent[axis]:g} is too far from 0 for float32: positions there are {ulp:.3g} m apart "
            f"(np.spacing), and the g*dt^2 = {fall:.3g} m a particle falls in a step is under half that, so "
            "it rounds away and the cloth never moves; put the scene nearer 0, use a larger dt or --precision f64"
        )
    longest = max(scene.rest_lengths())
    terms = {
        "the longest spring's squared length": longest * longest,
        "the sheet's squared extent (collider distances)": 3 * max(scene.size, abs(scene.height)) ** 2,
        "a spring's force k*rest*dt^2/m": scene.stiffness * longest * solver.dt**2 / scene.mass if scene.mass else 0.0,
    }
    for name, value in terms.items():
        if not math.isfinite(value) or value > FLOAT32_MAX:
            raise ClothbenchError(
                f"size {scene.size:g} overflows float32 in the step: {name} is {value:.3g}, above its max "
                f"{FLOAT32_MAX:.4g} (the state would be inf at step 1); use a smaller size or --precision f64"
            )


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
    grids: Iterable[int],
    precisions: Iterable[str] = ("f32",),
    jobs: int = 1,
    available: int | None = None,
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
