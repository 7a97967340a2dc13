"""`clothbench plot` (the chapter's figures from a sweep CSV) and `clothbench compare`
(what changed between two sweeps: two machines, two commits)."""

from __future__ import annotations

import math
import zlib
from pathlib import Path

from clothbench.errors import ClothbenchError
from clothbench.harness.sweep_csv import KEY_COLUMNS, KEY_COLUMNS_ADDED_LATER

# What compare needs of both files: the key columns but those added later (an older file's
# rows still compare with a newer's), and what it compares.
COMPARE_REQUIRED = tuple(c for c in KEY_COLUMNS if c not in KEY_COLUMNS_ADDED_LATER) + (
    "mode",
    "status",
    "ms_median",
    "steps",
    "repeats",
    "dt",
)
# Significance: a bootstrap of the ratio of medians over each row's timed chunks (chunk_ms),
# seeded by the row's key so that the same two files always give the same intervals.
CONFIDENCE = 0.95
RESAMPLES = 4000
MIN_CHUNKS = 5  # fewer per side: resampled medians take too few values for an interval to mean anything


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "plot",
        help="draw the comparison plots (PNG and SVG) from a sweep CSV",
        description="Draw time per step against grid size (the chapter's Figures 22.5/22.6), throughput "
        "with fitted scaling exponents, speed against error, and work-group size against time, as PNG "
        "and SVG.",
    )
    p.add_argument("csv", help="a CSV written by clothbench sweep")
    p.add_argument(
        "--out",
        help="folder for the plots (default: beside the CSV, named after it); with --kind mesh, the PNG to "
        "write (default: the CSV's name with .png; an SVG beside it)",
    )
    p.add_argument(
        "--kind",
        choices=["all", "mesh"],
        default="all",
        help="all: every figure the CSV has data for (default); mesh: only ms/step against mesh triangles, "
        "naive against accelerated with the crossover named (a sweep with --mesh-triangles)",
    )
    p.set_defaults(func=cmd_plot)

    c = subparsers.add_parser(
        "compare",
        help="ratios of ms/step between two sweep CSVs, row by matching row, with confidence intervals",
        description="For every row present in both sweeps (same backend, mode options, scene, grid and "
        "local size), the ratio B/A of the median ms per step (below 1, B is faster) with its "
        f"{CONFIDENCE:.0%} confidence interval: a seeded bootstrap ({RESAMPLES} resamples) of the ratio "
        "of medians over the two rows' timed chunks (the chunk_ms column). A change is flagged only "
        "where the interval excludes 1. Rows without chunk_ms (sweeps written before that column) or "
        f"with fewer than {MIN_CHUNKS} chunks are compared as before and marked untested. A row the "
        "machine was busy for, or whose chunks spread wide (a robust standard deviation over 10 % of "
        "the median), in A or B is inconclusive: listed with why, neither a pass nor a fail of the gate "
        "(--strict-gate fails it). With one run a side the interval sees the noise between chunks of "
        "one run; give several runs a side (A1.csv,A2.csv) for the spread between runs too.",
    )
    c.add_argument("a", help="the baseline sweep CSV, or several runs of it comma-separated (A1.csv,A2.csv)")
    c.add_argument("b", help="the sweep to compare with it, or several runs comma-separated")
    c.add_argument(
        "--fail-above",
        type=float,
        metavar="RATIO",
        help="exit 1 when a significant slowdown has B/A above RATIO (e.g. 1.10): a CI gate",
    )
    c.add_argument(
        "--strict-gate",
        action="store_true",
        help="with --fail-above: an inconclusive row (busy or unstable in A or B) fails the gate too",
    )
    c.set_defaults(func=cmd_compare)


def cmd_plot(args) -> int:
    from clothbench.reports.plots import plot_mesh, plot_sweep

    csv_path = Path(args.csv)
    if args.kind == "mesh":
        out = Path(args.out) if args.out else csv_path.with_suffix(".png")
        if out.suffix.lower() != ".png":
            raise ClothbenchError(
                f"--kind mesh writes one PNG (and an SVG beside it): --out must end in .png, got {out}"
            )
        report = plot_mesh(csv_path, out)
        for note in report.notes:
            print(note)
        for path in report.files:
            print(f"wrote {path}")
        return 0
    out = Path(args.out) if args.out else csv_path.with_suffix("")
    if out == csv_path:  # a CSV without a suffix
        out = csv_path.with_name(csv_path.name + "-plots")
    report = plot_sweep(csv_path, out)
    for note in report.notes:
        print(note)
    if report.exponents:
        print("scaling: time per step ∝ particles^p")
        width = max(map(len, report.exponents))
        for label, p in report.exponents.items():
            print(f"  {label:<{width}}  p = {p:.2f}")
    for path in report.files:
        print(f"wrote {path}")
    return 0


