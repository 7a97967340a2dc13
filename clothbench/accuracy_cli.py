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
    st.add_argument("--out", help="CSV path (default results/stability.csv); the map beside it")
    st.set_defaults(func=cmd_stability)


def _floats(text: str, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ClothbenchError(f"{what} must be comma-separated numbers, got {text!r}") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise ClothbenchError(f"{what} must be positive numbers, got {text!r}")
    return values


def _variants(spec: str):
    from .accuracy import backend_variants

    variants, skipped = backend_variants(resolve_names(spec))
    for name, reason in skipped:
        print(f"skipped {name}: {reason}")
    if not variants:
        raise ClothbenchError(f"no usable backend among {spec!r} (see clothbench backends)")
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
    scene = scene.replace(**changes)
    if args.levels < 2:
        raise ClothbenchError(f"--levels must be >= 2 to fit an order, got {args.levels}")
    # one level coarser than the scene's dt: float32 rounding swamps the error below ~dt/2
    dts = _floats(args.dts, "--dts") if args.dts else dt_levels(2 * scene.dt, args.levels)
    time_s = args.time if args.time is not None else (0.2 if scene.spheres else 0.1)
    if not (math.isfinite(time_s) and time_s > 0):
        raise ClothbenchError(f"--time must be > 0, got {args.time}")
    variants = _variants(args.backends)
    total = len(variants) * len(dts) + 6
    done = 0
    with LazyProgress(total, "accuracy") as progress:

        def note(what: str) -> None:
            nonlocal done
            done += 1
            progress.update(min(done, total), what)

        result = run_accuracy(scene, variants, dts, time_s, on_progress=note)

    out = Path(args.out or f"results/accuracy-{scene.name}.csv")
    write_csv(out, [r.as_dict() for r in result.rows])
    speed_png = out.with_name(out.stem + "-speed.png")
    conv_png = out.with_name(out.stem + "-convergence.png")
    plot_speed_vs_error(result, speed_png)
    plot_convergence(result, conv_png)
    _print_accuracy(result, scene, time_s)
    print(f"wrote {out}, {speed_png}, {conv_png}")
    return 0


def _print_accuracy(result, scene, time_s) -> None:
    from .accuracy import DOMINANCE

    ref = result.reference
    print(
        f"clothbench accuracy: {scene.name} {scene.grid}x{scene.grid}, start={scene.start}, "
        f"b={scene.damping:g}; errors at t = {time_s:g} s, in metres"
    )
    head = ("backend mode", "dt (s)", "ms/sim s", "disc RMS", "disc max", "impl RMS", "impl max", "")
    print(f"{head[0]:<34}{head[1]:>10}{head[2]:>10}{head[3]:>10}{head[4]:>10}{head[5]:>10}{head[6]:>10}  {head[7]}")
    for r in result.rows:
        fit = "*" if r.in_fit else " "
        status = "" if r.status == "ok" else r.status
        print(
            f"{r.label:<34}{r.dt:>10.4g}{r.ms_per_sim_s:>10.4g}{r.disc_rms:>10.3g}{r.disc_max:>10.3g}"
            f"{r.impl_rms:>10.3g}{r.impl_max:>10.3g}  {fit}{status}"
        )
    print("disc: against the converged float64 reference; impl: against float64 at the same dt;")
    print(f"* = in the order fit (discretisation at least {DOMINANCE:g}x the implementation error)")
    state = "converged" if ref.converged else "NOT converged (errors below its uncertainty mean nothing)"
    print(
        f"reference: float64 down to dt {ref.dt:.3g} s, Richardson-extrapolated (order "
        f"{ref.order:.2f}), {state}; last change {ref.uncertainty:.2g} m"
    )
    for label, (order, points) in result.orders().items():
        if math.isfinite(order):
            print(f"fitted convergence order: {label}: {order:.2f} (over {points} dts)")
        else:
            print(f"fitted convergence order: {label}: n/a (rounding dominates at {len(result.rows) and sum(1 for r in result.rows if r.label == label) - points} of its dts)")


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


def plot_speed_vs_error(result, path: Path) -> None:
    """Cost (ms per simulated second) against error to the converged reference, log-log."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 5))
    for label, rows in _by_label(result.rows).items():
        ok = [r for r in rows if r.status == "ok" and r.disc_rms > 0]
        if ok:
            ax.loglog([r.disc_rms for r in ok], [r.ms_per_sim_s for r in ok], "o-", label=label)
    r0 = result.rows[0]
    ax.set_xlabel(f"RMS position error at t = {r0.time_s:g} s vs converged float64 (m)")
    ax.set_ylabel("cost (ms of compute per simulated second)")
    ax.set_title(f"speed against error: {r0.scene} {r0.grid}x{r0.grid}, dt halved along each line")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_convergence(result, path: Path) -> None:
    """Error against dt per backend/mode with its fitted order, and slopes 1 and 2 to read by."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 5))
    all_dts = sorted({r.dt for r in result.rows})
    for label, rows in _by_label(result.rows).items():
        ok = [r for r in rows if r.status == "ok" and r.disc_rms > 0]
        if not ok:
            continue
        order = ok[0].order
        shown = f"order {order:.2f}" if math.isfinite(order) else "order n/a"
        ax.loglog([r.dt for r in ok], [r.disc_rms for r in ok], "o-", label=f"{label} ({shown})")
        ax.loglog([r.dt for r in ok], [r.impl_rms for r in ok], ":", alpha=0.6)
    top = max((r.disc_rms for r in result.rows if r.status == "ok" and r.disc_rms > 0), default=1.0)
    lo, hi = all_dts[0], all_dts[-1]
    for p in (1, 2):
        ax.loglog([lo, hi], [top * (lo / hi) ** p, top], "k--", alpha=0.3, lw=1)
        ax.annotate(f"slope {p}", (lo, top * (lo / hi) ** p), fontsize=8, alpha=0.6)
    r0 = result.rows[0]
    ax.set_xlabel("dt (s)")
    ax.set_ylabel(f"RMS position error at t = {r0.time_s:g} s (m)")
    ax.set_title(
        f"convergence: {r0.scene} {r0.grid}x{r0.grid}, start={r0.start}, b={r0.damping:g}\n"
        "solid: vs converged float64; dotted: vs float64 at the same dt",
        fontsize=9,
    )
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- stability ------------------------------------------------------------------------


def cmd_stability(args) -> int:
    from .accuracy import STABILITY_SCENES, measure_stability_limit
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
    variants = _variants(args.backends)
    rows = []
    total = len(variants) * len(ks) * len(kinds)
    with LazyProgress(total, "stability") as progress:
        for v in variants:
            for kind in kinds:
                for k in ks:
                    progress.update(len(rows), f"{v.label} {kind} k={k:g}")
                    try:
                        rows.append(measure_stability_limit(v, kind, k, args.steps, args.grid, args.damping))
                    except ClothbenchError:
                        raise
                    except Exception as e:  # a broken backend is reported, the others still run
                        print(f"{v.label} {kind} k={k:g}: error: {type(e).__name__}: {e}")
    if not rows:
        raise ClothbenchError("no stability limit could be measured (every backend failed)")
    out = Path(args.out or "results/stability.csv")
    write_csv(out, [r.as_dict() for r in rows])
    png = out.with_suffix(".png")
    plot_stability_map(rows, png)
    _print_stability(rows)
    print(f"wrote {out}, {png}")
    return 0


def _print_stability(rows) -> None:
    r0 = rows[0]
    print(
        f"clothbench stability: largest dt stable for {r0.steps} steps, {r0.grid}x{r0.grid}, "
        f"m = 0.01 kg, b = {r0.damping:g} N s/m"
    )
    print(
        f"{'backend mode':<34}{'scene':<11}{'k (N/m)':>9}{'measured':>12}{'predicted':>12}"
        f"{'meas/pred':>11}{'flat':>12}{'Gershgorin':>12}"
    )
    for r in rows:
        pred = f"{r.predicted:.4g}" if r.predicted else "-"
        ratio = f"{r.ratio:.3f}" if r.ratio else f"{r.dt_stable / r.flat_predicted:.3f}*"
        print(
            f"{r.label:<34}{r.kind:<11}{r.stiffness:>9g}{r.dt_stable:>12.4g}{pred:>12}"
            f"{ratio:>11}{r.flat_predicted:>12.4g}{r.gershgorin:>12.4g}"
        )
    print("dt in seconds. predicted: 2/omega of the infinite lattice (flat: omega^2 = 10.25 k/m;")
    print("stretched: the same lattice at 1.5x rest length, 12.85 k/m), with the lagged-velocity")
    print("damping (omega^2 dt^2 + 2 (12 b/m) dt = 4). * crumpled has no linear prediction: the")
    print("ratio shown is to the flat limit (docs/accuracy.md explains the difference).")


def plot_stability_map(rows, path: Path) -> None:
    """Largest stable dt against k: measured per scene and backend/mode, and the bounds."""
    from .accuracy import STRETCH, dt_limit, gershgorin_omega, omega_max
    from .scene import Scene

    plt = _plt()
    fig, ax = plt.subplots(figsize=(10, 5))
    ks = sorted({r.stiffness for r in rows})
    kk = [ks[0] / 1.5, ks[-1] * 1.5]
    m = Scene().mass  # every stability scene uses the default particle mass
    beta = 12 * rows[0].damping / m
    ax.loglog(kk, [dt_limit(omega_max(k, m), beta) for k in kk], "k-", lw=1, label="flat lattice 2/omega")
    ax.loglog(kk, [dt_limit(omega_max(k, m, STRETCH), beta) for k in kk], "k-.", lw=1, label=f"lattice at {STRETCH}x stretch")
    ax.loglog(kk, [dt_limit(gershgorin_omega(k, m), beta) for k in kk], "k:", lw=1, label="Gershgorin 24 k/m")
    # one colour per scene, one marker per backend/mode: backends that agree overlap
    colours = {"flat": "tab:blue", "stretched": "tab:orange", "crumpled": "tab:red"}
    labels = list(dict.fromkeys(r.label for r in rows))
    markers = "os^vD<>ph*"
    for kind in dict.fromkeys(r.kind for r in rows):
        for i, label in enumerate(labels):
            rs = [r for r in rows if r.kind == kind and r.label == label]
            ax.loglog([r.stiffness for r in rs], [r.dt_stable for r in rs], markers[i % len(markers)],
                      color=colours.get(kind, "k"), fillstyle="none", markersize=7, alpha=0.7)
        ax.plot([], [], "o", color=colours.get(kind, "k"), label=f"measured: {kind}")
    for i, label in enumerate(labels):
        ax.plot([], [], markers[i % len(markers)], color="grey", fillstyle="none", label=label)
    ax.set_xlabel("spring stiffness k (N/m), m = 0.01 kg")
    ax.set_ylabel("largest stable dt (s)")
    ax.set_title(f"stability map: {rows[0].grid}x{rows[0].grid}, {rows[0].steps} steps, b = {rows[0].damping:g}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
