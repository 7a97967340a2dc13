"""`clothbench sweep`: time every usable backend over grid sizes into a CSV, row by row."""

from __future__ import annotations

import os
import sys

from clothbench.cli.args import (
    add_device_args,
    add_documented_command,
    add_row_args,
    check_row_args,
    choice_list,
    int_list,
    sigterm_interrupts,
    solver_specs,
)
from clothbench.model.solver import SOLVER_SPECS

DEFAULT_GRIDS = "32,64,128,256,512,1024,2048"
DEFAULT_ROW_BUDGET = 15.0  # seconds of timed run a row may take before it runs fewer steps

EPILOG = """\
One CSV row per (backend, mode, grid, local size), appended and flushed to the disk as
soon as it is measured: an interrupted sweep keeps every finished row, and --resume
measures only the rows the file lacks. Each row: build and warm up, then R timed chunks
of S steps (uploads and readbacks outside the clock, except in per-step transfer modes),
then the final state against the numpy float64 run of the same scene and S*R steps.
Backends that cannot run here, or cannot take the scene (a mesh or a motion they lack), are
listed once as skipped, with the reason. A scene with meshes or motion adds dimensions:
--mesh-collision naive,accelerated (a row per algorithm a backend has), --mesh-triangles
(each built-in shape subdivided to the level nearest each count) and --motion on,off (the
scene as written, and with every motion stopped: the cost of motion); a scene with a
[self_collision] table adds --self-collision on,off (the scene with its pass, and the same
scene without the table: the cost of the pass; refused for a scene without one). Each row runs
in a worker process: one that crashes (a signal, an abort, out of memory) is written as
crashed, one past --row-timeout as timeout, and the sweep goes on. Rows already in the
file are kept whatever their status; --retry-failed measures failed, crashed and timeout
rows again. Ctrl-C or SIGTERM keeps every finished row and exits 130.
`clothbench sweep --columns` says what every column means."""


