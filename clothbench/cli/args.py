"""Argument groups every command shares, and how they become a Setup and BackendOptions."""

from __future__ import annotations

import argparse
import re

from clothbench.errors import ClothbenchError
from clothbench.model.solver import ITERATIVE, PBD_METHODS, SOLVER_SPECS, SOLVERS
from clothbench.variant_names import GL_PROVIDERS, PRECISIONS, transfers_help


# what argparse should read as a (negative) number, not an option: its own matcher takes
# -1 and -0.5 but not -1e-3 or -inf, so `--dt -1e-3` said "expected one argument" instead of
# the range check's answer
NEGATIVE_NUMBER = re.compile(r"^-(?:(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|inf(?:inity)?|nan)$", re.IGNORECASE)


class Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_NUMBER

    def error(self, message):  # one line, not usage + error
        where = self.prog.removeprefix("clothbench").strip()
        raise ClothbenchError(f"{where}: {message}" if where else message)


def add_documented_command(subparsers, name: str, help: str, doc: str, epilog: str) -> argparse.ArgumentParser:
    """The parser of a command whose --help is its module docstring `doc` then `epilog` (its
    examples), both shown as written: line breaks and indentation kept."""
    return subparsers.add_parser(
        name, help=help, description=doc, epilog=epilog, formatter_class=argparse.RawDescriptionHelpFormatter
    )


def add_scene_args(
    p: argparse.ArgumentParser, default: str = "sphere", run_length: bool = True, solver: bool = True
) -> None:
    """--scene and what overrides the scene file: --grid, --dt, and (where the command takes
    them) --steps and the solver settings."""
    p.add_argument("--scene", default=default, help=f"built-in scene name or a .toml file (default {default})")
    p.add_argument("--grid", type=int, help="particles per side (n >= 3; default: the scene's)")
    p.add_argument("--dt", type=float, help="time step (s); default: the scene's")
    if run_length:
        p.add_argument("--steps", type=int, help="steps to simulate (default: the scene's)")
    if solver:
        p.add_argument(
            "--solver", choices=SOLVERS, help="mass-spring Verlet, PBD (docs/pbd.md) or implicit VBD (docs/vbd.md)"
        )
        p.add_argument("--pbd-method", choices=PBD_METHODS, help="PBD: Jacobi or coloured Gauss-Seidel")
        p.add_argument("--iterations", type=int, help="PBD: constraint passes per substep; VBD: colour sweeps")
        p.add_argument("--substeps", type=int, help="PBD, VBD: substeps per step")
        p.add_argument(
            "--chebyshev-rho",
            type=float,
            help="PBD Jacobi, VBD: Chebyshev acceleration's spectral radius estimate, in [0, 1) (0: off; "
            "docs/pbd.md, docs/vbd.md)",
        )


# the solvers each solver setting of the command line applies to (a run of another refuses it)
SOLVER_SETTINGS = {"pbd_method": ("pbd",), "iterations": ITERATIVE, "substeps": ITERATIVE, "chebyshev_rho": ITERATIVE}


def flag(option: str) -> str:
    """The command-line flag of an argparse destination: 'pbd_method' -> '--pbd-method'."""
    return "--" + option.replace("_", "-")


def setup_from_args(args):
    """The scene file named by --scene with the command line's overrides applied."""
    from clothbench.model.scene import load_setup

    setup = load_setup(args.scene).replace(
        grid=args.grid,
        steps=getattr(args, "steps", None),
        dt=args.dt,
        solver=getattr(args, "solver", None),
        method=getattr(args, "pbd_method", None),
        iterations=getattr(args, "iterations", None),
        substeps=getattr(args, "substeps", None),
        chebyshev_rho=getattr(args, "chebyshev_rho", None),
    )
    name = setup.solver.name
    for option, takers in SOLVER_SETTINGS.items():  # a setting this run's solver would ignore: say so instead
        if getattr(args, option, None) is not None and name not in takers:
            raise ClothbenchError(
                f"{flag(option)} applies to the {' and '.join(takers)} solver{'s' * (len(takers) > 1)} only, and "
                f"this run's is {name}: add --solver {' or '.join(takers)}"
            )
    if getattr(args, "chebyshev_rho", None) is not None and name == "pbd" and setup.solver.method != "jacobi":
        raise ClothbenchError(
            f"--chebyshev-rho applies to PBD's jacobi method and to vbd, and this run's PBD is {setup.solver.method}: "
            "add --pbd-method jacobi"
        )
    if getattr(args, "precision", "f32") == "f32":
        from clothbench.harness.preflight import check_float32_motion

        check_float32_motion(setup.scene, setup.solver)
    return setup


