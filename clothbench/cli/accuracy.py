"""`clothbench accuracy`: error against cost and the convergence order, per backend, mode and
solver (analysis/convergence.py), and with --artefacts what PBD changes against Verlet
(analysis/artefacts.py). The reasoning behind every default is in docs/accuracy.md; the
plots are drawn by reports/accuracy_plots.py. The solver and variant arguments here are
shared with `clothbench stability` (cli/stability.py)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from clothbench.cli.args import add_row_args, check_row_args, int_list, sigterm_interrupts, solver_specs
from clothbench.cli.study_files import (
    accuracy_file,
    accuracy_key,
    add_resume_args,
    early_cells,
    finish_accuracy,
    say_interrupted,
)
from clothbench.errors import ClothbenchError
from clothbench.model.solver import ITERATIVE, SOLVER_SPECS

DEFAULT_LEVELS = 5  # 2 dt .. dt/8 around the scene's dt (docs/accuracy.md: why one coarser)
ACCURACY_GRID = 32  # a few minutes for every backend; the orders do not change with n
PBD_DT0_HZ = 60.0  # PBD's largest default dt is a 60 Hz frame: what it is used at


def register(subparsers) -> None:
    acc = subparsers.add_parser("accuracy", help="error against cost and the convergence order, per backend and mode")
    acc.add_argument("--backends", default="all", help="comma-separated names, or all (default)")
    acc.add_argument("--scene", default="drape", help="drape, sphere or a .toml file (default drape)")
    acc.add_argument("--grid", type=int, default=ACCURACY_GRID, help=f"particles per side (default {ACCURACY_GRID})")
    acc.add_argument("--dts", help="comma-separated time steps (default: twice the scene's dt, halved 4 times)")
    acc.add_argument("--levels", type=int, default=DEFAULT_LEVELS, help="how many dts when --dts is not given")
    acc.add_argument(
        "--time",
        type=float,
        help="simulated time of the comparison, s (default 0.1 without a collider, 0.2 with one)",
    )
    acc.add_argument("--start", choices=["rest", "second-order"], help="initial x_prev (default: the scene's)")
    acc.add_argument("--damping", type=float, help="override b (N s/m); 0 for undamped Verlet")
    acc.add_argument(
        "--stiffness", type=float, help="override k (N/m); PBD's compliance is 1/k unless the scene sets it"
    )
    acc.add_argument(
        "--solvers",
        default="verlet",
        help=f"comma-separated: {', '.join(SOLVER_SPECS)}: verlet (mass-spring), pbd (XPBD, docs/pbd.md; "
        "--pbd-methods), vbd (implicit Euler, docs/vbd.md; --vbd-iterations) (default verlet)",
    )
    add_pbd_args(acc)
    acc.add_argument(
        "--pbd-dts",
        help=f"PBD's and VBD's time steps (default 1/{PBD_DT0_HZ:g} s halved --levels - 1 times: where they are used)",
    )
    acc.add_argument(
        "--no-exact",
        action="store_true",
        help="VBD rows without vs_exact_rms/max (left empty): the exact implicit step they compare with "
        "is a sparse direct solve at every Newton iteration of every step, minutes a step from about "
        "128² (results/vbd-study/README.md, (c))",
    )
    acc.add_argument(
        "--artefacts",
        action="store_true",
        help="with pbd: also measure PBD's softness (strain at rest) and damping (energy lost "
        "undamped) against Verlet for 3/10/30/100 iterations and dt 1/60..1/240 (numpy f64); "
        "writes <out>-artefacts.csv",
    )
    acc.add_argument(
        "--out", help="CSV path (default results/accuracy-<scene>.csv; each row written as measured); plots beside it"
    )
    add_resume_args(acc, "resume, and measure again the rows the file holds as error, crashed or timeout")
    add_row_args(acc, jobs=True)
    acc.set_defaults(func=cmd_accuracy)


def add_pbd_args(p) -> None:
    """--pbd-methods and --pbd-iterations: which PBD lines --solvers pbd stands for."""
    p.add_argument(
        "--pbd-methods",
        default="jacobi,coloured",
        help="PBD formulations to run (default both: they meet on a sheet nearly at rest or with substeps, "
        "1.7e-5 m RMS after 20 steps of 4 substeps, and part as it swings within a step, 2e-4 m with one "
        'substep: docs/pbd.md, "What Jacobi and Gauss-Seidel converge to")',
    )
    p.add_argument(
        "--pbd-iterations",
        type=int_list("--pbd-iterations", 1),
        help="comma-separated PBD iteration counts (default: the scene's, 10), one line each",
    )
    p.add_argument(
        "--vbd-iterations",
        type=int_list("--vbd-iterations", 1),
        help="comma-separated VBD sweep counts (default: the scene's [vbd], 10), one line each: its "
        "convergence against iterations",
    )


def floats(text: str, what: str) -> list[float]:
    """'1e-3,5e-4' -> [0.001, 0.0005]: positive finite numbers, or one line saying not."""
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ClothbenchError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ClothbenchError(f"{what} must be positive numbers, got {text!r}")
    return values


def solvers_from_args(args, base, pbd, vbd=None) -> list:
    """The solvers --solvers, --pbd-methods and --pbd-iterations name, with `base`'s dt and
    start and the other settings of `pbd` (the scene file's [pbd]). 'pbd' runs --pbd-methods
    (default both); 'pbd-jacobi' and 'pbd-coloured' (the sweep's spelling) name one method
    each; each PBD method runs every --pbd-iterations count (default pbd's), and 'vbd' every
    --vbd-iterations count (default `vbd`'s: the scene file's [vbd])."""
    from clothbench.model.solver import PBD_METHODS, solver_for_spec

    specs = solver_specs(args.solvers)
    methods = tuple(dict.fromkeys(m.strip() for m in args.pbd_methods.split(",") if m.strip()))
    if not methods or any(m not in PBD_METHODS for m in methods):
        raise ClothbenchError(
            f"--pbd-methods takes {', '.join(PBD_METHODS)} (comma-separated), got {args.pbd_methods!r}"
        )
    named = [s.partition("-")[2] for s in specs if s.startswith("pbd-")]
    if named:
        methods = tuple(dict.fromkeys(named + (list(methods) if "pbd" in specs else [])))
    iterations = args.pbd_iterations or [pbd.iterations]
    solvers = []
    for kind in dict.fromkeys(s.partition("-")[0] for s in specs):
        if kind == "verlet":
            solvers.append(solver_for_spec("verlet", base, pbd))
        elif kind == "vbd":
            one = solver_for_spec("vbd", base, pbd, vbd)
            solvers += [one.replace(iterations=it) for it in getattr(args, "vbd_iterations", None) or [one.iterations]]
        else:
            solvers += [
                solver_for_spec(f"pbd-{m}", base, pbd).replace(iterations=it) for m in methods for it in iterations
            ]
    return solvers


def variants_for(spec: str, solvers: list):
    """plan_variants of the --backends `spec` and `solvers`, each skipped backend said."""
    from clothbench.backends import resolve_names
    from clothbench.harness.plan import plan_variants

    variants, skipped = plan_variants(resolve_names(spec), solvers)
    for name, reason in skipped:
        print(f"skipped {name}: {reason}")
    if not variants:
        raise ClothbenchError(f"no usable backend among {spec!r} (see clothbench backends)")
    for kind in dict.fromkeys(s.name for s in solvers):
        if not any(v.solver.name == kind for v in variants):
            print(f"note: no backend among {spec!r} runs the {kind} solver here; its lines are missing")
    return variants


def write_csv(path: Path, rows: list[dict]) -> None:
    """The whole file at once, by a rename: an interrupt leaves the old file or the new one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial")
    with open(partial, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    partial.replace(path)


def cmd_accuracy(args) -> int:
    from clothbench.analysis.convergence import dt_levels, run_accuracy, steps_for
    from clothbench.variant_names import model_name
    from clothbench.reports.accuracy_plots import plot_convergence, plot_speed_vs_error, plot_vbd_iterations
    from clothbench.progress import LazyProgress
    from clothbench.harness.executor import executor_for
    from clothbench.harness.preflight import check_memory, check_writable
    from clothbench.model.scene import check_float32_step, load_setup

    sigterm_interrupts()
    check_row_args(args)
    setup = load_setup(args.scene).replace(grid=args.grid)
    changes = {}
    if args.damping is not None:
        changes["damping"] = args.damping
    if args.stiffness is not None:
        if not (math.isfinite(args.stiffness) and args.stiffness > 0):
            raise ClothbenchError(f"--stiffness must be > 0, got {args.stiffness}")
        changes["stiffness"] = args.stiffness
    scene = setup.scene.replace(**changes)
    start = {"start": args.start} if args.start else {}
    base, pbd = setup.solver.replace(**start), setup.pbd.replace(**start)
    if args.levels < 2:
        raise ClothbenchError(f"--levels must be >= 2 to fit an order, got {args.levels}")
    solvers = solvers_from_args(args, base, pbd, setup.vbd.replace(**start))
    if args.no_exact and not any(s.name == "vbd" for s in solvers):
        raise ClothbenchError("--no-exact leaves out VBD rows' distance to the exact step: add vbd to --solvers")
    # one level coarser than the scene's dt: float32 rounding swamps the error below ~dt/2
    dts = floats(args.dts, "--dts") if args.dts else dt_levels(2 * base.dt, args.levels)
    pbd_dts = floats(args.pbd_dts, "--pbd-dts") if args.pbd_dts else dt_levels(1 / PBD_DT0_HZ, args.levels)
    time_s = args.time if args.time is not None else (0.2 if scene.spheres else 0.1)
    if not (math.isfinite(time_s) and time_s > 0):
        raise ClothbenchError(f"--time must be > 0, got {args.time}")
    for solver in solvers:
        for dt in pbd_dts if solver.name in ITERATIVE else dts:
            check_float32_step(scene, solver.replace(dt=dt))
    out = Path(args.out or f"results/accuracy-{scene.name}.csv")
    outputs = [out, out.with_name(out.stem + "-speed.png"), out.with_name(out.stem + "-convergence.png")]
    if any(s.name == "vbd" for s in solvers):
        outputs.append(out.with_name(out.stem + "-vbd-iterations.png"))
    for path in outputs + ([out.with_name(out.stem + "-artefacts.csv")] if args.artefacts else []):
        check_writable(path, make_folders=args.out is None)  # before the run, not after it; results/ made
    check_memory([scene.grid], ("f64",), jobs=args.jobs)
    variants = variants_for(args.backends, solvers)
    levels = lambda v: sorted(pbd_dts if v.solver.name in ITERATIVE else dts, reverse=True)  # noqa: E731
    planned = [(v, v.solver.replace(dt=dt)) for v in variants for dt in levels(v)]
    for _, solver in planned:
        steps_for(time_s, solver.dt)  # a bad --time refused before the file is touched
    with accuracy_file(out, planned, scene, time_s, base.start, pbd.start, args.resume, args.retry_failed) as f:
        have = f.keys()
        models = {model_name(v.solver) for v in variants} | {"verlet"}
        total = sum(1 for v, s in planned if accuracy_key(v, s) not in have) + 6 * len(models)
        done = 0
        try:
            with LazyProgress(total, "accuracy") as progress:

                def note(what: str) -> None:
                    nonlocal done
                    done += 1
                    progress.update(min(done, total), what)

                with executor_for(args.scheduler, args.jobs, args.row_timeout) as executor:
                    result = run_accuracy(
                        scene,
                        variants,
                        dts,
                        time_s,
                        on_progress=note,
                        pbd_dts=pbd_dts,
                        executor=executor,
                        skip=lambda v, s: accuracy_key(v, s) in have,
                        on_row=lambda row: f.append(early_cells(row)),
                        exact=not args.no_exact,
                    )
        except KeyboardInterrupt:
            say_interrupted(f)
            raise
        result.rows = finish_accuracy(f, planned, result.rows)

    speed_png, conv_png = outputs[1], outputs[2]
    plot_speed_vs_error(result, speed_png)
    plot_convergence(result, conv_png)
    written = [out, speed_png, conv_png]
    if len(outputs) > 3 and plot_vbd_iterations(result, outputs[3]):  # VBD with two or more sweep counts
        written.append(outputs[3])
    _print_accuracy(result, scene, base.start, time_s)
    print(f"wrote {', '.join(map(str, written))}")
    if args.artefacts:
        methods = tuple(dict.fromkeys(s.method for s in solvers if s.name == "pbd"))
        if not methods:
            print("--artefacts: skipped (it compares PBD with Verlet: add --solvers verlet,pbd)")
            return 0
        from clothbench.analysis.artefacts import ITERATIONS, solver_artefacts
        from clothbench.model.solver import solver_for_spec

        its = tuple(sorted(set(ITERATIONS) | set(args.pbd_iterations or ())))
        with LazyProgress(1 + len(methods) * (len(its) + 2), "artefacts") as progress:
            count = 0

            def step(what: str) -> None:
                nonlocal count
                count += 1
                progress.update(count, what)

            rows = solver_artefacts(scene, solver_for_spec("pbd", base, pbd), methods, its, on_progress=step)
        art = out.with_name(out.stem + "-artefacts.csv")
        write_csv(art, [r.as_dict() for r in rows])
        _print_artefacts(rows)
        print(f"wrote {art}")
    return 0


def _print_artefacts(rows) -> None:
    from clothbench.analysis.artefacts import SETTLE_DAMPING, SETTLE_S, SWING_S

    r0 = rows[0]
    print()
    print(
        f"what PBD changes (numpy float64, {r0.scene} {r0.grid}x{r0.grid}): strain of the cloth at rest "
        f"(b = {SETTLE_DAMPING:g}, after {SETTLE_S:g} s), and energy change in {SWING_S:g} s undamped (% of M g L)"
    )
    width = max(len(r.model) for r in rows) + 2
    print(f"{'model':<{width}}{'dt (s)':>10}{'strain':>10}{'x Verlet':>10}{'energy':>10}{'ms/sim s':>10}")
    for r in rows:
        energy = f"{100 * r.energy_change:+.1f}%" if r.strain_ratio < 1.5 else "(n/a)"
        print(
            f"{r.model:<{width}}{r.dt:>10.4g}{r.hanging_strain:>10.4g}{r.strain_ratio:>10.2f}{energy:>10}"
            f"{r.ms_per_sim_s:>10.4g}"
        )
    print("x Verlet > 1: a softer cloth (too few iterations, or Jacobi's own softer model);")
    print("energy < 0: numerical damping. (n/a): over-stretched by 1.5x or more, so its k-spring energy")
    print("is no damping measure (the CSV has the number).")


def _print_accuracy(result, scene, start, time_s) -> None:
    from clothbench.analysis.convergence import DOMINANCE

    print(
        f"clothbench accuracy: {scene.name} {scene.grid}x{scene.grid}, start={start}, "
        f"k={scene.stiffness:g}, b={scene.damping:g}; errors at t = {time_s:g} s, in metres"
    )
    pbd = any(r.solver in ITERATIVE for r in result.rows)
    vbd = any(r.solver == "vbd" for r in result.rows)
    width = max([34] + [len(r.label) + 2 for r in result.rows])
    head = ("backend mode", "dt (s)", "ms/sim s", "disc RMS", "disc max", "impl RMS", "impl max")
    extra = (f"{'vs Verlet':>10}" if pbd else "") + (f"{'vs exact':>10}" if vbd else "")
    print(f"{head[0]:<{width}}" + "".join(f"{h:>10}" for h in head[1:]) + extra)
    for r in result.rows:
        fit = "*" if r.in_fit else " "
        status = "" if r.status == "ok" else r.status
        vs = (f"{r.vs_verlet_rms:>10.3g}" if pbd else "") + (f"{r.vs_exact_rms:>10.3g}" if vbd else "")
        print(
            f"{r.label:<{width}}{r.dt:>10.4g}{r.ms_per_sim_s:>10.4g}{r.disc_rms:>10.3g}{r.disc_max:>10.3g}"
            f"{r.impl_rms:>10.3g}{r.impl_max:>10.3g}{vs}  {fit}{status}"
        )
    print("disc: against the converged float64 reference of the row's own model (its solver, and")
    print("for PBD its method, iterations, substeps: dt -> 0 with those fixed); impl: against float64")
    print("at the same dt" + ("; vs Verlet: RMS against the converged mass-spring (Verlet) answer" if pbd else ""))
    if vbd:
        print("vs exact (VBD): RMS against the exact implicit-Euler step at the same dt (docs/vbd.md)")
    print(f"* = in the order fit (discretisation at least {DOMINANCE:g}x the implementation error)")
    for name, ref in result.references.items():
        state = "converged" if ref.converged else "NOT converged (errors below its uncertainty mean nothing)"
        strain, kinetic = result.ref_bulk.get(name, (float("nan"), float("nan")))
        print(
            f"reference {name}: float64 down to dt {ref.dt:.3g} s, Richardson-extrapolated (order "
            f"{ref.order:.2f}), {state}; last change {ref.uncertainty:.2g} m; "
            f"mean strain {strain:.3g}, kinetic {kinetic:.4g} J"
        )
    for d in result.differences:
        sure = "" if d.converged else " (a reference did not converge: take it as indicative)"
        print(
            f"converged models differ at t = {time_s:g} s: {d.a} vs {d.b}: RMS {d.rms:.3g} m, "
            f"max {d.max:.3g} m (reference uncertainty {d.uncertainty:.2g} m){sure}"
        )
    for label, (order, points) in result.orders().items():
        if math.isfinite(order):
            print(f"fitted convergence order: {label}: {order:.2f} (over {points} dts)")
        else:
            print(
                f"fitted convergence order: {label}: n/a (rounding dominates at {len(result.rows) and sum(1 for r in result.rows if r.label == label) - points} of its dts)"
            )
    if pbd:
        _print_cost_at_error(result.rows)


def _print_cost_at_error(rows) -> None:
    """Per decade of error, the cheapest run of each solver that reaches it: against its own
    converged model, and (PBD) against the converged mass-spring answer."""
    from clothbench.analysis.convergence import cheapest_at

    errors = [r.disc_rms for r in rows if r.status == "ok" and r.disc_rms > 0]
    if not errors:
        return
    lo, hi = math.floor(math.log10(min(errors))), math.ceil(math.log10(max(errors)))
    print("cheapest run reaching an RMS error (ms of compute per simulated second; backend mode, dt):")
    for e in range(hi, lo - 1, -1):
        target = 10.0**e
        cells = []
        solvers = [s for s in ITERATIVE if any(r.solver == s for r in rows)]
        for solver, error in (
            ("verlet", "disc_rms"),
            *((s, e) for s in solvers for e in ("disc_rms", "vs_verlet_rms")),
        ):
            best = cheapest_at([r for r in rows if r.solver == solver], target, error)
            name = solver if error == "disc_rms" else f"{solver} vs Verlet's answer"
            cells.append(f"{name} {best.ms_per_sim_s:.3g} ({best.label}, {best.dt:.3g} s)" if best else f"{name} -")
        print(f"  <= {target:.0e} m: " + " | ".join(cells))
