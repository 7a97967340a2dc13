"""`clothbench run`: one scene on one backend, timed, with its health and penetration."""

from __future__ import annotations

import json
import statistics
import sys
import time

from clothbench.cli.args import (
    add_backend_args,
    add_scene_args,
    check_mesh_collision,
    options_from_args,
    setup_from_args,
    sigterm_interrupts,
)
from clothbench.variant_names import model_name


def register(subparsers) -> None:
    from clothbench.backends import BACKENDS

    p = subparsers.add_parser("run", help="run one scene on one backend and time it")
    p.add_argument("--backend", default="numpy", help=f"one of: {', '.join(BACKENDS)}")
    add_scene_args(p)
    add_backend_args(p)
    p.add_argument(
        "--save",
        metavar="FILE.npz",
        help="write pos, prev (and normals) to this .npz file, in a folder that exists, and say where "
        "(a folder or another suffix is refused)",
    )
    add_export_args(p)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    p.add_argument("--profile", action="store_true", help="also time each stage of the step on its own")
    p.set_defaults(func=cmd_run)


def default_export_every() -> int:
    """One exported frame per viewer frame, so that `view --from` shows each once."""
    from clothbench.viewer import ViewSettings

    return ViewSettings().steps_per_frame


def add_export_args(p) -> None:
    from clothbench.reports.export import FRAME_FORMATS

    every = default_export_every()
    p.add_argument(
        "--export",
        metavar="FILE.usd|FOLDER/",
        help="also write the run's frames, read back in a second, untimed run of the same steps (docs/export.md): "
        "a .usd, .usda or .usdc stage (cloth mesh with normals, colliders as their own prims), or a folder of "
        "one OBJ or PLY per frame",
    )
    p.add_argument(
        "--export-every",
        type=int,
        metavar="K",
        help=f"steps between exported frames (default {every}, the viewer's steps per frame); the first frame "
        "is the start, the last the final step",
    )
    p.add_argument("--export-format", choices=FRAME_FORMATS, help="a folder's frames: obj (default) or ply")


def cmd_run(args) -> int:
    import numpy as np

    from clothbench.backends import check_name, create_backend
    from clothbench.harness import run_timed
    from clothbench.harness.energy import predicted_fast_impact
    from clothbench.harness.noise import doubts
    from clothbench.machine_load import LoadSampler
    from clothbench.progress import LazyProgress, waiting

    from clothbench.harness.preflight import check_memory, check_writable
    from clothbench.reports.export import export_target

    sigterm_interrupts()
    check_name(args.backend)
    setup = setup_from_args(args)
    scene, solver, steps = setup.scene, setup.solver, setup.steps
    options = options_from_args(args)
    check_strict(args.backend, solver.name, options)
    check_mesh_collision(options.mesh_collision, scene)
    save = _npz(check_writable(args.save, "--save")) if args.save is not None else None  # before the run, not after
    export = export_target(args.export, args.export_every, args.export_format)
    check_memory([scene.grid], [args.precision])
    if warning := predicted_fast_impact(scene, solver):
        print(f"clothbench: warning: {warning}", file=sys.stderr)
    t0 = time.perf_counter()
    with waiting(f"building {args.backend}: imports, device, kernels"):
        backend = create_backend(args.backend, scene, solver, options)
    build_s = time.perf_counter() - t0
    warming = waiting(f"warming up {args.backend}: first steps (a JIT compiles here)")
    with backend, LazyProgress(steps, f"{args.backend} n={scene.grid}") as progress:
        watch = LoadSampler().start()  # how busy the machine was while it ran
        result = run_timed(
            backend, steps, on_progress=progress.update, raise_on_blowup=False, build_s=build_s, warming=warming
        )
        load = watch.stop()
        normals = backend.read_normals() if args.save_normals else None
        stages = None
        if args.profile and result.blowup is None:
            backend.upload(*backend.initial_state())
            stages = backend.profile_stages(steps)
        exported = _export(args, export, setup, backend, result) if export is not None else None
    for warning in result.warnings:
        print(f"clothbench: warning: {warning}", file=sys.stderr)
    if backend.run_note:
        print(f"clothbench: note: {backend.name}: {backend.run_note}", file=sys.stderr)
    if result.blowup is None and (doubt := doubts(load.busy, load.why, result.chunk_ms_per_step)):
        # as pyperf warns: the figure is printed, and said not to hold
        print(f"clothbench: warning: the result may not hold: {'; '.join(doubt)}", file=sys.stderr)
    if save is not None:
        arrays = {"pos": result.pos, "prev": result.prev}
        if normals is not None:
            arrays["normals"] = normals
        partial = save.with_name(f".{save.name}.partial")
        with open(partial, "wb") as f:  # an interrupt leaves the old file or the new one, never half
            np.savez(f, **arrays)
        partial.replace(save)
        if args.json or result.blowup is not None:  # stdout is one JSON object, or there is no table
            print(f"wrote {save}", file=sys.stderr)
    if exported is not None and (args.json or result.blowup is not None):
        print(exported, file=sys.stderr)
    if result.blowup is not None:
        raise result.blowup
    summary = {
        "backend": result.backend,
        "device": result.device,
        "driver": result.driver,
        "mode": result.mode,
        "scene": scene.name,
        "solver": solver.name,
        "model": model_name(solver),  # the solver with its settings: 'vbd/10it, chebyshev_rho 0.9'
        "grid": scene.grid,
        "particles": scene.particles,
        "springs": scene.springs,
        "steps": steps,
        "dt": solver.dt,
        "precision": args.precision,
        "ms_per_step": result.ms_per_step,
        "ms_per_step_min": result.spread()["min"],
        "ms_per_step_max": result.spread()["max"],
        "simulated_s": steps * solver.dt,
        "warmup_s": result.warmup_s,
        "finite": result.finite,
        "max_penetration": result.max_penetration,
        **(
            {}
            if (contact := result.self_contact) is None
            else {"self_pairs": contact[0], "self_min_distance": contact[1]}
        ),
        "busy": load.busy,  # None: not measured, or too short a run to tell
        "load": load.why,
    }
    if result.device_ms_per_step:
        summary["device_ms_per_step"] = statistics.median(result.device_ms_per_step)
        summary["device_timer"] = result.device_timer
    elif note := backend.device_timer_note:
        summary["device_timer_note"] = note  # why a device that has timers reports no device time
    if args.profile:
        summary["stages_ms_per_step"] = stages  # None: this backend has one stage
    if args.json:
        print(json.dumps(summary))
    else:
        from clothbench.reports.tables import print_run

        print_run(summary)
        if line := device_clock_line(summary):
            print(line)
        if save is not None:
            print(f"wrote {save}")
        if exported is not None:
            print(exported)
    return 0


