"""`clothbench stability`: the largest stable dt per stiffness, by bisection, beside the
linearised bound (analysis/stability.py, analysis/lattice.py), for Verlet and PBD. The map is
drawn by reports/accuracy_plots.py; docs/accuracy.md has the reasoning."""

from __future__ import annotations

import math
from pathlib import Path

from clothbench.cli.args import add_row_args, check_row_args, sigterm_interrupts
from clothbench.cli.accuracy import add_pbd_args, floats, solvers_from_args, variants_for
from clothbench.harness.study_csv import cells
from clothbench.cli.study_files import (
    add_resume_args,
    finish_stability,
    say_interrupted,
    stability_file,
    stability_key,
)
from clothbench.errors import ClothbenchError
from clothbench.variant_names import solver_model
from clothbench.model.solver import ITERATIVE, SOLVER_SPECS

STABILITY_GRID = 24  # its top frequency is within 1.4 % (omega^2) of the infinite lattice's


def register(subparsers) -> None:
    st = subparsers.add_parser(
        "stability", help="largest stable dt per stiffness (bisection) against the linearised bound"
    )
    st.add_argument("--backends", default="all", help="comma-separated names, or all (default)")
    st.add_argument("--stiffness", default="1000,10000,100000", help="comma-separated k values (N/m)")
    st.add_argument(
        "--scenes",
        default="flat,stretched,crumpled",
        help="flat (the bound's own case), stretched (x1.5, border held), crumpled (squeezed, buckled)",
    )
    st.add_argument("--grid", type=int, default=STABILITY_GRID, help=f"particles per side (default {STABILITY_GRID})")
    st.add_argument("--steps", type=int, default=2000, help="steps a dt must survive (default 2000)")
    st.add_argument("--damping", type=float, default=0.002, help="b (N s/m), default the scenes' 0.002")
    st.add_argument(
        "--solvers",
        default="verlet",
        help=f"comma-separated: {', '.join(SOLVER_SPECS)} (pbd: --pbd-methods; vbd: --vbd-iterations; default "
        "verlet); with PBD or VBD, every row also says whether dt = 1/60 s is stable",
    )
    add_pbd_args(st)
    st.add_argument(
        "--cap",
        type=float,
        default=None,
        help="largest dt the PBD bisection tries, s (default 0.1): stable there reads 'stable up to the cap'",
    )
    st.add_argument(
        "--out", help="CSV path (default results/stability.csv; each row written as measured); the map beside it"
    )
    add_resume_args(
        st, "the same as --resume: a case whose bisection failed is not written, so a resume measures it again"
    )
    add_row_args(st, jobs=True)
    st.set_defaults(func=cmd_stability)


