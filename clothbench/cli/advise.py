"""`clothbench advise`: the cheapest configuration on this machine whose error at T stays under E.

Reads an accuracy run (`--csv`, default results/accuracy-<scene>.csv) or makes one here
(`--run`: the run `clothbench accuracy` makes), and prints the cheapest measured
configuration (backend, mode, solver, dt) whose discretisation error at the run's simulated
time stays under --max-error, with its cost, the `clothbench run` command that runs it, the
runners-up, and what would have to give when none does. The choice is analysis/advise.py's.

Exit status: 0 a configuration qualifies; 1 none does (the output says what would have to
give); 2 bad input (one line on stderr, before any work).
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
import tempfile
from pathlib import Path

from clothbench.errors import ClothbenchError
from clothbench.variant_names import iterations_display, model_display

NONE_QUALIFIES = 1  # the exit status when nothing measured stays under E


def register(subparsers) -> None:
    from clothbench.analysis.advise import DEFAULT_METRIC, METRICS
    from clothbench.cli.accuracy import ACCURACY_GRID, add_pbd_args

    p = subparsers.add_parser(
        "advise", help="the cheapest measured configuration whose error at T stays under --max-error"
    )
    p.add_argument("--scene", default="drape", help="drape, sphere or a .toml file (default drape)")
    p.add_argument("--max-error", type=float, required=True, metavar="E", help="the error bound E, in metres")
    p.add_argument(
        "--metric",
        choices=tuple(METRICS),
        default=DEFAULT_METRIC,
        help="max (default: every particle within E) or rms per-particle distance to the converged "
        "float64 answer (the CSV's disc_max / disc_rms)",
    )
    p.add_argument("--time", type=float, help="simulated time T, s (default: the accuracy run's)")
    p.add_argument("--csv", help="an accuracy run's CSV (default results/accuracy-<scene>.csv)")
    p.add_argument("--backends", default="all", help="comma-separated names to choose among (default all)")
    p.add_argument(
        "--run",
        action="store_true",
        help="measure here instead of reading a CSV: the run `clothbench accuracy` makes (about 2 minutes "
        "on a 2-core CPU at the default grid, every backend, Verlet and PBD)",
    )
    p.add_argument("--grid", type=int, help=f"with --run: particles per side (default {ACCURACY_GRID})")
    p.add_argument("--solvers", default="verlet,pbd", help="with --run: as accuracy's (default verlet,pbd)")
    add_pbd_args(p)
    p.add_argument("--out", help="with --run: keep the measured CSV (and its plots) here")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.set_defaults(func=cmd_advise)


def _checked_args(args):
    """(setup, the backends to choose among or None for all), or one line on what is wrong."""
    from clothbench.backends import resolve_names
    from clothbench.scene import load_setup

    setup = load_setup(args.scene)
    if not (math.isfinite(args.max_error) and args.max_error > 0):
        raise ClothbenchError(f"--max-error must be a positive number of metres, got {args.max_error}")
    if args.time is not None and not (math.isfinite(args.time) and args.time > 0):
        raise ClothbenchError(f"--time must be > 0, got {args.time}")
    backends = None if args.backends.strip() == "all" else set(resolve_names(args.backends))
    if args.run and args.csv:
        raise ClothbenchError("give --csv (read a run) or --run (measure one here), not both")
    if not args.run:
        extra = [f for f, v in (("--grid", args.grid), ("--out", args.out)) if v is not None]
        if extra:
            raise ClothbenchError(f"{extra[0]} is for --run (a CSV has its own)")
    return setup, backends


def default_csv(scene: str) -> Path:
    """results/accuracy-<scene>.csv here, else the one committed beside the package (an
    editable install or a checkout, found from the package as its kernels are), so README's
    advise line answers from any folder; the path here where neither exists."""
    import clothbench

    name = f"accuracy-{scene}.csv"
    here = Path("results") / name
    committed = Path(clothbench.__file__).resolve().parents[1] / "results" / name
    return committed if not here.exists() and committed.is_file() else here


def _read_run(args, setup):
    from clothbench.analysis.advise import check_matches, read_accuracy_csv

    path = Path(args.csv) if args.csv else default_csv(setup.scene.name)
    if not args.csv and not path.exists():
        raise ClothbenchError(
            f"no accuracy run of {setup.scene.name} at {path} (nor in the repository's results/): "
            "give --csv FILE, or --run to measure one here"
        )
    run = read_accuracy_csv(path)
    check_matches(run, setup)
    if args.time is not None and not math.isclose(args.time, run.time_s, rel_tol=1e-9):
        raise ClothbenchError(
            f"{path} measured errors at t = {run.time_s:g} s, so it cannot answer --time {args.time:g}; "
            f"add --run to measure at {args.time:g} s here (the accuracy run, a few minutes)"
        )
    return run


def _measure_here(args, setup, out: Path):
    """The run `clothbench accuracy` makes, through its own parser and command, its table
    on stderr so stdout stays the advice."""
    from clothbench.analysis.advise import check_matches, measured_here, read_accuracy_csv
    from clothbench.cli import accuracy
    from clothbench.cli.args import Parser

    argv = ["accuracy", "--scene", args.scene, "--backends", args.backends, "--solvers", args.solvers,
            "--pbd-methods", args.pbd_methods, "--out", str(out)]  # fmt: skip
    argv += ["--grid", str(args.grid)] if args.grid is not None else []
    argv += ["--time", repr(args.time)] if args.time is not None else []
    if args.pbd_iterations:
        argv += ["--pbd-iterations", ",".join(map(str, args.pbd_iterations))]
    parser = Parser(prog="clothbench")
    accuracy.register(parser.add_subparsers(dest="command", parser_class=Parser))
    acc_args = parser.parse_args(argv)
    from clothbench.harness.preflight import check_writable

    check_writable(out, "--out")  # before saying it measures
    if out.exists() and out.stat().st_size > 0:
        raise ClothbenchError(f"--out {out} already exists: choose another path, or remove it")
    print(f"measuring here: clothbench {' '.join(argv)} (a few minutes at 32x32)", file=sys.stderr)
    with contextlib.redirect_stdout(sys.stderr):
        acc_args.func(acc_args)
    run = measured_here(read_accuracy_csv(out).rows)
    check_matches(run, setup)
    return run


def cmd_advise(args) -> int:
    from clothbench.analysis.advise import advise

    setup, backends = _checked_args(args)
    if not args.run:
        run = _read_run(args, setup)
    else:  # the measured CSV is kept only where --out says
        with tempfile.TemporaryDirectory(prefix="clothbench-advise-") as tmp:
            out = Path(args.out) if args.out else Path(tmp) / f"accuracy-{setup.scene.name}.csv"
            run = _measure_here(args, setup, out)
    advice = advise(run, setup, args.max_error, args.metric, backends)
    if args.json:
        print(json.dumps(_no_nan(advice.as_dict(args.scene) | {"exit_code": _status(advice)})))
    else:
        print_advice(advice, args.scene, setup.scene.stiffness)
    return _status(advice)


def _status(advice) -> int:
    return 0 if advice.choice else NONE_QUALIFIES


def _no_nan(value):
    """NaN and infinity as null: JSON has neither."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _no_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_no_nan(v) for v in value]
    return value


