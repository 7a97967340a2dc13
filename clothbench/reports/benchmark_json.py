"""A sweep as Google Benchmark's JSON (`clothbench sweep --json FILE`), for the dashboards
and tools that read that format, with clothbench's own fields beside GB's.

The mapping. A sweep row is one benchmark run: its timed run is S*R steps, so its
"iteration" entry has iterations = S*R and real_time = the mean ms per step over them
(GB's definition: the run's wall-clock time over its iterations). The R timed chunks are
what GB calls repetitions; the "<name>_median" entry (run_type "aggregate", repetitions R,
iterations S) holds their median, the ms_median that the CSV, the plots and `compare` use.
cpu_time is left out: clothbench does not measure the process's CPU time (on a GPU
backend it would be the host's waiting, not the work). A row that failed or blew up is an
entry with error_occurred and error_message, as GB writes a run that reported an error.

The file is rewritten whole after every row (a temporary file renamed over it), so an
interrupted sweep leaves valid JSON of every row in the CSV.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
from datetime import datetime
from pathlib import Path

from clothbench import environment
from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import KEY_COLUMNS, parse_chunks

# CSV columns copied into each entry as numbers, when the row has them.
NUMBER_FIELDS = (
    "grid",
    "particles",
    "springs",
    "dt",
    "steps",
    "repeats",
    "ms_median",
    "ms_min",
    "ms_max",
    "ms_iqr",
    "device_ms_median",
    "particles_per_s",
    "ms_per_sim_s",
    "warmup_s",
    "max_penetration_m",
    "err_rms_m",
    "err_max_m",
    "bound_ms",
    "specialised_speedup",
)
# ... as true/false ...
BOOL_FIELDS = ("peer", "strict", "generic", "finite")
# ... and as text.
TEXT_FIELDS = (
    "backend",
    "solver",
    "pbd_method",
    "mode",
    "precision",
    "transfer",
    "local_size",
    "device",
    "scene",
    "status",
    "note",
    "timed_region",
    "env",
    "git_commit",
    "timestamp",
)
# Key columns that the name leaves to the mode (added only where two names would clash).
_NAMED = ("backend", "solver", "pbd_method", "scene", "grid")


def check_writable(path: str | os.PathLike) -> Path:
    """`path`, after making sure a file can be written there (one line if not)."""
    path = Path(path)
    if path.is_dir():
        raise ClothbenchError(f"--json {path} is a directory: name a file")
    for folder in path.parents:
        if folder.exists() and not folder.is_dir():
            raise ClothbenchError(f"cannot write --json {path}: {folder} is a file, not a folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", delete=True):
            pass
    except OSError as e:
        raise ClothbenchError(f"cannot write --json {path}: {e.strerror or e}") from None
    return path


def benchmark_names(rows: list[dict[str, str]]) -> list[str]:
    """One name per row, 'backend/solver/mode/scene/grid' (GB's 'family/arg/...' shape),
    the other key columns added where two rows would otherwise share a name."""

    def base(r):
        solver = f"{r['solver']}-{r['pbd_method']}" if r.get("pbd_method") else r["solver"]
        return f"{r['backend']}/{solver}/{r['mode']}/{r['scene']}/{r['grid']}"

    names = [base(r) for r in rows]
    clashing = {n for n in names if names.count(n) > 1}
    for i, row in enumerate(rows):
        if names[i] in clashing:
            names[i] += "".join(f"/{c}={row[c]}" for c in KEY_COLUMNS if c not in _NAMED and row.get(c))
    return names


def _number(text: str) -> int | float | str:
    """A CSV number as JSON's: an int where the text is one, else a float (text if neither)."""
    if text.lstrip("-").isdigit():
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def _own_fields(row: dict[str, str]) -> dict:
    """clothbench's columns of `row` that are set, typed."""
    fields: dict = {c: row[c] for c in TEXT_FIELDS if row.get(c)}
    fields.update({c: row[c] == "true" for c in BOOL_FIELDS if row.get(c)})
    fields.update({c: _number(row[c]) for c in NUMBER_FIELDS if row.get(c)})
    return fields


def benchmark_entries(rows: list[dict[str, str]]) -> list[dict]:
    """The "benchmarks" list: an iteration entry per row, then a median aggregate for each
    row that has its timed chunks."""
    entries = []
    for family, (name, row) in enumerate(zip(benchmark_names(rows), rows)):
        steps, repeats = int(row["steps"]), int(row["repeats"])
        chunks = parse_chunks(row.get("chunk_ms", ""))
        ok = row["status"] == "ok" and row.get("ms_median")
        common = {"name": name, "family_index": family, "per_family_instance_index": 0, "run_name": name}
        entry = {**common, "run_type": "iteration", "repetitions": 1, "repetition_index": 0, "threads": 1}
        if ok:
            mean = statistics.fmean(chunks) if chunks else float(row["ms_median"])
            entry.update(iterations=steps * repeats, real_time=mean, time_unit="ms")
        else:
            entry.update(error_occurred=True, error_message=f"{row['status']}: {row.get('note', '')}".rstrip(": "))
            entry.update(iterations=0, real_time=0.0, time_unit="ms")
        entry.update(_own_fields(row))
        if chunks:
            entry["chunk_ms"] = chunks
        entries.append(entry)
        if ok and chunks:
            entries.append(
                {
                    **common,
                    "name": f"{name}_median",
                    "run_type": "aggregate",
                    "repetitions": len(chunks),
                    "threads": 1,
                    "aggregate_name": "median",
                    "aggregate_unit": "time",
                    "iterations": steps,
                    "real_time": statistics.median(chunks),
                    "time_unit": "ms",
                    **{k: v for k, v in _own_fields(row).items() if k in ("backend", "mode", "grid", "device")},
                }
            )
    return entries


def context(sweep_csv: str | os.PathLike, settings: dict | None = None) -> dict:
    """GB's "context" for this machine now, with clothbench's machine fields and the
    sweep's settings (`settings`: scene, steps, repeats, ...) under "clothbench"."""
    ctx: dict = {
        "date": datetime.now().astimezone().isoformat(timespec="seconds"),
        "host_name": environment.host_name(),
        "executable": "clothbench sweep",
        "num_cpus": environment.cores(),
    }
    mhz = environment.cpu_mhz()
    if mhz is not None:
        ctx["mhz_per_cpu"] = mhz
    scaling = environment.cpu_scaling_enabled()
    if scaling is not None:
        ctx["cpu_scaling_enabled"] = scaling
    found = environment.caches()
    if found:
        ctx["caches"] = found
    try:
        ctx["load_avg"] = list(os.getloadavg())
    except OSError:
        pass
    ctx["library_build_type"] = "release"  # clothbench has no debug build; GB warns on "debug"
    ctx["clothbench"] = {**environment.machine(), "sweep_csv": str(sweep_csv), **(settings or {})}
    return ctx


def write_benchmark_json(path: str | os.PathLike, rows: list[dict[str, str]], ctx: dict) -> None:
    """Replace `path` with the sweep's rows as GB JSON, atomically: a reader (or a crash)
    sees the old file or the new one, never half of one."""
    path = Path(path)
    document = {"context": ctx, "benchmarks": benchmark_entries(rows)}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o644)  # mkstemp's 0600 would make the renamed file private
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(document, f, indent=2, allow_nan=False)
            f.write("\n")
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
