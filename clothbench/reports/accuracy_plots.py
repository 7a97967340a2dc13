"""The plots of `clothbench accuracy` and `clothbench stability` (analysis/), drawn on
matplotlib Figures without pyplot, as reports/plots.py draws the sweep's.

1. speed_vs_error: cost (ms per simulated second) against the error to the converged
   reference of each line's own model, dt halved along each line.
2. convergence: error against dt per backend, mode and solver, with the fitted order.
3. stability_map: the largest stable dt against k, measured and linearised.

Verlet lines are solid with round markers; PBD dashed, square (Jacobi) or diamond (coloured).
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib
from matplotlib.figure import Figure

from clothbench.analysis.lattice import damping_rate, dt_limit, gershgorin_omega, omega_max
from clothbench.analysis.stability import DT_60HZ, STRETCH
from clothbench.scene import Scene


def _figure(size: tuple[float, float]) -> tuple[Figure, object]:
    fig = Figure(figsize=size)
    return fig, fig.add_subplot()


def _save(fig: Figure, path: Path) -> None:
    """Write a finished figure, its folder made if missing."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def _by_label(rows):
    groups: dict[str, list] = {}
    for r in rows:
        groups.setdefault(r.label, []).append(r)
    return groups


def _style(rows, i: int = 0) -> dict:
    """Verlet: solid lines, round markers; PBD: dashed, square (Jacobi) or diamond
    (coloured) markers, so the two solvers read apart at a glance. Colours from tab20 (20
    distinct; neighbours, e.g. a backend's two modes, are a dark and a light shade)."""
    r = rows[0]
    colour = matplotlib.colormaps["tab20"](i % 20)
    if r.solver != "pbd":
        return {"linestyle": "-", "marker": "o", "color": colour}
    return {"linestyle": "--", "marker": "s" if r.pbd_method == "jacobi" else "D", "markersize": 5, "color": colour}


def plot_speed_vs_error(result, path: Path) -> None:
    """Cost (ms per simulated second) against error to the converged reference, log-log; with
    both solvers, a vertical line per PBD model at its converged distance from Verlet's."""
    fig, ax = _figure((10.5, 6))
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


def plot_convergence(result, path: Path) -> None:
    """Error against dt per backend/mode with its fitted order, and slopes 1 and 2 to read by."""
    fig, ax = _figure((10.5, 6))
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


def plot_stability_map(rows, path: Path) -> None:
    """Largest stable dt against k: measured per scene and backend/mode, and the bounds; PBD
    as filled markers (at the cap when stable there), with lines at the cap and 1/60 s."""
    fig, ax = _figure((10, 5.5))
    ks = sorted({r.stiffness for r in rows})
    kk = [ks[0] / 1.5, ks[-1] * 1.5]
    m = Scene().mass  # every stability scene uses the default particle mass
    beta = damping_rate(Scene(damping=rows[0].damping))
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


__all__ = ["plot_speed_vs_error", "plot_convergence", "plot_stability_map"]
