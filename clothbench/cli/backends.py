"""`clothbench backends`: every backend, whether it can run here, and why not."""

from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser("backends", help="list every backend, whether it runs here, and why not")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_backends)


def cmd_backends(args) -> int:
    from clothbench.backends import BACKENDS, availability

    rows = []
    for name, entry in BACKENDS.items():
        a = availability(name)
        rows.append(
            {
                "backend": name,
                "kind": "peer" if entry.peer else "clothbench",
                "usable": a.usable,
                "device": a.device,
                "reason": a.reason,
            }
        )
    if args.json:
        print(json.dumps(rows))
    else:
        from clothbench.reports.tables import print_backends

        print_backends(rows)
    return 0