def fmt_dt(dt: float) -> str:
    """'0.001 s', or '1/480 s' for a frame-rate step that has no short decimal."""
    hz = 1 / dt
    if float(f"{dt:.4g}") != dt and abs(hz - round(hz)) < 1e-6 * hz:
        return f"1/{round(hz)} s"
    return f"{dt:.4g} s"


def solver_text(row) -> str:
    """'Verlet', 'PBD jacobi 10 it x2 substeps', 'VBD 10 it'."""
    if row.solver == "verlet":
        return model_display(row.solver, None)
    sub = f" x{row.substeps} substeps" if row.substeps and row.substeps > 1 else ""
    return f"{model_display(row.solver, row.pbd_method)} {iterations_display(row.iterations)}{sub}"


def _line(p, metric: str, width: int, against=None) -> str:
    ratio = f"x{p.cost / against.cost:<6.3g}" if against else " " * 7
    return (
        f"{p.cost:>8.4g} ms/s {ratio} {p.config.label:<{width}} {solver_text(p.row):<19} "
        f"dt {fmt_dt(p.row.dt):<11}{metric} {p.error:.2e} m"
    )


def _renamed(p) -> str:
    return "" if p.config.label == p.row.label else f" (measured as {p.row.label!r})"


def _machine_line(run) -> str:
    from clothbench.environment import cpu_model

    here = cpu_model()
    if run.source == "measured here":
        return f"costs: measured now on this machine ({here})"
    if run.cpu is None:
        return f"costs: from {run.source}, which does not say which machine measured them (this one: {here})"
    if run.cpu == here:
        return f"costs: measured on {run.cpu} ({run.cpu_from}), the same CPU model as this machine"
    return (
        f"costs: measured on {run.cpu} ({run.cpu_from}), NOT this machine ({here}): they are that "
        f"machine's; --run measures here"
    )


def _ceil2(x: float) -> float:
    """x rounded up to two significant digits."""
    unit = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.ceil(x / unit - 1e-9) * unit