def compare_rows(a_runs: list[list[dict]], b_runs: list[list[dict]]) -> tuple[list[dict], int, int]:
    """(matched rows with ratio B/A where both are ok, and its interval where both have
    enough chunks; rows only in A; rows only in B). Each side is one or more runs (files) of
    the same sweep: the ratio is that of the runs' median ms_median, and the interval resamples
    the runs as well as their chunks, so that it holds the spread between runs too. A change
    between rows that are busy or unstable in any run (harness/noise.py) is 'inconclusive'."""
    from clothbench.harness.noise import row_doubts
    from clothbench.harness.sweep_csv import row_key

    a = _by_key(a_runs, row_key)
    b = _by_key(b_runs, row_key)
    matched = []
    for key, ras in a.items():
        rbs = b.get(key)
        if rbs is None:
            continue
        m = {
            "a": ras[0],
            "b": rbs[0],
            "a_ms": None,
            "b_ms": None,
            "ratio": None,
            "interval": None,
            "change": "n/a",
            "doubts": [],
        }
        if all(r["status"] == "ok" for r in ras + rbs):
            m["a_ms"], m["b_ms"] = _median_ms(ras), _median_ms(rbs)
            m["ratio"] = m["b_ms"] / m["a_ms"]
            chunks_a, chunks_b = [_chunks(r) for r in ras], [_chunks(r) for r in rbs]
            every = chunks_a + chunks_b
            if min(map(len, every)) >= MIN_CHUNKS and min(map(min, every)) > 0:
                seed = zlib.crc32("|".join(key).encode())
                if len(ras) == len(rbs) == 1:
                    m["interval"] = ratio_interval(chunks_a[0], chunks_b[0], seed=seed)
                else:
                    m["interval"] = runs_ratio_interval(chunks_a, chunks_b, seed=seed)
                lo, hi = m["interval"]
                m["change"] = "slower" if lo > 1 else "faster" if hi < 1 else "same"
                side_doubts = [
                    (side, d)
                    for side, rows, chunks in (("A", ras, chunks_a), ("B", rbs, chunks_b))
                    for r, c in zip(rows, chunks)
                    for d in row_doubts(r, c)
                ]
                m["doubts"] = list(dict.fromkeys(f"{side} {d}" for side, d in side_doubts))
                if m["doubts"]:
                    m["change"] = "inconclusive"
            else:
                m["change"] = "untested"
        matched.append(m)
    return matched, len(set(a) - set(b)), len(set(b) - set(a))


def _by_key(runs: list[list[dict]], row_key) -> dict[tuple, list[dict]]:
    """key -> the key's row in each run that has it (in run order)."""
    out: dict[tuple, list[dict]] = {}
    for rows in runs:
        for key, r in {row_key(r): r for r in rows}.items():  # a key's last row in a run, as before
            out.setdefault(key, []).append(r)
    return out


def _median_ms(rows: list[dict]) -> float:
    import statistics

    values = []
    for r in rows:
        try:
            v = float(r["ms_median"])
        except ValueError:
            v = math.nan
        if not (v > 0 and math.isfinite(v)):
            raise ClothbenchError(
                f"ms_median {r['ms_median']!r} of {r['backend']} n={r['grid']} is not a positive number: "
                "a row with status ok must have one"
            )
        values.append(v)
    return statistics.median(values)


def _chunks(row: dict) -> list[float]:
    from clothbench.harness.sweep_csv import parse_chunks

    try:
        return parse_chunks(row.get("chunk_ms", ""))
    except ValueError:
        raise ClothbenchError(
            f"chunk_ms {row['chunk_ms']!r} of {row['backend']} n={row['grid']} is not a list of numbers"
        ) from None


