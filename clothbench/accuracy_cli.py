"""`clothbench accuracy` and `clothbench stability`: error against cost, convergence order,
and the measured stability limit beside the linearised one. Plots are PNG (matplotlib Agg).
The reasoning behind every default is in docs/accuracy.md."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from .backends import resolve_names
from .errors import ClothbenchError

DEFAULT_LEVELS = 5  # 2 dt .. dt/8 around the scene's dt (docs/accuracy.md: why one coarser)
ACCURACY_GRID = 32  # a few minutes for every backend; the orders do not change with n
STABILITY_GRID = 24  # its top frequency is within 1.4 % (omega^2) of the infinite lattice's
PBD_DT0_HZ = 60.0  # PBD's largest default dt is a 60 Hz frame: what it is used at


def register(subparsers) -> None:
    acc = subparsers.add_parser(
        "accuracy", help="error against cost and the convergence order, per backend and mode"
    )
    acc.add_argument("--backends", default="all", help="comma-separated names, or all (default)")
    acc.add_argument("--scene", default="drape", help="drape, sphere or a .toml file (default drape)")
    acc.add_argument("--grid", type=int, default=ACCURACY_GRID, help=f"particles per side (default {ACCURACY_GRID})")
    acc.add_argument("--dts", help="comma-separated time steps (default: twice the scene's dt, halved 4 times)")
    acc.add_argument("--levels", type=int, default=DEFAULT_LEVELS, help="how many dts when --dts is not given")
    acc.add_argument(
        "--time", type=float,
        help="simulated time of the comparison, s (default 0.1 without a collider, 0.2 with one)",
    )
    acc.add_argument("--start", choices=["rest", "second-order"], help="initial x_prev (default: the scene's)")
    acc.add_argument("--damping", type=float, help="override b (N s/m); 0 for undamped Verlet")
    acc.add_argument(
        "--stiffness", type=float, help="override k (N/m); PBD's compliance is 1/k unless the scene sets it"
    )
    acc.add_argument(
        "--solvers", default="verlet",
        help="comma-separated: verlet (mass-spring), pbd (XPBD, docs/pbd.md; --pbd-methods), pbd-jacobi, "
        "pbd-coloured (default verlet)",
    )
    _pbd_arguments(acc)
    acc.add_argument(
        "--pbd-dts",
        help=f"PBD's time steps (default 1/{PBD_DT0_HZ:g} s halved --levels - 1 times: where PBD is used)",
    )
    acc.add_argument(
        "--artefacts", action="store_true",
        help="with pbd: also measure PBD's softness (strain at rest) and damping (energy lost "
        "undamped) against Verlet for 3/10/30/100 iterations and dt 1/60..1/240 (numpy f64); "
        "writes <out>-artefacts.csv",
    )
    acc.add_argument("--out", help="CSV path (default results/accuracy-<scene>.csv); plots beside it")
    acc.set_defaults(func=cmd_accuracy)

    st = subparsers.add_parser(
        "stability", help="largest stable dt per stiffness (bisection) against the linearised bound"
    )
    st.add_argument("--backends", default="all", help="comma-separated names, or all (default)")
    st.add_argument("--stiffness", default="1000,10000,100000", help="comma-separated k values (N/m)")
    st.add_argument(
        "--scenes", default="flat,stretched,crumpled",
        help="flat (the bound's own case), stretched (x1.5, border held), crumpled (squeezed, buckled)",
    )
    st.add_argument("--grid", type=int, default=STABILITY_GRID, help=f"particles per side (default {STABILITY_GRID})")
    st.add_argument("--steps", type=int, default=2000, help="steps a dt must survive (default 2000)")
    st.add_argument("--damping", type=float, default=0.002, help="b (N s/m), default the scenes' 0.002")
    st.add_argument(
        "--solvers", default="verlet",
        help="comma-separated: verlet, pbd (--pbd-methods), pbd-jacobi, pbd-coloured (default verlet); "
        "with PBD, every row also says whether dt = 1/60 s is stable",
    )
    _pbd_arguments(st)
    st.add_argument(
        "--cap", type=float, default=None,
        help="largest dt the PBD bisection tries, s (default 0.1): stable there reads 'stable up to the cap'",
    )
    st.add_argument("--out", help="CSV path (default results/stability.csv); the map beside it")
    st.set_defaults(func=cmd_stability)


def _pbd_arguments(p) -> None:
    p.add_argument(
        "--pbd-methods", default="jacobi,coloured",
        help="PBD formulations to run (default both: they converge to different answers)",
    )
    p.add_argument(
        "--pbd-iterations",
        help="comma-separated PBD iteration counts (default: the scene's, 10), one line each",
    )


def _floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ClothbenchError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ClothbenchError(f"{what} must be positive numbers, got {text!r}")
    return values


SOLVER_SPECS = ("verlet", "pbd", "pbd-jacobi", "pbd-coloured")  # as the sweep's --solvers


def _solvers(text: str) -> tuple[str, ...]:
    specs = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    if not specs or any(s not in SOLVER_SPECS for s in specs):
        raise ClothbenchError(f"--solvers takes {', '.join(SOLVER_SPECS)} (comma-separated), got {text!r}")
    return specs


def _solver_choices(args) -> tuple[tuple[str, ...], tuple[str, ...], tuple[int | None, ...]]:
    """(solvers, PBD methods, PBD iteration counts) from --solvers, --pbd-methods and
    --pbd-iterations. 'pbd' runs --pbd-methods (default both); 'pbd-jacobi' and
    'pbd-coloured' (the sweep's spelling) name one method each."""
    from .scene import PBD_METHODS

    specs = _solvers(args.solvers)
    solvers = tuple(dict.fromkeys(s.partition("-")[0] for s in specs))
    named = [s.partition("-")[2] for s in specs if s.startswith("pbd-")]
    methods = tuple(dict.fromkeys(m.strip() for m in args.pbd_methods.split(",") if m.strip()))
    if not methods or any(m not in PBD_METHODS for m in methods):
        raise ClothbenchError(
            f"--pbd-methods takes {', '.join(PBD_METHODS)} (comma-separated), got {args.pbd_methods!r}"
        )
    if named:
        methods = tuple(dict.fromkeys(named + (list(methods) if "pbd" in specs else [])))
    iterations: tuple[int | None, ...] = (None,)
    if args.pbd_iterations:
        try:
            iterations = tuple(dict.fromkeys(int(v) for v in args.pbd_iterations.split(",") if v.strip()))
        except ValueError:
            iterations = ()
        if not iterations or min(iterations) < 1:
            raise ClothbenchError(f"--pbd-iterations must be whole numbers >= 1, got {args.pbd_iterations!r}")
    return solvers, methods, iterations


def _variants(spec: str, solvers=("verlet",), methods=(None,), iterations=(None,)):
    from .accuracy import backend_variants

    variants, skipped = backend_variants(resolve_names(spec), solvers, methods, iterations)
    for name, reason in skipped:
        print(f"skipped {name}: {reason}")
    if not variants:
        raise ClothbenchError(f"no usable backend among {spec!r} (see clothbench backends)")
    for solver in solvers:
        if not any(v.solver == solver for v in variants):
            print(f"note: no backend among {spec!r} runs the {solver} solver here; its lines are missing")
    return variants


def write_csv(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


# --- accuracy -------------------------------------------------------------------------


def cmd_accuracy(args) -> int:
    from .accuracy import dt_levels, run_accuracy
    from .reports.progress import LazyProgress
    from .scene import load_scene

    scene = load_scene(args.scene)
    changes = {"grid": args.grid}
    if args.start:
        changes["start"] = args.start
    if args.damping is not None:
        changes["damping"] = args.damping
    if args.stiffness is not None:
        if not (math.isfinite(args.stiffness) and args.stiffness > 0):
            raise ClothbenchError(f"--stiffness must be > 0, got {args.stiffness}")
        changes["stiffness"] = args.stiffness
    scene = scene.replace(**changes)
    if args.levels < 2:
        raise ClothbenchError(f"--levels must be >= 2 to fit an order, got {args.levels}")
    solvers, methods, iterations = _solver_choices(args)
    # one level coarser than the scene's dt: float32 rounding swamps the error below ~dt/2
    dts = _floats(args.dts, "--dts") if args.dts else dt_levels(2 * scene.dt, args.levels)
    pbd_dts = _floats(args.pbd_dts, "--pbd-dts") if args.pbd_dts else dt_levels(1 / PBD_DT0_HZ, args.levels)
    time_s = args.time if args.time is not None else (0.2 if scene.spheres else 0.1)
    if not (math.isfinite(time_s) and time_s > 0):
        raise ClothbenchError(f"--time must be > 0, got {args.time}")
    variants = _variants(args.backends, solvers, methods, iterations)
    models = {(v.solver, v.pbd_method, v.iterations) for v in variants} | {("verlet", None, None)}
    total = sum(len(pbd_dts if v.pbd else dts) for v in variants) + 6 * len(models)
    done = 0
    with LazyProgress(total, "accuracy") as progress:

        def note(what: str) -> None:
            nonlocal done
            done += 1
            progress.update(min(done, total), what)

        result = run_accuracy(scene, variants, dts, time_s, on_progress=note, pbd_dts=pbd_dts)

    out = Path(args.out or f"results/accuracy-{scene.name}.csv")
    write_csv(out, [r.as_dict() for r in result.rows])
    speed_png = out.with_name(out.stem + "-speed.png")
    conv_png = out.with_name(out.stem + "-convergence.png")
    plot_speed_vs_error(result, speed_png)
    plot_convergence(result, conv_png)
    _print_accuracy(result, scene, time_s)
    print(f"wrote {out}, {speed_png}, {conv_png}")
    if args.artefacts:
        if "pbd" not in solvers:
            print("--artefacts: skipped (it compares PBD with Verlet: add --solvers verlet,pbd)")
            return 0
        from .accuracy import solver_artefacts

        its = tuple(sorted({3, 10, 30, 100} | {i for i in iterations if i is not None}))
        with LazyProgress(1 + len(methods) * (len(its) + 2), "artefacts") as progress:
            count = 0

            def step(what: str) -> None:
                nonlocal count
                count += 1
                progress.update(count, what)

            rows = solver_artefacts(scene, methods, its, on_progress=step)
        art = out.with_name(out.stem + "-artefacts.csv")
        write_csv(art, [r.as_dict() for r in rows])
        _print_artefacts(rows)
        print(f"wrote {art}")
    return 0


def _print_artefacts(rows) -> None:
    from .accuracy import SETTLE_DAMPING, SETTLE_S, SWING_S

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


def _print_accuracy(result, scene, time_s) -> None:
    from .accuracy import DOMINANCE

    print(
        f"clothbench accuracy: {scene.name} {scene.grid}x{scene.grid}, start={scene.start}, "
        f"k={scene.stiffness:g}, b={scene.damping:g}; errors at t = {time_s:g} s, in metres"
    )
    pbd = any(r.solver == "pbd" for r in result.rows)
    width = max([34] + [len(r.label) + 2 for r in result.rows])
    head = ("backend mode", "dt (s)", "ms/sim s", "disc RMS", "disc max", "impl RMS", "impl max")
    extra = f"{'vs Verlet':>10}" if pbd else ""
    print(f"{head[0]:<{width}}" + "".join(f"{h:>10}" for h in head[1:]) + extra)
    for r in result.rows:
        fit = "*" if r.in_fit else " "
        status = "" if r.status == "ok" else r.status
        vs = f"{r.vs_verlet_rms:>10.3g}" if pbd else ""
        print(
            f"{r.label:<{width}}{r.dt:>10.4g}{r.ms_per_sim_s:>10.4g}{r.disc_rms:>10.3g}{r.disc_max:>10.3g}"
            f"{r.impl_rms:>10.3g}{r.impl_max:>10.3g}{vs}  {fit}{status}"
        )
    print("disc: against the converged float64 reference of the row's own model (its solver, and")
    print("for PBD its method, iterations, substeps: dt -> 0 with those fixed); impl: against float64")
    print("at the same dt" + ("; vs Verlet: RMS against the converged mass-spring (Verlet) answer" if pbd else ""))
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
            print(f"fitted convergence order: {label}: n/a (rounding dominates at {len(result.rows) and sum(1 for r in result.rows if r.label == label) - points} of its dts)")
    if pbd:
        _print_cost_at_error(result.rows)


def cheapest_at(rows, target: float, error: str = "disc_rms"):
    """The row with the lowest cost (ms per simulated second) among those whose `error`
    column is at most `target`; None when no row reaches it."""
    ok = [r for r in rows if r.status == "ok" and getattr(r, error) <= target and r.ms_per_sim_s > 0]
    return min(ok, key=lambda r: r.ms_per_sim_s) if ok else None


def _print_cost_at_error(rows) -> None:
    """Per decade of error, the cheapest run of each solver that reaches it: against its own
    converged model, and (PBD) against the converged mass-spring answer."""
    errors = [r.disc_rms for r in rows if r.status == "ok" and r.disc_rms > 0]
    if not errors:
        return
    lo, hi = math.floor(math.log10(min(errors))), math.ceil(math.log10(max(errors)))
    print("cheapest run reaching an RMS error (ms of compute per simulated second; backend mode, dt):")
    for e in range(hi, lo - 1, -1):
        target = 10.0**e
        cells = []
        for solver, error in (("verlet", "disc_rms"), ("pbd", "disc_rms"), ("pbd", "vs_verlet_rms")):
            best = cheapest_at([r for r in rows if r.solver == solver], target, error)
            name = solver if error == "disc_rms" else "pbd vs Verlet's answer"
            cells.append(
                f"{name} {best.ms_per_sim_s:.3g} ({best.label}, {best.dt:.3g} s)" if best else f"{name} -"
            )
        print(f"  <= {target:.0e} m: " + " | ".join(cells))


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _by_label(rows):
    groups: dict[str, list] = {}
    for r in rows:
        groups.setdefault(r.label, []).append(r)
    return groups


def _style(rows, i: int = 0) -> dict:
    """Verlet: solid lines, round markers; PBD: dashed, square (Jacobi) or diamond
    (coloured) markers, so the two solvers read apart at a glance. Colours from tab20 (20
    distinct; neighbours, e.g. a backend's two modes, are a dark and a light shade)."""
    import matplotlib

    r = rows[0]
    colour = matplotlib.colormaps["tab20"](i % 20)
    if r.solver != "pbd":
        return {"linestyle": "-", "marker": "o", "color": colour}
    return {"linestyle": "--", "marker": "s" if r.pbd_method == "jacobi" else "D", "markersize": 5, "color": colour}


def plot_speed_vs_error(result, path: Path) -> None:
    """Cost (ms per simulated second) against error to the converged reference, log-log; with
    both solvers, a vertical line per PBD model at its converged distance from Verlet's."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10.5, 6))
    for i, (label, rows) in enumerate(_by_label(result.rows).items()):
        ok = [r for r in rows if r.status == "ok" and r.disc_rms > 0]
        if ok:
            ax.loglog([r.disc_rms for r in ok], [r.ms_per_sim_s for r in ok], label=label, **_style(ok, i))
    for i, d in enumerate(result.differences):
        ax.axvline(d.rms, color="grey", lw=1, alpha=0.6, linestyle=(0, (1, 2 + i)))
        ax.annotate(
            f"{d.b.split(' ')[0].split(',')[0]} vs verlet\n(converged models)", (d.rms, 0.98),
            xycoords=("data", "axes fraction"), fontsize=7, alpha=0.7, ha="right", va="top", rotation=90,
        )
    r0 = result.rows[0]
    ax.set_xlabel(f"RMS position error at t = {r0.time_s:g} s vs the converged float64 answer of its own model (m)")
    ax.set_ylabel("cost (ms of compute per simulated second)")
    solvers = " and ".join(dict.fromkeys(r.solver for r in result.rows))
    ax.set_title(
        f"speed against error: {r0.scene} {r0.grid}x{r0.grid}, {solvers}; dt halved along each line", fontsize=10
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _save(fig, path)



def _save(fig, path: Path) -> None:
    """Write a finished figure (its folder made if missing) and free it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)

def plot_convergence(result, path: Path) -> None:
    """Error against dt per backend/mode with its fitted order, and slopes 1 and 2 to read by."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(10.5, 6))
    all_dts = sorted({r.dt for r in result.rows})
    for i, (label, rows) in enumerate(_by_label(result.rows).items()):
        ok = [r for r in rows if r.status == "ok" and r.disc_rms > 0]
        if not ok:
            continue
        order = ok[0].order
        shown = f"order {order:.2f}" if math.isfinite(order) else "order n/a"
        style = _style(ok, i)
        line = ax.loglog([r.dt for r in ok], [r.disc_rms for r in ok], label=f"{label} ({shown})", **style)[0]
        ax.loglog([r.dt for r in ok], [r.impl_rms for r in ok], ":", alpha=0.6, color=line.get_color())
    top = max((r.disc_rms for r in result.rows if r.status == "ok" and r.disc_rms > 0), default=1.0)
    lo, hi = all_dts[0], all_dts[-1]
    for p in (1, 2):
        ax.loglog([lo, hi], [top * (lo / hi) ** p, top], "k--", alpha=0.3, lw=1)
        ax.annotate(f"slope {p}", (lo, top * (lo / hi) ** p), fontsize=8, alpha=0.6)
    unstable = sorted({r.dt for r in result.rows if r.status.startswith("unstable")})
    if unstable:
        ax.annotate(
            f"unstable (not drawn) at dt >= {unstable[0]:.3g} s on " + ", ".join(
                sorted({r.solver for r in result.rows if r.status.startswith("unstable")})
            ),
            (0.02, 0.02), xycoords="axes fraction", fontsize=7,
        )
    r0 = result.rows[0]
    ax.set_xlabel("dt (s)")
    ax.set_ylabel(f"RMS position error at t = {r0.time_s:g} s (m)")
    ax.set_title(
        f"convergence: {r0.scene} {r0.grid}x{r0.grid}, start={r0.start}, b={r0.damping:g}\n"
        "solid (Verlet), dashed (PBD): vs the converged float64 answer of its own model;\n"
        "dotted: vs float64 at the same dt (rounding)",
        fontsize=9,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _save(fig, path)


# --- stability ------------------------------------------------------------------------


def cmd_stability(args) -> int:
    from .accuracy import PBD_CAP, STABILITY_SCENES, measure_stability_limit
    from .reports.progress import LazyProgress

    ks = _floats(args.stiffness, "--stiffness")
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
    solvers, methods, iterations = _solver_choices(args)
    check_60hz = "pbd" in solvers
    variants = _variants(args.backends, solvers, methods, iterations)
    rows = []
    total = len(variants) * len(ks) * len(kinds)
    with LazyProgress(total, "stability") as progress:
        for v in variants:
            for kind in kinds:
                for k in ks:
                    progress.update(len(rows), f"{v.backend} {v.solver} {kind} k={k:g}")
                    try:
                        rows.append(
                            measure_stability_limit(
                                v, kind, k, args.steps, args.grid, args.damping,
                                cap=cap if v.pbd else None, check_60hz=check_60hz,
                            )
                        )
                    except ClothbenchError:
                        raise
                    except Exception as e:  # a broken backend is reported, the others still run
                        print(f"{v.backend} {v.solver} {kind} k={k:g}: error: {type(e).__name__}: {e}")
    if not rows:
        raise ClothbenchError("no stability limit could be measured (every backend failed)")
    out = Path(args.out or "results/stability.csv")
    write_csv(out, [r.as_dict() for r in rows])
    png = out.with_suffix(".png")
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
    if any(r.solver == "pbd" for r in rows):
        caps = sorted({r.cap for r in rows if r.cap})
        print(
            "PBD (XPBD) has no explicit-step limit to predict: its ratio is to Verlet's flat limit; "
            f">= means stable at the cap ({', '.join(f'{c:g}' for c in caps)} s), so the limit is at least that."
        )


def _solver_model(r) -> str:
    return "verlet" if r.solver != "pbd" else f"pbd-{r.pbd_method}/{r.iterations}it"


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
    v_bad = [r for r in rows if r.solver != "pbd" and r.at_60hz and not r.stable_at_60hz]
    p_ok = [r for r in rows if r.solver == "pbd" and r.at_60hz and r.stable_at_60hz]
    v_all = [r for r in rows if r.solver != "pbd" and r.at_60hz]
    p_all = [r for r in rows if r.solver == "pbd" and r.at_60hz]
    if v_all and p_all:
        print(
            f"=> at dt = 1/60 s Verlet explodes in {len(v_bad)} of {len(v_all)} runs and PBD stays "
            f"stable in {len(p_ok)} of {len(p_all)}, at the same stiffness."
        )


def plot_stability_map(rows, path: Path) -> None:
    """Largest stable dt against k: measured per scene and backend/mode, and the bounds; PBD
    as filled markers (at the cap when stable there), with lines at the cap and 1/60 s."""
    from .accuracy import DT_60HZ, STRETCH, dt_limit, gershgorin_omega, omega_max
    from .scene import Scene

    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 5.5))
    ks = sorted({r.stiffness for r in rows})
    kk = [ks[0] / 1.5, ks[-1] * 1.5]
    m = Scene().mass  # every stability scene uses the default particle mass
    beta = 12 * rows[0].damping / m
    ax.loglog(kk, [dt_limit(omega_max(k, m), beta) for k in kk], "k-", lw=1, label="flat lattice 2/omega")
    ax.loglog(kk, [dt_limit(omega_max(k, m, STRETCH), beta) for k in kk], "k-.", lw=1, label=f"lattice at {STRETCH}x stretch")
    ax.loglog(kk, [dt_limit(gershgorin_omega(k, m), beta) for k in kk], "k:", lw=1, label="Gershgorin 24 k/m")
    # one colour per scene, one marker per backend/mode: backends that agree overlap
    colours = {"flat": "tab:blue", "stretched": "tab:orange", "crumpled": "tab:red"}
    verlet = [r for r in rows if r.solver != "pbd"]
    pbd = [r for r in rows if r.solver == "pbd"]
    labels = list(dict.fromkeys(r.label for r in verlet))
    markers = "os^vD<>ph*"
    kinds = list(dict.fromkeys(r.kind for r in rows))
    for kind in kinds:
        for i, label in enumerate(labels):
            rs = [r for r in verlet if r.kind == kind and r.label == label]
            ax.loglog([r.stiffness for r in rs], [r.dt_stable for r in rs], markers[i % len(markers)],
                      color=colours.get(kind, "k"), fillstyle="none", markersize=7, alpha=0.7)
        ax.plot([], [], "o", color=colours.get(kind, "k"), label=f"measured: {kind}")
    for i, label in enumerate(labels):
        ax.plot([], [], markers[i % len(markers)], color="grey", fillstyle="none", label=label)
    if pbd:
        pbd_markers = {"jacobi": "P", "coloured": "X"}
        # scene x method side by side around k, so points that coincide stay visible
        slots = list(dict.fromkeys((r.kind, r.pbd_method) for r in pbd))
        shift = {slot: 1.1 ** (j - (len(slots) - 1) / 2) for j, slot in enumerate(slots)}
        for r in pbd:
            x = r.stiffness * shift[(r.kind, r.pbd_method)]
            ax.loglog([x], [r.dt_stable], pbd_markers.get(r.pbd_method, "*"),
                      color=colours.get(r.kind, "k"), markersize=8, alpha=0.8)
            if r.capped:
                ax.annotate("", (x, r.dt_stable * 1.8), (x, r.dt_stable * 1.1),
                            arrowprops=dict(arrowstyle="->", color=colours.get(r.kind, "k"), alpha=0.6))
        for method, mk in pbd_markers.items():
            if any(r.pbd_method == method for r in pbd):
                its = sorted({r.iterations for r in pbd if r.pbd_method == method})
                ax.plot([], [], mk, color="grey", label=f"PBD {method} ({'/'.join(map(str, its))} it), every backend")
        caps = sorted({r.cap for r in pbd if r.cap})
        for c in caps:
            ax.axhline(c, color="tab:green", lw=1, ls="--", alpha=0.6)
            ax.annotate(f"PBD cap {c:g} s (arrow: stable there, the limit is higher)", (kk[0], c / 1.25),
                        fontsize=7, va="top", ha="left", color="tab:green")
        ax.set_ylim(top=max(caps or [DT_60HZ]) * 3)
    ax.axhline(DT_60HZ, color="grey", lw=1, ls=(0, (4, 4)), alpha=0.7)
    ax.annotate("dt = 1/60 s", (kk[0], DT_60HZ), fontsize=7, va="bottom", color="grey")
    ax.set_xlabel("spring stiffness k (N/m), m = 0.01 kg")
    ax.set_ylabel("largest stable dt (s)")
    ax.set_title(f"stability map: {rows[0].grid}x{rows[0].grid}, {rows[0].steps} steps, b = {rows[0].damping:g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    _save(fig, path)