def print_advice(advice, scene_arg: str, stiffness: float) -> None:
    from clothbench.analysis.advise import METRICS

    run, m, E = advice.run, advice.metric, advice.max_error
    print(
        f"clothbench advise: {run.scene} {run.grid}x{run.grid}, error at t = {run.time_s:g} s under "
        f"E = {E:g} m; error = {m} per-particle distance to the converged float64 answer of the "
        f"configuration's own model ({METRICS[m]}), plus that reference's uncertainty"
    )
    source = "the accuracy run just made here" if run.source == "measured here" else run.source
    print(f"from {source} ({len(run.rows)} runs); {_machine_line(run)}")
    if run.stiffness is None and run.source != "measured here":
        print(f"  (the CSV does not record k: taken to be the scene's, {stiffness:g} N/m)")
    c = advice.choice
    shown = [p for p in (c, *advice.runners_up) if p] + [
        p for g in advice.by_model + advice.by_backend for p in (g.cheapest, g.closest) if p
    ]
    width = max([30] + [len(p.config.label) for p in shown])
    print()
    if c is None:
        _print_none(advice, scene_arg)
    else:
        r = c.row
        print(
            f"choice: {c.config.label}{_renamed(c)}, {solver_text(r)}, dt {fmt_dt(r.dt)} ({r.steps} steps to t = {r.time_s:g} s)"
        )
        print(f"  cost: {c.cost:.4g} ms of compute per simulated second ({r.ms_per_step:.4g} ms a step) on {r.device}")
        print(
            f"  error at t = {r.time_s:g} s: max {r.disc_max:.2e} m, RMS {r.disc_rms:.2e} m "
            f"(reference uncertainty {c.uncertainty:.2g} m)"
        )
        if r.solver != "verlet" and math.isfinite(r.vs_verlet_max):
            print(
                f"  against the mass-spring (Verlet) answer: max {r.vs_verlet_max:.2e} m, RMS {r.vs_verlet_rms:.2e} m"
            )
        if r.solver == "vbd" and math.isfinite(r.vs_exact_max):
            print(f"  against the exact implicit step: max {r.vs_exact_max:.2e} m, RMS {r.vs_exact_rms:.2e} m")
        print(f"  run it: {' '.join(c.config.run_args(scene_arg))}")
        if advice.runners_up:
            print("runners-up, the next cheapest under E (x: cost against the choice's):")
            for p in advice.runners_up:
                print(f"  {_line(p, m, width, c)}")
    for title, groups in (("solver", advice.by_model), ("backend", advice.by_backend)):
        if groups:
            print(f"cheapest of each other {title}:" if c else f"smallest error of each {title}:")
        for g in groups:
            if c is None:
                print(f"  {_line(g.closest, m, width)}")
            elif g.cheapest:
                print(f"  {_line(g.cheapest, m, width, c)}")
            else:
                print(f"  {_line(g.closest, m, width)}  (its smallest error: none under E)")
    for label, why in advice.left_out:
        print(f"left out: {label}: {why}")
    if c is not None:
        print("costs on a shared machine move by up to 2x between runs (docs/accuracy.md): a runner-up")
        print("within that of the choice is as good a choice")


def _print_none(advice, scene_arg: str) -> None:
    run, m, E = advice.run, advice.metric, advice.max_error
    print(f"nothing measured stays under E = {E:g} m ({m} error at t = {run.time_s:g} s). What would have to give:")
    best = advice.closest
    if best is None:
        print("  nothing measured can run here (see left out)")
        return
    print(
        f"  E: the smallest error measured is {best.error:.3g} m ({best.config.label}, {solver_text(best.row)}, "
        f"dt {fmt_dt(best.row.dt)}, {best.cost:.4g} ms/s): --max-error {_ceil2(best.bound):.2g} is met"
    )
    cheapest = advice.cheapest
    print(
        f"  or the other end: the cheapest configuration measured, {cheapest.config.label}, {solver_text(cheapest.row)}, "
        f"dt {fmt_dt(cheapest.row.dt)}, {cheapest.cost:.4g} ms/s, meets --max-error {_ceil2(cheapest.bound):.2g}"
    )
    if best.uncertainty >= E:
        print(f"  E is under the reference's own uncertainty ({best.uncertainty:.2g} m): no run can show it")
        return
    for p in advice.predictions[:3]:
        row = p.pick.row
        dts = "--pbd-dts" if row.solver != "verlet" else "--dts"
        spec = {
            "pbd": f"pbd-{row.pbd_method} --pbd-iterations {row.iterations}",
            "vbd": f"vbd --vbd-iterations {row.iterations}",
        }.get(row.solver, "verlet")
        print(
            f"  dt: {p.pick.config.label}, {solver_text(row)} at dt {p.dt:.4g} s ({p.steps} steps) is predicted "
            f"from its order {row.order:.2f} (not measured) to reach E, at ~{p.cost:.4g} ms/s"
        )
        if row.solver != "verlet" and math.isfinite(row.vs_verlet_max):
            print(
                f"      (E against its own model; at its finest dt it was {row.vs_verlet_max:.2e} m from the mass-spring answer)"
            )
        print(
            f"      measure it: clothbench accuracy --scene {scene_arg} --grid {run.grid} --time {run.time_s:g} "
            f"--backends {row.backend} --solvers {spec} {dts} {p.dt!r}"
        )
    if not advice.predictions:
        print("  dt: no measured line was still converging at its finest dt (float32 rounding or the")
        print("      reference's uncertainty dominates there): a smaller dt would not help")