def ratio_interval(a: list[float], b: list[float], seed: int) -> tuple[float, float]:
    """The CONFIDENCE percentile interval of median(b) / median(a), bootstrapped: both
    samples resampled with replacement RESAMPLES times, from a generator seeded by `seed`."""
    import numpy as np

    rng = np.random.default_rng(seed)
    medians_a = np.median(rng.choice(np.asarray(a), size=(RESAMPLES, len(a))), axis=1)
    medians_b = np.median(rng.choice(np.asarray(b), size=(RESAMPLES, len(b))), axis=1)
    tail = (1 - CONFIDENCE) / 2
    lo, hi = np.quantile(medians_b / medians_a, [tail, 1 - tail])
    return float(lo), float(hi)


def runs_ratio_interval(a_runs: list[list[float]], b_runs: list[list[float]], seed: int) -> tuple[float, float]:
    """The CONFIDENCE interval of median(B) / median(A) where each side is several runs of
    chunks: every resample draws that side's runs with replacement, then each drawn run's
    chunks with replacement, and takes the median of them pooled (a two-level bootstrap, as
    asv's and Google Benchmark's repetitions call for): the spread between runs is in it."""
    import numpy as np

    rng = np.random.default_rng(seed)

    def medians(runs: list[list[float]]) -> np.ndarray:
        arrays = [np.asarray(r) for r in runs]
        out = np.empty(RESAMPLES)
        for i in range(RESAMPLES):
            drawn = rng.integers(len(arrays), size=len(arrays))
            out[i] = np.median(np.concatenate([rng.choice(arrays[j], size=len(arrays[j])) for j in drawn]))
        return out

    tail = (1 - CONFIDENCE) / 2
    lo, hi = np.quantile(medians(b_runs) / medians(a_runs), [tail, 1 - tail])
    return float(lo), float(hi)


def geometric_mean(values: list[float]) -> float:
    return math.exp(sum(math.log(v) for v in values) / len(values))


CHANGE_STYLE = {
    "slower": "red",
    "faster": "green",
    "same": "default",
    "untested": "yellow",
    "n/a": "yellow",
    "inconclusive": "yellow",
}


def cmd_compare(args) -> int:
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    from clothbench.harness.sweep_csv import read_sweep

    if args.fail_above is not None and not (math.isfinite(args.fail_above) and args.fail_above >= 1):
        raise ClothbenchError(f"--fail-above must be a ratio >= 1 (e.g. 1.10), got {args.fail_above}")
    if args.strict_gate and args.fail_above is None:
        raise ClothbenchError("--strict-gate applies to the gate: give --fail-above RATIO with it")
    a_files, b_files = _side(args.a), _side(args.b)
    a_runs = [read_sweep(path, COMPARE_REQUIRED) for path in a_files]
    b_runs = [read_sweep(path, COMPARE_REQUIRED) for path in b_files]
    matched, only_a, only_b = compare_rows(a_runs, b_runs)
    if not matched:
        raise ClothbenchError(
            f"{args.a} and {args.b} have no row in common (same backend, mode options, scene, grid, local size)"
        )
    a_rows, b_rows = [r for rows in a_runs for r in rows], [r for rows in b_runs for r in rows]
    console = Console()
    if not console.is_terminal:
        console = Console(width=160)  # a CI log or a pipe: no reason to wrap at 80
    console.print(f"A: {args.a}  ({_machine(a_rows)})")
    console.print(f"B: {args.b}  ({_machine(b_rows)})")
    local = any(m["a"]["local_size"] for m in matched)
    table = Table(title=f"ms per step, B / A (below 1: B is faster), {CONFIDENCE:.0%} interval from the timed chunks")
    cols = ("backend", "mode") + (("local",) if local else ()) + ("n", "A ms", "B ms", "B / A", "interval", "change")
    for col in cols:
        table.add_column(col, justify="left" if col in ("backend", "mode", "change") else "right")
    per_backend: dict[str, list[float]] = {}
    for m in matched:
        ra, rb, ratio = m["a"], m["b"], m["ratio"]
        style = CHANGE_STYLE[m["change"]]
        if ratio is not None:
            per_backend.setdefault(ra["backend"], []).append(ratio)
        shown = f"{ratio:.2f}" if ratio is not None else "n/a"
        interval = f"{m['interval'][0]:.2f}-{m['interval'][1]:.2f}" if m["interval"] else ""
        lead = [ra["backend"], escape(rb["mode"])] + ([ra["local_size"] or "auto"] if local else []) + [ra["grid"]]
        change = f"[{style}]{m['change']}[/{style}]"
        a_ms, b_ms = (_ms(r) if ms is None else f"{ms:.3f}" for r, ms in ((ra, m["a_ms"]), (rb, m["b_ms"])))
        table.add_row(*lead, a_ms, b_ms, f"[{style}]{shown}[/{style}]", interval, change)
    console.print(table)
    for backend, ratios in per_backend.items():
        console.print(f"{backend}: geometric mean B/A {geometric_mean(ratios):.2f} over {len(ratios)} rows")
    everything = [r for rs in per_backend.values() for r in rs]
    if everything:
        console.print(f"all: geometric mean B/A {geometric_mean(everything):.2f} over {len(everything)} rows")
    _print_notes(console, matched, only_a, only_b)
    for m in matched:
        if m["change"] == "inconclusive":
            console.print(
                f"inconclusive: {_row_name(m['a'])}: B/A {m['ratio']:.2f}: {'; '.join(m['doubts'])}", highlight=False
            )
    gate = math.inf if args.fail_above is None else args.fail_above
    failing = [m for m in matched if m["change"] == "slower" and m["ratio"] > gate]
    for m in failing:
        lo, hi = m["interval"]
        console.print(
            f"[red]slower than --fail-above {args.fail_above:g}[/red]: {_row_name(m['a'])}: "
            f"B/A {m['ratio']:.2f} (interval {lo:.2f}-{hi:.2f})",
            highlight=False,
        )
    doubtful = [m for m in matched if m["change"] == "inconclusive"] if args.strict_gate else []
    for m in doubtful:
        console.print(f"[red]inconclusive under --strict-gate[/red]: {_row_name(m['a'])}", highlight=False)
    return 1 if failing or doubtful else 0