def cmd_stability(args) -> int:
    from clothbench.analysis.stability import PBD_CAP, STABILITY_SCENES, measure_stability_limit, stability_scene
    from clothbench.reports.accuracy_plots import plot_stability_map
    from clothbench.progress import LazyProgress
    from clothbench.harness.executor import executor_for, fork_safe
    from clothbench.harness.preflight import check_memory, check_writable
    from clothbench.model.solver import Pbd, Vbd, Verlet

    sigterm_interrupts()
    check_row_args(args)
    ks = floats(args.stiffness, "--stiffness")
    kinds = [s.strip() for s in args.scenes.split(",") if s.strip()]
    for kind in kinds:
        if kind not in STABILITY_SCENES:
            raise ClothbenchError(f"unknown stability scene {kind!r} (known: {', '.join(STABILITY_SCENES)})")
    if args.grid < 8:
        raise ClothbenchError(f"--grid must be >= 8 for a stability scene, got {args.grid}")
    if args.steps < 100:
        raise ClothbenchError(f"--steps must be >= 100, got {args.steps}")
    if not (math.isfinite(args.damping) and args.damping >= 0):
        raise ClothbenchError(f"--damping must be >= 0, got {args.damping}")
    cap = args.cap if args.cap is not None else PBD_CAP
    if not (math.isfinite(cap) and cap > 0):
        raise ClothbenchError(f"--cap must be > 0, got {args.cap}")
    solvers = solvers_from_args(args, Verlet(), Pbd(), Vbd())  # the dt is what is bisected
    check_60hz = any(s.name in ITERATIVE for s in solvers)
    out = Path(args.out or "results/stability.csv")
    png = out.with_suffix(".png")
    for path in (out, png):
        check_writable(path, make_folders=args.out is None)  # before the bisections, not after them
    check_memory([args.grid], ("f64",), jobs=args.jobs)
    for kind in kinds:  # every scene's constants checked (float32 included) before any bisection
        for k in ks:
            stability_scene(kind, k, args.grid, args.damping)
    variants = variants_for(args.backends, solvers)
    cases = [(v, kind, k) for v in variants for kind in kinds for k in ks]
    resume = args.resume or args.retry_failed
    with stability_file(out, cases, args.grid, args.steps, args.damping, cap, resume) as f:
        have = f.keys()
        todo = [c for c in cases if stability_key(*c) not in have]
        measured = {}
        try:
            with (
                LazyProgress(len(todo), "stability") as progress,
                executor_for(args.scheduler, args.jobs, args.row_timeout) as executor,
            ):
                futures = [
                    executor.submit(
                        measure_stability_limit,
                        v,
                        kind,
                        k,
                        args.steps,
                        args.grid,
                        args.damping,
                        cap=cap if v.solver.name in ITERATIVE else None,
                        check_60hz=check_60hz,
                        fork_safe=fork_safe(v.backend, v.solver.name),
                    )
                    for v, kind, k in todo
                ]
                for done, ((v, kind, k), future) in enumerate(zip(todo, futures)):
                    progress.update(done, f"{v.backend} {v.solver.name} {kind} k={k:g}")
                    try:
                        outcome = future.result()
                    except ClothbenchError:
                        raise
                    except Exception as e:  # a broken backend is reported, the others still run
                        print(f"{v.backend} {v.solver.name} {kind} k={k:g}: error: {type(e).__name__}: {e}")
                        continue
                    if outcome.ok:
                        f.append(cells(outcome.value.as_dict()))
                        measured[stability_key(v, kind, k)] = outcome.value
                    else:
                        print(f"{v.backend} {v.solver.name} {kind} k={k:g}: {outcome.status}: {outcome.note}")
        except KeyboardInterrupt:
            say_interrupted(f)
            raise
        rows = finish_stability(f, cases, measured)
    if not rows:
        raise ClothbenchError("no stability limit could be measured (every backend failed)")
    plot_stability_map(rows, png)
    _print_stability(rows)
    if len({_solver_model(r) for r in rows}) > 1 or check_60hz:
        _print_side_by_side(rows)
    print(f"wrote {out}, {png}")
    return 0


def _fmt_dt(r) -> str:
    return f">={r.dt_stable:.4g}" if r.capped else f"{r.dt_stable:.4g}"


