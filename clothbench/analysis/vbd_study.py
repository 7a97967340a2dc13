"""Issue 33's VBD studies read from their committed CSVs (results/vbd-study/, made by
tools/vbd-study): one markdown table per goal, with the verdict each row supports, so that
results/vbd-study/README.md and tests/test_vbd_study.py say the same thing from the same file.

Rows are the CSVs' dicts (strings), as csv.DictReader gives them.
"""

from __future__ import annotations

import math

EXACT_GOAL_M = 1e-6  # goal (a): VBD f64 within this of the exact implicit-Euler step (RMS)
SPEEDUP_GOAL = 5.0  # goal (d): clothbench's fastest VBD at least this many times newton's


def _f(row: dict, key: str) -> float:
    value = row.get(key, "")
    return float(value) if value not in ("", None) else float("nan")


def _dt_name(dt: float) -> str:
    return f"1/{1 / dt:.4g}"


def iterations_table(rows: list[dict]) -> str:
    """Goal (a): the float64 VBD rows' RMS distance to the exact implicit-Euler step, by sweep
    count (columns) and dt (rows)."""
    vbd = [r for r in rows if r["solver"] == "vbd" and r["status"] == "ok" and "f64" in r["mode"]]
    its = sorted({int(r["iterations"]) for r in vbd})
    dts = sorted({_f(r, "dt") for r in vbd}, reverse=True)
    lines = [
        "| dt (s) | " + " | ".join(f"{i} sweeps" for i in its) + " |",
        "| --- | " + " | ".join("---" for _ in its) + " |",
    ]
    for dt in dts:
        cells = []
        for i in its:
            got = [r for r in vbd if _f(r, "dt") == dt and int(r["iterations"]) == i]
            cells.append(f"{_f(got[0], 'vs_exact_rms'):.2g}" if got else "-")
        lines.append(f"| {_dt_name(dt)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def exact_goal_met(rows: list[dict]) -> bool:
    """Goal (a): some float64 VBD row at dt = 1/60 s is within EXACT_GOAL_M of the exact step."""
    return any(
        _f(r, "vs_exact_rms") <= EXACT_GOAL_M
        for r in rows
        if r["solver"] == "vbd" and r["status"] == "ok" and "f64" in r["mode"] and abs(_f(r, "dt") - 1 / 60) < 1e-12
    )


def stability_table(rows: list[dict]) -> str:
    """Goal (b): per scene and stiffness, Verlet's largest stable dt (smallest over its backend
    modes) and how many VBD backend modes hold dt = 1/60 s, named by backend."""
    lines = [
        "| scene | k (N/m) | Verlet's largest stable dt (s) | VBD stable at 1/60 s | VBD backends |",
        "| --- | --- | --- | --- | --- |",
    ]
    for kind, k in dict.fromkeys((r["kind"], r["stiffness"]) for r in rows):
        mine = [r for r in rows if r["kind"] == kind and r["stiffness"] == k]
        verlet = [_f(r, "dt_stable") for r in mine if r["solver"] == "verlet"]
        vbd = [r for r in mine if r["solver"] == "vbd"]
        held = sum(1 for r in vbd if r["stable_at_60hz"] == "True")
        backends = ", ".join(dict.fromkeys(r["backend"] for r in vbd))
        lines.append(
            f"| {kind} | {float(k):.0e} | {min(verlet):.3g} | {held} of {len(vbd)} | {backends} |"
            if verlet
            else f"| {kind} | {float(k):.0e} | - | {held} of {len(vbd)} | {backends} |"
        )
    return "\n".join(lines)


def _interpolated_error(line: list[dict], cost: float) -> float:
    """A solver line's error (vs_verlet_rms) at `cost` ms per simulated second, interpolated
    in log-log between its two runs around it; nan outside the line's range."""
    pts = sorted((_f(r, "ms_per_sim_s"), _f(r, "vs_verlet_rms")) for r in line)
    for (c0, e0), (c1, e1) in zip(pts, pts[1:]):
        if c0 <= cost <= c1 and c1 > c0:
            t = math.log(cost / c0) / math.log(c1 / c0)
            return math.exp(math.log(e0) + t * (math.log(e1) - math.log(e0)))
    return float("nan")


def equal_cost_table(rows: list[dict]) -> str:
    """Goal (c): every VBD run's cost and error against Verlet's converged answer (the
    continuous model both solvers approximate), beside XPBD coloured's error at the same cost
    (its line interpolated in log-log; '-' where no coloured run is as cheap and one as dear),
    and which is closer. Outside the coloured line's costs a verdict still follows where one
    run dominates: a VBD run cheaper than the line's cheapest and no further from the answer
    than it is closer than XPBD could be at its cost ('>= e'), and one dearer than the line's
    dearest and further than it is not ('<= e'), as XPBD's error falls as its dt is halved."""
    ok = [r for r in rows if r["status"] == "ok"]
    lines = [
        "| grid | backend mode | VBD sweeps | dt (s) | ms per simulated s | VBD error (mm) "
        "| XPBD coloured at that cost (mm) | closer |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in (r for r in ok if r["solver"] == "vbd"):
        pbd = [
            p for p in ok if p["pbd_method"] == "coloured" and p["backend"] == r["backend"] and p["grid"] == r["grid"]
        ]
        lines_by_mode = {}
        for p in pbd:
            lines_by_mode.setdefault((p["mode"].split("/pbd")[0], p["iterations"]), []).append(p)
        mode = r["mode"].split("/vbd")[0]
        same = [line for (m, _), line in lines_by_mode.items() if m == mode]
        cost, err = _f(r, "ms_per_sim_s"), _f(r, "vs_verlet_rms")
        theirs = [e for e in (_interpolated_error(line, cost) for line in same) if math.isfinite(e)]
        best = min(theirs) if theirs else float("nan")
        verdict, shown = ("VBD" if err <= best else "XPBD", f"{best * 1e3:.3g}") if theirs else ("-", "-")
        ends = [sorted((_f(p, "ms_per_sim_s"), _f(p, "vs_verlet_rms")) for p in line) for line in same]
        if not theirs and ends:
            cheapest = min(end[0][1] for end in ends)  # the least error XPBD has below its costs
            dearest = min(end[-1][1] for end in ends)  # and above them
            if all(cost < end[0][0] for end in ends) and err <= cheapest:
                verdict, shown = "VBD", f">= {cheapest * 1e3:.3g}"
            elif all(cost > end[-1][0] for end in ends) and err > dearest:
                verdict, shown = "XPBD", f"<= {dearest * 1e3:.3g}"
        lines.append(
            f"| {r['grid']} | {r['backend']} {mode} | {r['iterations']} | {_dt_name(_f(r, 'dt'))} | {cost:.4g} "
            f"| {err * 1e3:.3g} | {shown} | {verdict} |"
        )
    return "\n".join(lines)


def cpu_table(rows: list[dict]) -> str:
    """Goal (d): per grid, clothbench's fastest VBD backend mode (median ms per step) and its
    error against NumPy float64 beside newton's, their ratio, and whether it is the goal's."""
    ok = [r for r in rows if r["status"] == "ok" and r["solver"] == "vbd"]
    lines = [
        "| grid | fastest clothbench VBD | ms/step | error (m) | newton ms/step | newton error (m) "
        f"| newton / fastest | >= {SPEEDUP_GOAL:g}x at equal or smaller error | load |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for grid in sorted({int(r["grid"]) for r in ok}):
        mine = [r for r in ok if int(r["grid"]) == grid]
        peer = [r for r in mine if r["backend"] == "newton"]
        ours = [r for r in mine if r["backend"] != "newton"]
        if not peer or not ours:
            continue
        fast, nw = min(ours, key=lambda r: _f(r, "ms_median")), peer[0]
        ratio = _f(nw, "ms_median") / _f(fast, "ms_median")
        met = ratio >= SPEEDUP_GOAL and _f(fast, "err_rms_m") <= _f(nw, "err_rms_m")
        busy = "busy" if any(r["busy"] == "true" for r in (fast, nw)) else "quiet"
        lines.append(
            f"| {grid}² | {fast['backend']} {fast['mode']} | {_f(fast, 'ms_median'):.4g} | {_f(fast, 'err_rms_m'):.2g} "
            f"| {_f(nw, 'ms_median'):.4g} | {_f(nw, 'err_rms_m'):.2g} | {ratio:.2f} | {'yes' if met else 'no'} | {busy} |"
        )
    return "\n".join(lines)


__all__ = [
    "EXACT_GOAL_M",
    "SPEEDUP_GOAL",
    "iterations_table",
    "exact_goal_met",
    "stability_table",
    "equal_cost_table",
    "cpu_table",
]
