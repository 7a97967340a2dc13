"""The `clothbench` command. Bad input gets one line on stderr and exit 2, never a traceback."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

from . import __version__
from .backends import BACKENDS, BackendOptions, availability, check_name, create_backend
from .errors import BlowUp, ClothbenchError
from .scene import Scene, load_scene


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, not usage + error
        where = self.prog.removeprefix("clothbench").strip()
        raise ClothbenchError(f"{where}: {message}" if where else message)


def _add_scene_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="sphere", help="built-in scene name or a .toml file")
    p.add_argument("--grid", type=int, help="particles per side (n >= 3)")
    p.add_argument("--steps", type=int, help="steps to simulate")
    p.add_argument("--dt", type=float, help="time step (s)")
    p.add_argument("--solver", choices=["verlet", "pbd"], help="mass-spring Verlet or PBD (docs/pbd.md)")
    p.add_argument("--pbd-method", choices=["jacobi", "coloured"], help="PBD: Jacobi or coloured Gauss-Seidel")
    p.add_argument("--iterations", type=int, help="PBD: constraint passes per substep")
    p.add_argument("--substeps", type=int, help="PBD: substeps per step")


def _add_backend_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--precision", choices=["f32", "f64"], default="f32")
    p.add_argument(
        "--strict", action="store_true", help="bit-exact with the numpy f32 reference (no FMA, no fast math)"
    )
    p.add_argument("--transfer", help="opencl: resident|per-step; cuda: swap|copy")
    p.add_argument("--local-size", type=int, help="work-group / block size (default: the runtime's)")
    p.add_argument("--device", help="device selector (opencl: 'platform:device' index, like PYOPENCL_CTX)")
    p.add_argument("--gl", choices=["egl", "osmesa"], default="egl", help="GL context provider")
    p.add_argument("--save-normals", action="store_true", help="compute normals and save them with --save")
    p.add_argument("--generic", action="store_true", help="one kernel for every scene (no specialisation)")


def scene_from_args(args) -> Scene:
    scene = load_scene(args.scene)
    names = ("grid", "steps", "dt", "solver", "pbd_method", "iterations", "substeps")
    changes = {k: getattr(args, k) for k in names if getattr(args, k, None) is not None}
    return scene.replace(**changes) if changes else scene


def options_from_args(args) -> BackendOptions:
    if args.local_size is not None and args.local_size < 1:
        raise ClothbenchError(f"--local-size must be >= 1, got {args.local_size}")
    return BackendOptions(
        precision=args.precision,
        strict=args.strict,
        transfer=args.transfer,
        local_size=args.local_size,
        device=args.device,
        gl=args.gl,
        normals=args.save_normals,
        generic=args.generic,
    )


def cmd_run(args) -> int:
    from .harness import run_timed
    from .reports.progress import LazyProgress

    check_name(args.backend)
    scene = scene_from_args(args)
    options = options_from_args(args)
    if args.precision == "f64" and args.backend != "numpy":
        raise ClothbenchError(f"{args.backend} runs in f32 only; f64 is the numpy reference")
    from .harness.energy import predicted_fast_impact

    if warning := predicted_fast_impact(scene):
        print(f"clothbench: warning: {warning}", file=sys.stderr)
    t0 = time.perf_counter()
    backend = create_backend(args.backend, scene, options)
    build_s = time.perf_counter() - t0
    with backend, LazyProgress(scene.steps, f"{args.backend} n={scene.grid}") as progress:
        result = run_timed(
            backend, scene, scene.steps, on_progress=progress.update, raise_on_blowup=False, build_s=build_s
        )
        normals = backend.read_normals() if args.save_normals else None
        stages = None
        if args.profile and result.blowup is None:
            backend.upload(*scene.initial_state(options.dtype))
            stages = backend.profile_stages(scene.steps)
    for warning in result.warnings:
        print(f"clothbench: warning: {warning}", file=sys.stderr)
    if args.save:
        arrays = {"pos": result.pos, "prev": result.prev}
        if normals is not None:
            arrays["normals"] = normals
        np.savez(args.save, **arrays)
    if result.blowup is not None:
        raise result.blowup
    summary = {
        "backend": result.backend,
        "device": result.device,
        "mode": result.mode,
        "scene": scene.name,
        "solver": scene.solver,
        "grid": scene.grid,
        "particles": scene.particles,
        "springs": scene.springs,
        "steps": scene.steps,
        "dt": scene.dt,
        "precision": args.precision,
        "ms_per_step": result.ms_per_step,
        "ms_per_step_min": result.spread()["min"],
        "ms_per_step_max": result.spread()["max"],
        "simulated_s": scene.steps * scene.dt,
        "warmup_s": result.warmup_s,
        "finite": result.finite,
        "max_penetration": result.max_penetration,
    }
    if result.device_ms_per_step:
        summary["device_ms_per_step"] = statistics.median(result.device_ms_per_step)
    if args.profile:
        summary["stages_ms_per_step"] = stages  # None: this backend has one stage
    if args.json:
        print(json.dumps(summary))
    else:
        from .reports.tables import print_run

        print_run(summary)
    return 0


def cmd_backends(args) -> int:
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
        from .reports.tables import print_backends

        print_backends(rows)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="clothbench", description=__doc__)
    parser.add_argument("--version", action="version", version=f"clothbench {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    run = sub.add_parser("run", help="run one scene on one backend and time it")
    run.add_argument("--backend", default="numpy", help=f"one of: {', '.join(BACKENDS)}")
    _add_scene_args(run)
    _add_backend_args(run)
    run.add_argument("--save", help="write pos, prev (and normals) to this .npz")
    run.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    run.add_argument("--profile", action="store_true", help="also time each stage of the step on its own")
    run.set_defaults(func=cmd_run)

    backends = sub.add_parser("backends", help="list every backend, whether it runs here, and why not")
    backends.add_argument("--json", action="store_true")
    backends.set_defaults(func=cmd_backends)

    for register in _extra_commands():
        register(sub)
    return parser


# Commands that live in their own modules; each module has register(subparsers).
EXTRA_COMMAND_MODULES = (
    "clothbench.harness.sweep_cli",
    "clothbench.reports.plot_cli",
    "clothbench.accuracy_cli",
    "clothbench.reports.render_cli",
)


def _extra_commands():
    import importlib

    for module in EXTRA_COMMAND_MODULES:
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if e.name == module:
                continue  # not written yet
            raise
        yield mod.register


def main(argv: list[str] | None = None) -> int:
    try:
        args = build_parser().parse_args(argv)
        return args.func(args)
    except BlowUp as e:
        print(f"clothbench: {e}", file=sys.stderr)
        return e.exit_code
    except ClothbenchError as e:
        print(f"clothbench: error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("clothbench: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `clothbench backends | head`: the reader left, nothing to say
        # point stdout at /dev/null so the interpreter's final flush does not complain
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
