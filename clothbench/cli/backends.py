"""`clothbench backends`: every backend, whether it can run here, and why not; then every
OpenCL device of every platform (runtime, versions, whether it compiles) and which one is
the default, and why."""

from __future__ import annotations

import json

from clothbench.errors import ClothbenchError


def register(subparsers) -> None:
    p = subparsers.add_parser("backends", help="list every backend, whether it runs here, and why not")
    p.add_argument(
        "names",
        nargs="*",
        metavar="BACKEND",
        help="only these backends (default: all; a cold probe of every peer imports each, seconds apiece)",
    )
    p.add_argument("--json", action="store_true")
    p.add_argument("--retune", action="store_true", help="measure the OpenCL devices again to choose the default")
    p.set_defaults(func=cmd_backends)


def cmd_backends(args) -> int:
    from clothbench.backends import BACKENDS, availability, check_name
    from clothbench.progress import waiting

    names = list(dict.fromkeys(args.names)) or list(BACKENDS)
    for name in names:
        check_name(name)  # an unknown name refused before any probe
    if args.retune and "opencl" not in names:
        raise ClothbenchError("--retune measures the OpenCL devices: add opencl to the backends named")
    rows = []
    devices = None
    with waiting("probing backends"):  # a cold probe imports every peer and opens every device
        for name in names:
            entry = BACKENDS[name]
            with waiting(f"probing backends: {name}"):
                a = availability(name)
            rows.append(
                {
                    "backend": name,
                    "kind": "peer" if entry.peer else "clothbench",
                    "usable": a.usable,
                    "device": a.device,
                    "driver": a.driver,
                    "reason": a.reason,
                }
            )
        if "opencl" in names:
            with waiting("probing backends: OpenCL devices (compiling a kernel on each)"):
                devices, default = opencl_devices(args.retune)
    for row in rows:
        if row["backend"] == "opencl" and devices is not None:
            row["devices"], row["default_device"] = devices, default
    if args.json:
        print(json.dumps(rows))
        return 0
    from clothbench.reports.tables import print_backends

    print_backends(rows)
    if devices:
        print_opencl_devices(devices, default)
    return 0


def opencl_devices(retune: bool) -> tuple[list[dict] | None, str]:
    """The OpenCL device rows and the default's line; (None, why) without pyopencl or any
    platform (the opencl row's reason already says so)."""
    try:
        from clothbench.backends.opencl import device

        device.import_pyopencl()
        return device.device_listing(retune)
    except ImportError:
        return None, "pyopencl not installed"
    except ClothbenchError as e:
        return None, str(e)


DEVICE_COLUMNS = ("device", "name", "runtime", "platform version", "driver", "LLVM", "compiles")


def device_cells(d: dict) -> tuple[str, ...]:
    """One OpenCL device's cells, plain text (a driver's text is not rich markup)."""
    compiles = "yes" if d["compiles"] else f"no: {d['error']}"
    return (
        d["device"] + ("*" if d["default"] else ""),
        d["name"],
        f"{d['runtime']} ({d['platform']})",
        d["platform_version"],
        d["driver_version"],
        d["llvm"] or "-",
        compiles,
    )


def print_opencl_devices(devices: list[dict], default: str, width: int | None = None) -> None:
    """The devices as a table where it fits the terminal unwrapped, else (narrow, or piped:
    rich then assumes 80 columns) as lines under a heading, each cell whole: a table squeezed
    to 80 columns cut every cell to a few letters."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console() if width is None else Console(width=width)
    width = console.width
    rows = [device_cells(d) for d in devices]
    widths = [max(len(c) for c in col) for col in zip(DEVICE_COLUMNS, *rows)]
    if sum(widths) + 3 * len(widths) + 1 <= width:  # cells, padding and borders: rich's box
        table = Table(title="OpenCL devices")
        for col in DEVICE_COLUMNS:
            table.add_column(col, no_wrap=True)
        for d, cells in zip(devices, rows):
            compiles = "[green]yes[/green]" if d["compiles"] else f"[red]no[/red]: {escape(d['error'])}"
            table.add_row(*map(escape, cells[:-1]), compiles)
        console.print(table)
    else:
        print("OpenCL devices (* the default):")
        for cells in rows:
            device, *rest = cells
            print(f"  {device} {rest[0]}")
            for label, value in zip(DEVICE_COLUMNS[2:], rest[1:]):
                print(f"      {label}: {value}")
    print(default)  # one line, unwrapped: what a script or a bug report quotes