def _side(spec: str) -> list[str]:
    """The files of one side of compare: one CSV, or several runs comma-separated."""
    files = [f.strip() for f in spec.split(",")]
    if not all(files):
        raise ClothbenchError(f"compare: {spec!r} names an empty file (runs are comma-separated: A1.csv,A2.csv)")
    return files


def _print_notes(console, matched: list[dict], only_a: int, only_b: int) -> None:
    changes = [m["change"] for m in matched]
    significant = {c: changes.count(c) for c in ("slower", "faster") if c in changes}
    console.print(
        "significant changes: "
        + (", ".join(f"{n} {c}" for c, n in significant.items()) or "none")
        + f" (of {sum(m['interval'] is not None for m in matched)} rows tested)"
    )
    inconclusive = [m for m in matched if m["change"] == "inconclusive"]
    if inconclusive:
        why = {k: sum(any(k in d for d in m["doubts"]) for m in inconclusive) for k in ("busy", "unstable")}
        console.print(
            f"{len(inconclusive)} rows inconclusive ("
            + ", ".join(f"{k}: {n}" for k, n in why.items() if n)
            + "): the machine was busy or the chunks spread too wide in A or B; neither a pass nor a fail "
            "(--strict-gate fails them), measure again on a quiet machine (clothbench machine)"
        )
    untested = changes.count("untested")
    if untested:
        console.print(
            f"{untested} rows untested for significance: no chunk_ms column (a sweep older than it) "
            f"or fewer than {MIN_CHUNKS} timed chunks (--repeat) in A or B"
        )
    not_ok = changes.count("n/a")
    if not_ok:
        console.print(f"{not_ok} matching rows are not ok in A or B (n/a): see their status and note columns")
    if only_a or only_b:
        console.print(f"rows only in A: {only_a}; only in B: {only_b} (not compared)")
    settings = {(m[s]["steps"], m[s]["repeats"], m[s]["dt"]) for m in matched for s in ("a", "b")}
    if len(settings) > 1:
        console.print(
            "note: the files were timed with different --steps/--repeat/--dt: "
            + "; ".join(f"{s} steps x {r} at dt {d}" for s, r, d in sorted(settings))
        )


def _row_name(row: dict) -> str:
    size = f" local {row['local_size']}" if row["local_size"] else ""
    return f"{row['backend']} {row['mode']}{size} {row['scene']} n={row['grid']}"


def _ms(row: dict) -> str:
    return f"{float(row['ms_median']):.3f}" if row["status"] == "ok" else row["status"]


def _machine(rows: list[dict]) -> str:
    def values(col):
        return sorted({r.get(col, "") for r in rows} - {""})

    parts = [", ".join(values("cpu")) or "unknown CPU"]
    if values("git_commit"):
        parts.append(f"commit {', '.join(values('git_commit'))}")
    stamps = values("timestamp")
    if stamps:
        parts.append(stamps[0][:16])
    return "; ".join(parts)
