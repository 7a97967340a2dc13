"""What both xdist workers would compute alike, computed once per test run and shared.

Each is the same in both workers (a reference is a function of its arguments alone; the limits
are the one machine's), cached per process by clothbench; with two workers it was computed twice,
and for the references clothbench's cache (32 states) dropped states that later tests of the same
worker asked for again. The first process to need one
computes it under a lock and writes it to the run's shared temporary folder; every other reads
the file. CLOTHBENCH_SHARED_RUNS names a folder that several runs share instead: .ci/run makes
one for its full tier and OpenCL legs (measured on the Zen 3: a warm leg 92 s, 66 s reading the
references). A folder of one checkout only: a file's key holds no version of the step's code.

- NumPy's float32 references (`harness.reference(..., "f32")`): NumPy's own step, never `c`'s,
  whatever the machine has (harness/simulate.py). Float64 references are not shared: which
  backend steps them is what some tests check (tests/test_c_backend.py), and `c` makes them
  cheap. A run with `simulate._states` replaced (the `reference_steppers` fixture records each
  run) steps every reference itself.
- The machine's limits (`bounds.measure_machine`, a STREAM run over 1.5 GiB: 3–8 s on these
  VMs), which every in-process sweep with bounds measures once per process.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import importlib
import json
import os
import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np

import clothbench.harness as harness
from clothbench.harness import bounds

simulate = importlib.import_module("clothbench.harness.simulate")  # the module: harness.simulate is its function

_REFERENCE = simulate.reference
_STATES = simulate._states
_MEASURED = bounds._measured
_folder: Path | None = None  # set once the session's shared temporary folder is known


def share_in(folder: Path) -> None:
    """Keep this run's shared results in `folder` (a folder both workers see)."""
    global _folder
    folder.mkdir(parents=True, exist_ok=True)
    _folder = folder


def _once(path: Path, write: Callable[[Path], None]) -> Path:
    """`path`, written by write(partial) in the first process to ask; the others wait for it."""
    if not path.exists():
        with open(path.with_name(path.name + ".lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not path.exists():
                partial = path.with_name(f"{os.getpid()}.{path.name}")
                write(partial)
                partial.replace(path)  # whole or absent: a reader never sees half a file
    return path


# --- NumPy's float32 references --------------------------------------------------------------


@functools.lru_cache(maxsize=64)  # a test that asks again reads no file again
def _read_state(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with np.load(path) as saved:
        pos, prev = saved["pos"], saved["prev"]
    pos.setflags(write=False)
    prev.setflags(write=False)
    return pos, prev


@functools.wraps(_REFERENCE)
def reference(scene, solver, steps, precision="f64"):
    if precision != "f32" or _folder is None or simulate._states is not _STATES:
        return _REFERENCE(scene, solver, steps, precision)
    # pickle holds every field, arrays included (a repr would summarise a mesh's vertices)
    key = hashlib.sha256(pickle.dumps((scene, solver, steps), protocol=5)).hexdigest()

    def write(partial: Path) -> None:
        pos, prev = _REFERENCE(scene, solver, steps, precision)
        with open(partial, "wb") as f:
            np.savez(f, pos=pos, prev=prev)

    return _read_state(_once(_folder / f"reference-{key}.npz", write))


reference.cache_clear = _REFERENCE.cache_clear
# every `from clothbench.harness(.simulate) import reference` made after conftest's import gets this
simulate.reference = reference
harness.reference = reference


# --- the machine's limits --------------------------------------------------------------------


@functools.lru_cache(maxsize=None)  # once per process, as bounds._measured is (tests/test_bounds.py)
def _measured(threads: int, array_mib: int) -> bounds.MachineBounds:
    if _folder is None:
        return _MEASURED(threads, array_mib)

    def write(partial: Path) -> None:  # a ClothbenchError (no compiler) writes nothing: each asks
        partial.write_text(json.dumps(_MEASURED(threads, array_mib).to_dict()))

    path = _once(_folder / f"machine-bounds-{threads}-{array_mib}.json", write)
    return bounds.MachineBounds.from_dict(json.loads(path.read_text()))


_measured.__wrapped__ = _MEASURED.__wrapped__  # what a test that measures again without the cache calls
bounds._measured = _measured
