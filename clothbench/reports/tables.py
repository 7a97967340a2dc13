"""Terminal tables (rich) for `run` and `backends`."""

from __future__ import annotations

from rich.console import Console
from rich.markup import escape
from rich.table import Table

from clothbench.backends import check_name


def print_run(s: dict) -> None:
    table = Table(title=f"clothbench run: {s['scene']} on {s['backend']}", show_header=False)
    table.add_column("what", style="bold")
    table.add_column("value")
    spread = f"{s['ms_per_step']:.3f} (min {s['ms_per_step_min']:.3f}, max {s['ms_per_step_max']:.3f})"
    rows = [
        ("backend", f"{s['backend']} ({s['mode']})"),
        ("solver", s["model"]),
        ("device", s["device"]),
        *((("driver", s["driver"]),) if s.get("driver") else ()),  # which runtime: the device name may not say
        ("grid", f"{s['grid']} x {s['grid']}"),
        ("particles", f"{s['particles']:,}"),
        ("springs", f"{s['springs']:,}"),
        ("steps", f"{s['steps']:,} x dt {s['dt']:g} s = {s['simulated_s']:.4g} s simulated"),
        ("ms/step", spread + " median of timed chunks"),
    ]
    if "device_ms_per_step" in s:
        rows.append(
            ("device ms/step", f"{s['device_ms_per_step']:.3f} ({s.get('device_timer') or 'profiling events'})")
        )
    rows += [
        ("warm-up", f"{s['warmup_s']:.2f} s (build + first steps, not timed)"),
        ("finite", "yes" if s["finite"] else "NO"),
        ("max penetration", f"{s['max_penetration']:.3g} m"),
    ]
    if "self_pairs" in s:  # a self-colliding scene: docs/semantics.md, "The measure"
        closest = f"closest {s['self_min_distance']:.3g} m"
        rows.append(("self-contact", f"{s['self_pairs']:,} pairs closer than the thickness, {closest}"))
    if s.get("stages_ms_per_step"):
        for stage, ms in s["stages_ms_per_step"].items():
            rows.append((f"  stage {stage}", f"{ms:.3f} ms/step (synchronised per stage)"))
    elif "stages_ms_per_step" in s:
        rows.append(("stages", "one kernel: no separate stages to profile"))
    for what, value in rows:
        table.add_row(what, str(value))
    Console().print(table)


def print_backends(rows: list[dict]) -> None:
    table = Table(title="clothbench backends")
    for col in ("backend", "kind", "usable", "device / reason"):
        table.add_column(col)
    for r in rows:
        usable = "[green]yes[/green]" if r["usable"] else "[red]no[/red]"
        # escaped: a reason's install hint ("pip install 'clothbench[peers]'") is not markup
        table.add_row(r["backend"], r["kind"], usable, escape(device_cell(r) if r["usable"] else r["reason"]))
    Console().print(table)


def device_cell(r: dict) -> str:
    """A usable backend's device, and on a line of its own the driver that runs it where it
    names one: one CPU's name is every CPU runtime's."""
    return r["device"] + (f"\ndriver: {r['driver']}" if r.get("driver") else "")


def gpu_style(backend: str) -> bool:
    """One of clothbench's GPGPU platforms, what the chapter compares (the registry says; numpy
    is the reference, c the native CPU line each is measured against)."""
    return check_name(backend).gpu_style


def peer_ratios(rows: list[dict]) -> list[dict]:
    """Per grid: clothbench's fastest GPU-style backend (any mode, default local size)
    against the fastest peer, from sweep rows with status ok. The README's performance table."""
    out = []
    for grid in sorted({int(r["grid"]) for r in rows}):
        mine = [
            r
            for r in rows
            if int(r["grid"]) == grid
            and gpu_style(r["backend"])
            and not r["local_size"]
            and r["status"] == "ok"
            and r["precision"] == "f32"
        ]
        peers = [r for r in rows if int(r["grid"]) == grid and r["peer"] == "true" and r["status"] == "ok"]
        if not mine or not peers:
            continue
        best = min(mine, key=lambda r: float(r["ms_median"]))
        peer = min(peers, key=lambda r: float(r["ms_median"]))
        out.append(
            {
                "grid": grid,
                "ours": f"{best['backend']} {best['mode']}",
                "ours_ms": float(best["ms_median"]),
                "peer": f"{peer['backend']} {peer['mode']}",
                "peer_ms": float(peer["ms_median"]),
                "ratio": float(peer["ms_median"]) / float(best["ms_median"]),
            }
        )
    return out


def peer_ratio_markdown(rows: list[dict]) -> str:
    lines = [
        "| grid | fastest GPU-style backend | ms/step | fastest peer | ms/step | peer / it |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for r in peer_ratios(rows):
        lines.append(
            f"| {r['grid']}×{r['grid']} | {r['ours']} | {r['ours_ms']:.3f} | {r['peer']} | "
            f"{r['peer_ms']:.3f} | {r['ratio']:.1f}× |"
        )
    return "\n".join(lines)