def _export(args, target, setup, backend, result) -> str:
    """The frames of the run written to `target` by a replay after the timed run (the timed
    chunks' numbers are as without --export), and the line that says so. A replay that does not
    end on the timed run's final state (a backend that is not deterministic) is warned about."""
    import numpy as np

    from clothbench.progress import waiting
    from clothbench.reports.export import RunInfo, export_replay, open_writer, scene_spec

    every = args.export_every or default_export_every()
    steps = result.steps if result.blowup is None else result.blowup.step - 1  # the frames before it
    info = RunInfo(
        scene_spec(args.scene),
        setup.scene.grid,
        setup.solver.dt,
        setup.solver.spec,
        every,
        steps,
        backend.name,
        backend.mode,
    )
    with waiting(f"exporting {target.path}: the {steps} steps again, read back every {every}"):
        writer = open_writer(target, setup.scene, info)
        frames, last = export_replay(backend, steps, writer)
        path = writer.close()
    for note in writer.notes:
        print(f"clothbench: warning: --export: {note}", file=sys.stderr)
    if result.blowup is None and not np.array_equal(last, result.pos[:, : last.shape[1]], equal_nan=True):
        worst = float(np.abs(last[:, :3].astype(np.float64) - result.pos[:, :3]).max())
        print(
            f"clothbench: warning: --export: the replay ended up to {worst:.3g} m from the timed run's final "
            f"state ({backend.name} did not repeat its steps bit for bit)",
            file=sys.stderr,
        )
    return f"exported {frames} frames to {path} (every {every} steps, read back in an untimed second run)"


def check_strict(backend: str, solver: str, options) -> None:
    """--strict where the backend has no fast mode would be ignored (numpy is the reference
    --strict matches, in either precision): refused instead."""
    from clothbench.backends import capabilities
    from clothbench.errors import ClothbenchError

    if options.strict and not capabilities(backend, solver).strict:
        why = "it is the reference --strict matches" if backend == "numpy" else "it has one mode, no fast one"
        raise ClothbenchError(
            f"{backend} does not take --strict ({why}; --strict applies to backends with a fast mode)"
        )


def device_clock_line(summary: dict) -> str:
    """One line under the table: which device clock timed the steps and what it includes
    (harness/timing.py DEVICE_TIMERS), or why a device backend has none; '' for a backend
    without one (numpy, c). The wall clock's ms/step holds the device time and the host's side
    (launches, the synchronize)."""
    from clothbench.harness.timing import DEVICE_TIMERS

    if timer := summary.get("device_timer"):
        return f"device clock: {timer}: {DEVICE_TIMERS[timer]}"
    if why := summary.get("device_timer_note"):
        return f"device clock: none ({why}); ms/step is the wall clock alone"
    return ""


def _npz(path):
    """--save's file, a .npz name as given, or one line saying why not (np.savez would add .npz
    to any other name: outdir.npz beside a folder, x.npy.npz for x.npy)."""
    from clothbench.errors import ClothbenchError

    if path.suffix.lower() != ".npz":
        raise ClothbenchError(f"--save takes a .npz file, got {str(path)!r}")
    return path
