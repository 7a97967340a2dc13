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

A choice is `final` or `provisional`, so that a choice made in one busy minute does not stick
for good (docs/timing.md, "Kernel shapes chosen on a busy machine"). The tuning watches the
machine while it measures (clothbench.machine_load: other processes' CPU, steal); a choice
made while the machine was busy, or whose best two candidates lie within their own noise, is
provisional. The next meeting of a provisional key on a quiet
machine (a MIN_WINDOW_S look first) re-measures only its best RECHECK_BEST candidates and the
default, and that quiet re-measure is final, tie or not (a tie on a quiet machine is a tie:
either shape is as fast). A busy meeting keeps the provisional choice and measures nothing:
tuning time spent while busy would only measure the load again; nor does the process that
measured it, a moment later (a sweep meets a key once per row). A final choice is measured
again when its key changes (kernel, driver, machine: they are in the key), on --retune, and
once when a sweep row using it on a quiet machine runs FAR_OFF times its recorded time
(check_row). An entry without a status (UNMARKED) is read as provisional, since nothing says
the machine was quiet when it was measured; each costs one small quiet re-measure.

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

from clothbench import environment, machine_load
from clothbench.errors import ClothbenchError
from clothbench.machine_load import MIN_WINDOW_S, Load, LoadSampler
from clothbench.native import cache_dir
from clothbench.progress import waiting

TUNING_ENV = "CLOTHBENCH_TUNING"
# turns per candidate: with one timed turn each, a passing load can decide the choice (the
# tuner's picks that docs/pbd.md, "Time per step on OpenCL", finds not the fastest); with
# interleaved turns it falls on one turn of every candidate instead
TUNING_ROUNDS = 3
# a provisional choice is re-measured with its best RECHECK_BEST candidates by the stored times,
# plus the default (the first candidate): for c that is every core, the shape a load hurts most,
# so the one a busy ranking is most likely to have put too low
RECHECK_BEST = 2
# a sweep row on a quiet machine this many times slower than its shape's recorded time sends the
# choice back to provisional: a row runs longer and later in the motion than a tuning turn, and
# has collisions the start has not, so small differences are expected; 1.5x is not one of them
FAR_OFF = 1.5
FINAL, PROVISIONAL = "final", "provisional"
UNMARKED = "stored before tuning recorded the machine's load"

sampler = LoadSampler()  # the machine's load; tests replace it with recorded numbers
_met: dict[str, dict] = {}  # backend -> the choice choose_shape last returned for it (check_row)
# (backend, key)s this process measured: a provisional one is re-checked by a later run, not
# by the same process a moment later (a sweep meets a key once per row; it is the same minute)
_measured_here: set[tuple[str, str]] = set()


def sweeps_key(solver) -> dict[str, str]:
    """The part of a VBD or PBD tuning key its launches depend on (VBD on opencl, glsl-compute
    and cuda alike; PBD on opencl): the solver, its sweeps (iterations) a substep, its substeps,
    and Chebyshev (VBD: a launch more a sweep; Jacobi PBD: a second multiplier buffer), so that
    neither another solver's choice nor one of other settings answers for it."""
    return {
        "solver": solver.spec,
        "iterations": str(solver.iterations),
        "substeps": str(solver.substeps),
        "chebyshev": "on" if solver.chebyshev_rho > 0 else "off",
    }


# A timed turn of a candidate is about this many particle-steps: a few milliseconds on every
# CPU backend at every grid (c's 2-thread step ~0.25 ms at 256^2, 65,536 particles), so that a
# turn is long against the clock and a launch, and short against the row it tunes. A fixed step
# count per turn instead made the largest grids' tuning the slowest part of a sweep: 8 steps of
# glsl-compute at 2048^2 on llvmpipe are 0.44 s a turn, 60 turns a row (docs/timing.md).
TURN_PARTICLE_STEPS = 2_000_000


def turn_steps(
    per_step: int, least: int = 1, most: int = 50, multiple: int = 1, work: int = TURN_PARTICLE_STEPS
) -> int:
    """Steps of a timed turn while tuning: about `work` units of what a step does `per_step` of
    (particles; particle-sweeps for VBD), within [least, most], rounded up to a whole number of
    `multiple` (a multi-step launch's steps)."""
    steps = max(least, min(most, work // max(1, per_step)))
    return -(-steps // multiple) * multiple


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


def status_of(entry: dict) -> str:
    """final or provisional; an entry without a status (written before statuses) is provisional."""
    return FINAL if entry.get("status") == FINAL else PROVISIONAL


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

    time_candidate(name) -> seconds per step of a short synchronised run of that shape (the
    backend builds it, warms it up and times a few steps), called TUNING_ROUNDS times per
    candidate in turns; a candidate's fastest turn counts. A candidate that raises is dropped
    (a work-group too large for this device, say), unless every one does. A provisional choice
    met on a quiet machine is re-measured first (module docstring)."""
    if not candidates:
        raise ClothbenchError(f"{backend}: no kernel shape to choose from")
    if len(candidates) == 1 or not tuning_enabled():
        return candidates[0]
    text_key = json.dumps(key, sort_keys=True)
    entry = None if retune else _load(backend).get(text_key)
    if isinstance(entry, dict) and entry.get("choice") in candidates:
        if status_of(entry) == FINAL or (backend, text_key) in _measured_here:
            return _meet(backend, text_key, entry)
        if sampler.sample(MIN_WINDOW_S).busy is True:
            return _meet(backend, text_key, entry)  # busy: keep the provisional one, measure nothing
        names = recheck_candidates(entry, candidates)
        turns, failures, load = _measure(backend, text_key, names, time_candidate)
        if load.busy is True:  # the load came back while re-measuring: nothing learnt
            return _meet(backend, text_key, entry)
        fresh = _entry(turns, failures, load, recheck=True)
        fresh["replaced"] = {k: entry.get(k) for k in ("choice", "status", "why", "measured_at")}
        fresh["replaced"]["status"] = status_of(entry)
        if entry.get("row_flagged") or entry.get("row_rechecked"):
            fresh["row_rechecked"] = True  # a row's doubt is answered once (check_row)
        _store(backend, text_key, fresh)
        return _meet(backend, text_key, fresh)
    turns, failures, load = _measure(backend, text_key, list(candidates), time_candidate)
    fresh = _entry(turns, failures, load, recheck=False)
    _store(backend, text_key, fresh)
    return _meet(backend, text_key, fresh)


def _measure(backend: str, text_key: str, names: list[str], time_candidate) -> tuple[dict, dict, Load]:
    """Every candidate's turn times (seconds per step), the failures, and the load meanwhile."""
    what = f"tuning {backend} (measured once, then cached)"
    with waiting(what, timed=True) as say:
        window = sampler.start()
        _measured_here.add((backend, text_key))
        turns: dict[str, list[float]] = {}
        failures: dict[str, str] = {}
        for turn in range(TUNING_ROUNDS):
            for name in names:
                if name in failures:
                    continue
                say(f"{what}: {name}, turn {turn + 1} of {TUNING_ROUNDS}")  # drawn here, between the timed runs
                try:
                    seconds = time_candidate(name)
                except ClothbenchError as e:
                    failures[name] = str(e).splitlines()[0]
                    turns.pop(name, None)
                    continue
                turns.setdefault(name, []).append(seconds)
        if not turns:
            why = "; ".join(f"{k}: {v}" for k, v in failures.items())
            raise ClothbenchError(f"{backend}: no kernel shape runs here ({why})")
        return turns, failures, window.stop(MIN_WINDOW_S)  # a short tuning waits out the window for a verdict


def threads_for_this_run(threads: int, chosen_by_user: bool) -> tuple[int, str]:
    """(threads, why) a split step runs on now: the chosen count, or fewer where the machine
    is busy (machine_load.threads_left_free), with why; (threads, '') where the count is the
    user's, or tuning is off (the test suite: nothing measured decides a run). For this run
    only: the cached choice is untouched, as a choice made under load must not stick."""
    if chosen_by_user or threads <= 1 or not tuning_enabled():
        return threads, ""
    free, load = machine_load.threads_left_free(threads, environment.cores())
    if free >= threads:
        return threads, ""
    return free, f"the machine was busy ({load.why})"


def noise(times: Sequence[float]) -> float:
    """A candidate's noise: its second-fastest turn less its fastest. One slow turn (a load
    that passed) does not count, as it does not count for the choice; two do."""
    fastest = sorted(times)
    return fastest[1] - fastest[0] if len(fastest) > 1 else 0.0


def overlap(turns: dict[str, list[float]]) -> tuple[str, str, float, float] | None:
    """(best, next, gap, noise) where the best two candidates' fastest turns differ by no more
    than the larger of their noises, else None."""
    if len(turns) < 2:
        return None
    best, second = sorted(turns, key=lambda n: min(turns[n]))[:2]
    gap = min(turns[second]) - min(turns[best])
    spread = max(noise(turns[best]), noise(turns[second]))
    return (best, second, gap, spread) if gap <= spread else None


def _entry(turns: dict[str, list[float]], failures: dict[str, str], load: Load, recheck: bool) -> dict:
    best = {k: min(v) for k, v in turns.items()}
    choice = min(best, key=best.get)
    tie = overlap(turns)
    if load.busy is True:
        status, why = PROVISIONAL, f"busy: {load.why}"
    elif tie and not recheck:
        b, s, gap, spread = tie
        why = f"{b} and {s} within their noise ({gap * 1e3:.4g} ms apart, noise {spread * 1e3:.4g} ms)"
        status = PROVISIONAL
    else:
        status = FINAL
        why = ("a quiet re-measure" if recheck else "quiet, clear winner") + (f"; {load.why}" if load.why else "")
    return {
        "choice": choice,
        "ms": {k: round(v * 1e3, 5) for k, v in best.items()},  # each one's fastest turn
        "turns_ms": {k: [round(t * 1e3, 5) for t in v] for k, v in turns.items()},
        "failed": failures,
        "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "status": status,
        "why": why,
        "load": load.as_dict(),
    }


def recheck_candidates(entry: dict, candidates: Sequence[str]) -> list[str]:
    """The best RECHECK_BEST of `candidates` by the entry's stored times, plus the default."""
    ms = entry.get("ms") if isinstance(entry.get("ms"), dict) else {}
    timed = [n for n in candidates if isinstance(ms.get(n), (int, float))]
    names = sorted(timed, key=ms.get)[:RECHECK_BEST]
    names += [n for n in dict.fromkeys((entry["choice"], candidates[0])) if n not in names]
    names += [n for n in candidates if n not in names][: max(0, 2 - len(names))]  # two at least
    return [n for n in candidates if n in names]  # in the candidates' own order


def _meet(backend: str, text_key: str, entry: dict) -> str:
    _met[backend] = {"key": text_key, "entry": entry}
    return entry["choice"]


def forget_met() -> None:
    """Forget which choices were met: the harness calls it before building a row's backend, so
    that check_row sees only that backend's (a --shape run, or tuning off, meets none)."""
    _met.clear()


def check_row(backend: str, shape: str | None, ms_per_step: float, quiet: bool) -> str:
    """The note a row of `backend` running `shape` at `ms_per_step` should carry about its
    shape's tuning: '' for a final choice; a line for a provisional one (the sweep's c rows are
    every ratio's reference, a provisional one must say so). On a `quiet` machine, a final
    choice whose row runs more than FAR_OFF times its recorded time goes back to provisional
    (once per choice: a row that is always slower than its tuning turns is not news)."""
    met = _met.get(backend)
    if met is None or shape is None or met["entry"].get("choice") != shape:
        return ""
    entry = met["entry"]
    if status_of(entry) == PROVISIONAL:
        return f"kernel shape {shape} from a provisional tuning ({entry.get('why') or UNMARKED})"
    recorded = (entry.get("ms") or {}).get(shape)
    if not quiet or entry.get("row_rechecked") or not isinstance(recorded, (int, float)) or recorded <= 0:
        return ""
    if ms_per_step <= FAR_OFF * recorded:
        return ""
    why = f"a quiet row ran {ms_per_step:.4g} ms/step, {ms_per_step / recorded:.1f}x its tuning's {recorded:.4g} ms"
    stored = _load(backend).get(met["key"])
    if isinstance(stored, dict) and stored.get("choice") == shape and status_of(stored) == FINAL:
        _store(backend, met["key"], {**stored, "status": PROVISIONAL, "why": why, "row_flagged": True})
    return f"kernel shape {shape}: {why}; re-measured at the next quiet run"


def listing() -> list[dict]:
    """Every cached choice, for `clothbench tuning`: backend, key, choice, status, why, when,
    load, and how far apart the best two candidates were against their noise."""
    rows = []
    for path in sorted(cache_dir("tuning").glob("*.json")):
        for text_key, entry in sorted(_load(path.stem).items()):
            if not isinstance(entry, dict) or "choice" not in entry:
                continue  # not a choice (the OpenCL probe cache shares the folder)
            try:
                key = json.loads(text_key)
            except ValueError:
                key = {"key": text_key}
            rows.append({"backend": path.stem, "key": key, **_summary(entry)})
    return rows


def _summary(entry: dict) -> dict:
    ms = {k: v for k, v in (entry.get("ms") or {}).items() if isinstance(v, (int, float))}
    ranked = sorted(ms, key=ms.get)
    turns = entry.get("turns_ms") or {}
    apart = (ms[ranked[1]] - ms[ranked[0]]) / ms[ranked[0]] if len(ranked) > 1 and ms[ranked[0]] > 0 else None
    spread = [noise(turns[n]) / ms[n] for n in ranked[:2] if turns.get(n) and ms[n] > 0]
    load = entry.get("load") if isinstance(entry.get("load"), dict) else {}
    return {
        "choice": entry["choice"],
        "status": status_of(entry),
        "why": entry.get("why") or UNMARKED,
        "measured_at": entry.get("measured_at", ""),
        "other_share": load.get("other_share"),
        "steal_share": load.get("steal_share"),
        "busy": load.get("busy"),
        "next_best": ranked[1] if len(ranked) > 1 else None,
        "apart": None if apart is None else round(apart, 4),
        "noise": round(max(spread), 4) if spread else None,
        "ms": ms,
    }


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