def add_backend_args(p: argparse.ArgumentParser) -> None:
    from clothbench.backends.base import MESH_COLLISIONS

    p.add_argument("--precision", choices=PRECISIONS, default=PRECISIONS[0])
    p.add_argument(
        "--strict", action="store_true", help="bit-exact with the numpy f32 reference (no FMA, no fast math)"
    )
    p.add_argument("--transfer", help=transfers_help())
    p.add_argument("--local-size", type=int, help="work-group / block size (default: the runtime's)")
    add_device_args(p)
    p.add_argument("--save-normals", action="store_true", help="compute normals and save them with --save")
    p.add_argument("--generic", action="store_true", help="one kernel for every scene (no specialisation)")
    p.add_argument(
        "--shape",
        help="run this kernel shape (as the mode names it, e.g. v8/wg=64) instead of the one tuned for this device",
    )
    p.add_argument(
        "--mesh-collision",
        choices=MESH_COLLISIONS,
        help="scenes with [[mesh]] colliders: naive (every triangle) or accelerated (a BVH); same bits "
        "(default: the backend's first)",
    )


def add_device_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", help="device selector (opencl: 'platform:device' index, like PYOPENCL_CTX)")
    p.add_argument("--gl", choices=GL_PROVIDERS, default=GL_PROVIDERS[0], help="GL context provider")
    p.add_argument(
        "--retune",
        action="store_true",
        help="measure the kernel shapes (vector width, work-group size) again on this device instead of "
        "reading the choice cached by the first run (CLOTHBENCH_TUNING=off: default shapes, no measuring)",
    )


def options_from_args(args):
    from clothbench.backends import BackendOptions

    if args.local_size is not None and args.local_size < 1:
        raise ClothbenchError(f"--local-size must be >= 1, got {args.local_size}")
    return fields_from_args(BackendOptions, args, normals=args.save_normals)


def fields_from_args(settings: type, args, **given):
    """The dataclass `settings` with each field the command has an option of the same name
    for read from `args`, and `given` for the others (or in place of one); a field with
    neither keeps its default."""
    import dataclasses

    names = (f.name for f in dataclasses.fields(settings) if f.init)
    return settings(**{name: getattr(args, name) for name in names if hasattr(args, name)} | given)


def check_mesh_collision(algorithm: str | None, scene) -> None:
    """--mesh-collision only where the scene has a mesh for it to find triangles in."""
    if algorithm is not None and not scene.meshes:
        raise ClothbenchError(f"--mesh-collision: scene {scene.name} has no [[mesh]] collider")


def solver_specs(text: str, option: str = "--solvers") -> tuple[str, ...]:
    """'verlet,pbd-coloured' -> ('verlet', 'pbd-coloured'), each checked, duplicates dropped."""
    specs = tuple(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    bad = [s for s in specs if s not in SOLVER_SPECS]
    if bad or not specs:
        raise ClothbenchError(f"{option} takes {', '.join(SOLVER_SPECS)} (comma-separated), got {text!r}")
    return specs


def choice_list(what: str, choices: tuple[str, ...]):
    """An argparse type for 'naive,accelerated': each one of `choices`, duplicates dropped, order kept."""

    def parse(text: str) -> list[str]:
        values = list(dict.fromkeys(part.strip() for part in text.split(",") if part.strip()))
        bad = [v for v in values if v not in choices]
        if bad or not values:
            raise argparse.ArgumentTypeError(
                f"{what} takes {', '.join(choices)} (comma-separated), got {(bad[0] if bad else text)!r}"
            )
        return values

    return parse


def int_list(what: str, minimum: int):
    """An argparse type for '32,64,128': positive integers, duplicates dropped, order kept."""

    def parse(text: str) -> list[int]:
        values = []
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            try:
                value = int(part)
            except ValueError:
                raise argparse.ArgumentTypeError(
                    f"{what} takes comma-separated integers like 32,64,128, got {part!r}"
                ) from None
            if value < minimum:
                raise argparse.ArgumentTypeError(f"{what} must all be >= {minimum}, got {value}")
            if value not in values:
                values.append(value)
        if not values:
            raise argparse.ArgumentTypeError(f"{what} is empty")
        return values

    return parse


def add_row_args(p: argparse.ArgumentParser, jobs: bool = False) -> None:
    """What runs each row: a worker process with a time limit, and (for commands whose rows
    only measure error) how many at once; --scheduler sends them to a Dask cluster."""
    p.add_argument(
        "--row-timeout",
        type=float,
        default=3600.0,
        metavar="SECONDS",
        help="a row still running after this long is killed and written as timeout (default 3600)",
    )
    if jobs:
        p.add_argument(
            "--jobs", type=int, default=1, help="rows that only measure error run this many at once (default 1)"
        )
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run the rows on this Dask distributed scheduler (default: $CLOTHBENCH_SCHEDULER, else here)",
    )


def check_row_args(args) -> None:
    if not args.row_timeout > 0:
        raise ClothbenchError(f"--row-timeout must be > 0 seconds, got {args.row_timeout}")
    if getattr(args, "jobs", 1) < 1:
        raise ClothbenchError(f"--jobs must be >= 1, got {args.jobs}")


def sigterm_interrupts() -> None:
    """SIGTERM as a Ctrl-C: the command keeps its finished rows, writes no partial one, exits 130."""
    import signal
    import threading

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, interrupt)