def register(subparsers) -> None:
    from clothbench.backends.base import MESH_COLLISIONS
    from clothbench.harness.plan import MOTION_CHOICES, SELF_COLLISION_CHOICES

    p = add_documented_command(
        subparsers,
        "sweep",
        "time every usable backend over grid sizes into a CSV (rows kept as measured)",
        __doc__,
        EPILOG,
    )
    p.add_argument(
        "--backends",
        default="all",
        help="comma-separated backend names, or all (default); unusable ones are skipped with the reason",
    )
    p.add_argument(
        "--grids",
        type=int_list("--grids", 3),
        default=int_list("--grids", 3)(DEFAULT_GRIDS),
        help=f"particles per side, comma-separated (default {DEFAULT_GRIDS})",
    )
    p.add_argument("--steps", type=int, default=50, help="steps per timed chunk, S (default 50)")
    p.add_argument("--repeat", type=int, default=10, help="timed chunks per row, R (default 10)")
    p.add_argument("--scene", default="sphere", help="built-in scene name or a .toml file (default sphere)")
    p.add_argument(
        "--row-budget",
        type=float,
        default=DEFAULT_ROW_BUDGET,
        metavar="SECONDS",
        help="timed run a row may take: a row whose warm-up step says it would take longer runs fewer, "
        f"shorter chunks (at least 3), recorded in its budget_s, steps, repeats and note (default {DEFAULT_ROW_BUDGET:g})",
    )
    p.add_argument("--dt", type=float, help="time step (s); default: the scene's")
    _add_dimension(
        p,
        "--local-sizes",
        int_list,
        1,
        "also time these work-group / block sizes on backends that have one, e.g. 16,32,64,128",
    )
    add_device_args(p)
    p.add_argument(
        "--generic",
        nargs="?",
        const="yes",
        default="no",
        choices=["no", "yes", "both"],
        help="time the generic kernel (one for every scene) instead of the specialised one; "
        "'both' times each and writes the specialised speed-up on the generic row",
    )
    p.add_argument(
        "--solvers",
        default="verlet",
        help=f"comma-separated: {', '.join(SOLVER_SPECS)}: verlet (mass-spring), pbd (docs/pbd.md, the scene's "
        "method), vbd (implicit Euler, docs/vbd.md) (default verlet)",
    )
    _add_dimension(
        p,
        "--mesh-collision",
        choice_list,
        MESH_COLLISIONS,
        "scenes with meshes: the mesh algorithms to time, a row each where a backend has it "
        "(naive, accelerated; default: each backend's own)",
    )
    _add_dimension(
        p,
        "--mesh-triangles",
        int_list,
        1,
        "scenes with built-in mesh shapes: set each shape's subdivisions to the level nearest each count, "
        "e.g. 20,320,5120,20480 (icosphere 20*4^s, box 12*4^s, torus 256*4^s), a row each",
    )
    _add_dimension(
        p,
        "--motion",
        choice_list,
        MOTION_CHOICES,
        "scenes with motion: on (as the file says), off (every collider fixed where it is placed, attached "
        "pins fixed where they start), or on,off: a row each, the cost of motion",
    )
    _add_dimension(
        p,
        "--self-collision",
        choice_list,
        SELF_COLLISION_CHOICES,
        "scenes with a [self_collision] table (twist, fold, pile): on (with the pass), off (the same scene "
        "without the table), or on,off: a row each, the cost of the pass; refused for a scene without the table",
    )
    p.add_argument("--out", default="sweep.csv", help="the CSV to write (default sweep.csv)")
    p.add_argument(
        "--json",
        metavar="FILE",
        help="also write every row of --out to FILE in Google Benchmark's JSON format (clothbench's "
        "fields beside GB's; no cpu_time), rewritten atomically after each row",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="add only the rows --out lacks (after an interruption); a file written before a column "
        "was added (e.g. chunk_ms) cannot be resumed: sweep into a new --out",
    )
    p.add_argument(
        "--retry-failed",
        action="store_true",
        help="resume, and measure again the rows the file holds as failed, crashed or timeout",
    )
    p.add_argument(
        "--no-bound",
        dest="bound",
        action="store_false",
        help="do not measure the machine's limits before the first row (1-5 s: a STREAM run over 1.5 GiB and "
        "the arithmetic rates, docs/bounds.md); bound_ms and the columns beside it stay empty",
    )
    add_row_args(p)
    p.add_argument("--columns", action="store_true", help="print what every CSV column means, and exit")
    p.set_defaults(func=cmd_sweep)


def _add_dimension(p, option: str, parse, values, help: str) -> None:
    """An option that adds a dimension to the sweep: a comma-separated list checked by
    parse(option, values), a row for each; not given, no dimension (the empty list)."""
    p.add_argument(option, type=parse(option, values), default=[], help=help)