def _print_stability(rows) -> None:
    r0 = rows[0]
    print(
        f"clothbench stability: largest dt stable for {r0.steps} steps, {r0.grid}x{r0.grid}, "
        f"m = 0.01 kg, b = {r0.damping:g} N s/m"
    )
    width = max([34] + [len(r.label) + 2 for r in rows])
    sixty = any(r.at_60hz for r in rows)
    print(
        f"{'backend mode':<{width}}{'scene':<11}{'k (N/m)':>9}{'measured':>12}{'predicted':>12}"
        f"{'meas/pred':>11}{'flat':>12}{'Gershgorin':>12}" + ("  dt = 1/60 s" if sixty else "")
    )
    for r in rows:
        pred = f"{r.predicted:.4g}" if r.predicted else "-"
        ratio = f"{r.ratio:.3f}" if r.ratio else f"{'>=' if r.capped else ''}{r.dt_stable / r.flat_predicted:.3f}*"
        at = ("  " + ("stable" if r.stable_at_60hz else "EXPLODES")) if r.at_60hz else ""
        print(
            f"{r.label:<{width}}{r.kind:<11}{r.stiffness:>9g}{_fmt_dt(r):>12}{pred:>12}"
            f"{ratio:>11}{r.flat_predicted:>12.4g}{r.gershgorin:>12.4g}{at}"
        )
    print("dt in seconds. predicted: 2/omega of the infinite lattice (flat: omega^2 = 10.25 k/m;")
    print("stretched: the same lattice at 1.5x rest length, 12.85 k/m), with the lagged-velocity")
    print("damping (omega^2 dt^2 + 2 (12 b/m) dt = 4). * crumpled has no linear prediction: the")
    print("ratio shown is to the flat limit (docs/accuracy.md explains the difference).")
    if any(r.solver in ITERATIVE for r in rows):
        caps = sorted({r.cap for r in rows if r.cap})
        present = [
            name for solver, name in (("pbd", "PBD (XPBD)"), ("vbd", "VBD")) if any(r.solver == solver for r in rows)
        ]
        has, its = ("has", "its") if len(present) == 1 else ("have", "their")
        print(
            f"{' and '.join(present)} {has} no explicit-step limit to predict: {its} ratio is to Verlet's flat limit; "
            f">= means stable at the cap ({', '.join(f'{c:g}' for c in caps)} s), so the limit is at least that."
        )


def _solver_model(r) -> str:
    return solver_model(r.solver if r.solver != "pbd" else f"pbd-{r.pbd_method}", r.iterations)


def _print_side_by_side(rows) -> None:
    """The largest stable dt of each solver per scene and k, next to each other (the
    smallest over the backends and modes; backends agree to the bisection's 0.5 % except on
    the chaotic crumpled scene), and the verdict at dt = 1/60 s on every backend."""
    models = list(dict.fromkeys(_solver_model(r) for r in rows))
    cases = list(dict.fromkeys((r.kind, r.stiffness) for r in rows))
    width = max(16, *(len(m) + 2 for m in models))
    print()
    print("largest stable dt (s), side by side (the smallest over backends and modes):")
    print(f"{'scene':<11}{'k (N/m)':>9}" + "".join(f"{m:>{width}}" for m in models))
    for kind, k in cases:
        cells = []
        for m in models:
            rs = [r for r in rows if r.kind == kind and r.stiffness == k and _solver_model(r) == m]
            if not rs:
                cells.append("-")
                continue
            worst = min(rs, key=lambda r: r.dt_stable)
            cells.append(_fmt_dt(worst))
        print(f"{kind:<11}{k:>9g}" + "".join(f"{c:>{width}}" for c in cells))
    if not any(r.at_60hz for r in rows):
        return
    print()
    print("at dt = 1/60 s (16.7 ms), the same start and steps:")
    for kind, k in cases:
        parts = []
        for m in models:
            rs = [r for r in rows if r.kind == kind and r.stiffness == k and _solver_model(r) == m and r.at_60hz]
            if not rs:
                continue
            stable = sum(1 for r in rs if r.stable_at_60hz)
            if stable == len(rs):
                verdict = "stable"
            elif stable == 0:
                verdict = "EXPLODES"
            else:
                verdict = f"stable on {stable}, explodes on {len(rs) - stable}"
            parts.append(f"{m} {verdict} ({len(rs)} backend/modes)")
        print(f"  {kind} k={k:g}: " + "; ".join(parts))
    v_bad = [r for r in rows if r.solver == "verlet" and r.at_60hz and not r.stable_at_60hz]
    v_all = [r for r in rows if r.solver == "verlet" and r.at_60hz]
    for solver in ITERATIVE:
        p_ok = [r for r in rows if r.solver == solver and r.at_60hz and r.stable_at_60hz]
        p_all = [r for r in rows if r.solver == solver and r.at_60hz]
        if v_all and p_all:
            print(
                f"=> at dt = 1/60 s Verlet explodes in {len(v_bad)} of {len(v_all)} runs and {solver.upper()} stays "
                f"stable in {len(p_ok)} of {len(p_all)}, at the same stiffness."
            )
