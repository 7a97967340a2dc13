"""`clothbench machine`: whether this machine is fit to benchmark now, and what to do if not
(clothbench/machine_fitness.py), as `pyperf system show` does. `sweep` prints the same verdict
when it starts and records it in every row it writes (the `machine_state` column)."""

from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "machine", help="is this machine fit to benchmark now: cores, load, steal, heavy processes, governor, turbo"
    )
    p.add_argument(
        "--window",
        type=float,
        default=None,
        metavar="S",
        help="seconds to watch the load over (default: 1.0; at least 0.25)",
    )
    p.add_argument("--json", action="store_true", help="the whole state as one JSON object")
    p.set_defaults(func=cmd_machine)


def cmd_machine(args) -> int:
    from clothbench.errors import ClothbenchError
    from clothbench.machine_fitness import WINDOW_S, check
    from clothbench.machine_load import MIN_WINDOW_S

    window = WINDOW_S if args.window is None else args.window
    if not window >= MIN_WINDOW_S or window > 60:
        raise ClothbenchError(f"--window takes {MIN_WINDOW_S} to 60 seconds, got {args.window}")
    f = check(window_s=window)
    if args.json:
        print(json.dumps(f.as_dict()))
        return 0
    print(f"cpus        {len(f.cpus)} ({','.join(map(str, f.cpus))})")
    print(f"load        {f.load.why}" + (f"; load average {f.loadavg}" if f.loadavg else ""))
    heavy = ", ".join(f"{h.name} (pid {h.pid}) {h.cores:.2f}" for h in f.heavy) or "none"
    print(f"heavy       {heavy}")
    governors = ", ".join(f"{g} x{n}" for g, n in sorted(f.governors.items())) or "not readable"
    print(f"governor    {governors}")
    print(f"turbo       {'not readable' if f.turbo is None else 'on' if f.turbo else 'off'}")
    for note in f.notes:
        print(f"note        {note}")
    for problem in f.problems:
        print(f"PROBLEM     {problem}")
    verdict = {True: "fit to benchmark", False: "NOT fit to benchmark now", None: "fitness unknown"}[f.fit]
    print(f"verdict     {verdict}: {f.verdict}")
    return 0
