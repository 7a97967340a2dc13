"""`clothbench tuning`: every kernel shape chosen by measurement and cached
(backends/tuning.py), whether it is final or provisional and why, when it was measured, how
busy the machine was, and how far apart the best two candidates were against their noise."""

from __future__ import annotations

import json

# key fields that name the machine and its software rather than the work: long, and the same
# for every entry of one machine, so the table leaves them to --json
MACHINE_FIELDS = ("cpu", "cores", "compiler", "kernel", "device", "devices", "driver")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "tuning", help="list the cached kernel-shape choices: final or provisional, when, how busy, how close"
    )
    p.add_argument("--backend", help="only this backend's choices (the name of its tuning file)")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_tuning)


def cmd_tuning(args) -> int:
    from clothbench.backends.tuning import listing
    from clothbench.errors import ClothbenchError

    rows = listing()
    if args.backend is not None:
        known = sorted({r["backend"] for r in rows})
        if args.backend not in known:
            have = ", ".join(known) if known else "none yet"
            raise ClothbenchError(f"tuning: no cached choice for {args.backend!r} (cached: {have})")
        rows = [r for r in rows if r["backend"] == args.backend]
    if args.json:
        print(json.dumps(rows))
        return 0
    if not rows:
        print("no cached kernel-shape choices (they are measured the first time a backend runs)")
        return 0
    table = [("backend", "key", "choice", "status", "measured (UTC)", "others", "next best", "why")]
    table += [_cells(r) for r in rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(table[0]) - 1)]
    for row in table:
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[-1])
    return 0


def _cells(r: dict) -> tuple[str, ...]:
    key = " ".join(f"{k}={v}" for k, v in r["key"].items() if k not in MACHINE_FIELDS)
    others = "?" if r["other_share"] is None else f"{r['other_share']:.0%}"
    if r["next_best"] is None or r["apart"] is None:
        apart = "-"
    else:
        noise = "" if r["noise"] is None else f", noise {r['noise']:.0%}"
        apart = f"{r['next_best']} +{r['apart']:.0%}{noise}"
    return (r["backend"], key, _short(r["choice"]), r["status"], r["measured_at"], others, _short(apart), r["why"])


def _short(text: str, width: int = 40) -> str:
    """An OpenCL device's name runs to 150 characters with its driver: --json has it whole."""
    return text if len(text) <= width else text[: width - 1] + "…"