def cmd_sweep(args) -> int:
    from clothbench.backends import BackendOptions, resolve_names
    from clothbench.harness.executor import SCHEDULER_ENV, executor_for
    from clothbench.harness.sweep import SweepSettings, run_sweep
    from clothbench.harness.sweep_csv import COLUMN_DOCS, KEY_COLUMNS
    from clothbench.progress import LazyProgress
    from clothbench.model.scene import load_setup

    if args.columns:
        from clothbench.backends import precision_backends

        width = max(map(len, COLUMN_DOCS))
        f64 = ", ".join(precision_backends("f64"))  # from the backends' Capabilities, not a list here
        for name, doc in COLUMN_DOCS.items():
            print(f"{name:<{width}}  {doc.replace('{f64_backends}', f64)}")
        print(f"\none row per key: {', '.join(KEY_COLUMNS)}")
        return 0
    sigterm_interrupts()
    check_row_args(args)
    json_path = _check_json_path(args.json, args.out) if args.json else None
    from clothbench.harness.preflight import check_float32_motion, check_memory

    names = resolve_names(args.backends)
    setup = load_setup(args.scene).replace(dt=args.dt)
    check_float32_motion(setup.scene, setup.solver)  # every sweep has float32 rows
    check_memory(args.grids, ("f32", "f64"))
    scene = setup.scene
    settings = SweepSettings(
        setup=setup,
        grids=args.grids,
        steps=args.steps,
        repeats=args.repeat,
        base=BackendOptions(device=args.device, gl=args.gl, retune=args.retune),
        local_sizes=tuple(args.local_sizes),
        solvers=solver_specs(args.solvers),
        generic=args.generic,
        row_timeout=args.row_timeout,
        row_budget=args.row_budget,
        mesh_collisions=tuple(args.mesh_collision),
        mesh_triangles=tuple(args.mesh_triangles),
        motion=tuple(args.motion),
        self_collision=tuple(args.self_collision),
        bounds=args.bound,
    )
    for note in settings.notes:
        _note(note)
    bar: LazyProgress | None = None
    state: list = []  # the sweep's progress, once it has started

    json_context: dict = {}  # the machine as the sweep starts, said in every rewrite of --json

    def write_json() -> None:
        if json_path is not None:
            from clothbench.reports.benchmark_json import context, write_benchmark_json

            if not json_context:
                about = {"scene": scene.name, "steps": args.steps, "repeats": args.repeat, "dt": setup.solver.dt}
                json_context.update(context(args.out, about))
            write_benchmark_json(json_path, state[0].rows, json_context)

    def on_start(progress) -> None:
        nonlocal bar
        state.append(progress)
        write_json()  # the rows already in the file (none in a new sweep)
        for name, reason in progress.plan.skipped:
            _note(f"skipped {name}: {reason}")
        if progress.dropped_bytes:
            _note(f"dropped a partial last line ({progress.dropped_bytes} bytes) left by an interrupted write")
        if progress.earlier_commits:
            _note(f"rows already in {args.out} were measured at commit {', '.join(sorted(progress.earlier_commits))}")
        backends = sorted({r.backend for r in progress.todo}, key=[r.backend for r in progress.plan.rows].index)
        variants = [sv.label for sv, _, _ in settings.scene_variants if sv.label]
        shapes = f" ({'; '.join(variants)})" if len(variants) > 1 else ""
        already = f" ({progress.already} already in the file)" if progress.already else ""
        _note(
            f"sweep: {len(progress.todo)} rows to measure{already}: {', '.join(backends) or 'none'} "
            f"on {scene.name}{shapes}, grids {','.join(map(str, args.grids))}, {args.repeat} chunks x {args.steps} steps "
            f"-> {args.out}"
        )
        if progress.fitness is not None:  # rows measured here
            _note(machine_verdict(progress.fitness))
        bar = LazyProgress(max(1, len(progress.todo) * args.steps * args.repeat), "sweep")

    def on_step(done: int, description: str) -> None:
        if bar is not None:
            bar.update(done, description)

    executor = None
    if args.scheduler or os.environ.get(SCHEDULER_ENV):
        executor = executor_for(args.scheduler, timeout=args.row_timeout)
    try:
        progress = run_sweep(
            names,
            settings,
            args.out,
            args.resume or args.retry_failed,
            on_start,
            on_step,
            lambda row: write_json(),
            args.retry_failed,
            executor,
        )
    except KeyboardInterrupt:
        if bar is not None:
            bar.close()
        if state:
            p = state[0]
            _note(
                f"{p.already + len(p.measured)} rows are in {args.out}; "
                "run the same command with --resume to measure the rest"
            )
        raise
    finally:
        if bar is not None:
            bar.close()
        if executor is not None:
            executor.shutdown()

    if progress.measured:
        print_rows(progress.measured, title=f"clothbench sweep: {args.out}")
    if progress.machine is not None:
        _note(f"machine limits (the bound_ms column, docs/bounds.md): {progress.machine.what()}")
    elif progress.machine_note:
        _note(f"no machine bound measured: {progress.machine_note}")
    elif not args.bound and progress.measured:
        _note("no machine bound measured (--no-bound): bound_ms and the columns beside it are empty")
    bad = [r for r in progress.measured if r["status"] != "ok"]
    total = progress.already + len(progress.measured)
    _note(
        f"{len(progress.measured)} rows measured, {total} in {args.out}"
        + (f"; {len(bad)} not ok (see the status and note columns)" if bad else "")
        + (f"; {progress.reference_runs} float64 reference runs beside the rows" if progress.reference_runs else "")
        + (f"; Google Benchmark JSON in {json_path}" if json_path else "")
    )
    return 0


