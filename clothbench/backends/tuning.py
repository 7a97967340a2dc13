"""Kernel shape chosen per device by measurement, and remembered.

A backend with several kernel shapes (vector width, work-group size, tile shape, ...) lists
them as candidates; the first time a (backend, device, driver version, scene shape, grid,
arithmetic) is met, each candidate is timed for a few steps, the candidates taking turns for
TUNING_ROUNDS rounds and each keeping its fastest turn (a load that comes and goes on a shared
machine then falls on every candidate alike, rather than on whichever was being timed), and
the fastest is kept in
`<cache>/tuning/<backend>.json` (clothbench.native.cache_dir). Later runs read the choice
back without measuring; `--retune` measures again and replaces it. The chosen shape is part
of the row's mode, so a CSV says what ran.

Strict builds stay bit-exact whatever wins: a shape changes how the work is split, never the
operations done on one particle (each backend's contract test runs every candidate).

CLOTHBENCH_TUNING=off skips the measurement and takes each backend's default shape (the
first candidate): what the test suite does, so that a test's result never depends on which
shape won on the machine running it.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from typing import Callable, Sequence

from clothbench.errors import ClothbenchError
from clothbench.native import cache_dir

TUNING_ENV = "CLOTHBENCH_TUNING"
# turns per candidate: with one timed turn each, the tuner picked a band shape ~20% slower than
# another at 128^2 on the Zen 5 (docs/pbd.md); with interleaved turns a passing load falls on one
# turn of every candidate instead of deciding the choice
TUNING_ROUNDS = 3


def tuning_enabled() -> bool:
    value = os.environ.get(TUNING_ENV, "on").strip().lower()
    if value not in ("on", "off"):
        raise ClothbenchError(f"{TUNING_ENV} must be on or off, got {value!r}")
    return value == "on"


def _path(backend: str):
    return cache_dir("tuning") / f"{backend}.json"


def _load(backend: str) -> dict:
    path = _path(backend)
    try:
        data = json.loads(path.read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, ValueError):  # absent or damaged: measure again, never fail a run for it
        return {}


def _store(backend: str, key: str, entry: dict) -> None:
    """Read, update and replace the file atomically: concurrent writers lose at most an entry."""
    data = _load(backend)
    data[key] = entry
    path = _path(backend)
    fd, partial = tempfile.mkstemp(dir=path.parent, suffix=".json.partial")
    with os.fdopen(fd, "w") as f:
        json.dump(data, f, indent=1, sort_keys=True)
    os.replace(partial, path)


def cached_choice(backend: str, key: dict[str, str]) -> str | None:
    """The shape chosen before for `key`, or None."""
    entry = _load(backend).get(json.dumps(key, sort_keys=True))
    return entry.get("choice") if isinstance(entry, dict) else None


def choose_shape(
    backend: str,
    key: dict[str, str],
    candidates: Sequence[str],
    time_candidate: Callable[[str], float],
    retune: bool = False,
) -> str:
    """The shape to run for `key` among `candidates` (names; the first is the default).

    time_candidate(name) -> seconds for a short synchronised run of that shape (the backend
    builds it, warms it up and times a few steps), called TUNING_ROUNDS times per candidate in
    turns; a candidate's fastest turn counts. A candidate that raises is dropped (a
    work-group too large for this device, say), unless every one does."""
    if not candidates:
        raise ClothbenchError(f"{backend}: no kernel shape to choose from")
    if len(candidates) == 1 or not tuning_enabled():
        return candidates[0]
    text_key = json.dumps(key, sort_keys=True)
    if not retune:
        entry = _load(backend).get(text_key)
        if isinstance(entry, dict) and entry.get("choice") in candidates:
            return entry["choice"]
    measured: dict[str, float] = {}
    failures: dict[str, str] = {}
    for _ in range(TUNING_ROUNDS):
        for name in candidates:
            if name in failures:
                continue
            try:
                seconds = time_candidate(name)
            except ClothbenchError as e:
                failures[name] = str(e).splitlines()[0]
                measured.pop(name, None)
                continue
            measured[name] = min(seconds, measured.get(name, seconds))
    if not measured:
        raise ClothbenchError(f"{backend}: no kernel shape runs here ({'; '.join(f'{k}: {v}' for k, v in failures.items())})")
    choice = min(measured, key=measured.get)
    _store(
        backend,
        text_key,
        {
            "choice": choice,
            "ms": {k: round(v * 1e3, 5) for k, v in measured.items()},
            "failed": failures,
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    )
    return choice


def median_seconds(run: Callable[[], None], synchronize: Callable[[], None], repeats: int = 5) -> float:
    """Median wall time of `run` over `repeats` synchronised calls, after one untimed call."""
    run()
    synchronize()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        synchronize()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