def _check_json_path(path: str, csv_path: str):
    """--json's file, checked writable and not the CSV itself, before anything is measured."""
    from pathlib import Path

    from clothbench.errors import ClothbenchError
    from clothbench.reports.benchmark_json import check_writable

    if Path(path).resolve() == Path(csv_path).resolve():
        raise ClothbenchError(f"--json {path} is the --out CSV: name another file")
    return check_writable(path)


def print_rows(rows: list[dict[str, str]], title: str) -> None:
    """The measured rows as a terminal table (time with its spread, error, status), then the
    reason for every row that is not ok, each distinct reason once."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console()
    if not console.is_terminal:
        console = Console(width=160)  # a log file or a pipe: no reason to wrap at 80
    local = any(r["local_size"] for r in rows)
    # the scene's mesh size and motion, where a row has them (sweep --mesh-triangles, --motion)
    shape = {
        c: head
        for c, head in (("mesh_triangles", "triangles"), ("motion", "motion"), ("self_collision", "self-collision"))
        if any(r.get(c) for r in rows)
    }
    table = Table(title=title)
    heads = ("backend", "mode") + (("local",) if local else ()) + tuple(shape.values())
    for col in heads + ("n", "ms/step", "min-max", "RMS err (m)", "status"):
        table.add_column(col, justify="left" if col in ("backend", "mode", "status") else "right")
    from clothbench.harness.noise import row_doubts

    reasons: dict[tuple[str, str], list[str]] = {}
    doubtful = 0
    for r in rows:
        if r["status"] == "ok":
            cells = [f"{float(r['ms_median']):.3f}", f"{float(r['ms_min']):.3f}-{float(r['ms_max']):.3f}"]
            # the mark of a figure that may not hold: busy, unstable (harness/noise.py)
            marks = [d.split(" (")[0] for d in row_doubts(r)]
            doubtful += bool(marks)
            status = f"[yellow]ok, {', '.join(marks)}[/yellow]" if marks else "ok"
            cells += [f"{float(r['err_rms_m']):.2e}" if r["err_rms_m"] else "", status]
        else:
            cells = ["", "", "", f"[red]{r['status']}[/red]"]
            reasons.setdefault((r["status"], r["note"]), []).append(f"{r['backend']} n={r['grid']}")
        lead = [r["backend"], escape(r["mode"])] + ([r["local_size"] or "auto"] if local else [])
        lead += [r.get(c, "") for c in shape] + [r["grid"]]
        table.add_row(*lead, *cells)
    console.print(table)
    if doubtful:
        console.print(
            f"[yellow]{doubtful} rows may not hold[/yellow]: measured while the machine was busy, or their chunks "
            "spread over 10 % of the median (the note column says which); measure them again on a quiet machine "
            "(clothbench machine)",
            highlight=False,
        )
    for (status, note), where in reasons.items():
        places = ", ".join(dict.fromkeys(where))
        console.print(f"[red]{status}[/red] ({len(where)} rows: {escape(places)}): {escape(note)}", highlight=False)


def machine_verdict(f) -> str:
    """One line on whether this machine is fit to benchmark now (`clothbench machine` says more),
    from the quarter of a second's watch of its load the sweep made before its first row."""
    if f.fit is False:
        return f"machine: NOT fit to benchmark now: {'; '.join(map(str, f.problems))} (clothbench machine)"
    return f"machine: {f.verdict}"


def _note(text: str) -> None:
    print(text, file=sys.stderr, flush=True)
