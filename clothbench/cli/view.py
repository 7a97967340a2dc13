"""`clothbench view`: the cloth live in a window; the backend, the grid and the colliders
change by key while it runs, with a text overlay and a hierarchical profiler."""

from __future__ import annotations

from pathlib import Path

from clothbench.cli.args import add_documented_command, add_scene_args, fields_from_args, setup_from_args
from clothbench.cli.render import size
from clothbench.errors import ClothbenchError

EPILOG = """\
keys:
{keys}

Driven without a person: --keys "40:F3,80:F2,120:P" presses F3 before frame 40 is stepped,
F2 before frame 80, P before frame 120, key names as on the keyboard:
  {names}
--frames N stops after N frames and writes --screenshot (the last frame), --record (every
frame), --save (the final pos and prev, as `run --save` writes them) and --log (one JSON line
per frame: backend, grid, step, ms, fps, the profiler tree, the shadow error when on). Without a
display, run it under a virtual one:
  xvfb-run -a clothbench view --scene sphere --backend numpy --strict \\
      --keys "40:F3,80:F2,120:F5" --frames 200 --screenshot s.png --log l.jsonl --save v.npz"""


def _epilog() -> str:
    from clothbench.viewer.keys import KEYS_TEXT, help_lines

    return EPILOG.format(keys="\n".join(f"  {key:<11} {what}" for key, what in help_lines()), names=KEYS_TEXT)


def register(subparsers) -> None:
    from clothbench.viewer import ViewSettings

    d = ViewSettings()
    p = add_documented_command(
        subparsers,
        "view",
        "the cloth live in a window: switch backend and grid by key, with the profiler",
        __doc__,
        _epilog(),
    )
    add_scene_args(p, run_length=False)
    p.add_argument("--backend", default="glsl", help="the backend it starts on (default glsl)")
    p.add_argument("--strict", action="store_true", help="every backend bit-exact with the numpy f32 reference")
    p.add_argument("--generic", action="store_true", help="one kernel for every scene (no specialisation)")
    p.add_argument(
        "--steps-per-frame",
        type=int,
        default=d.steps_per_frame,
        help=f"steps simulated per frame (default {d.steps_per_frame})",
    )
    p.add_argument("--frames", type=int, help="stop after this many frames (default: when the window closes)")
    p.add_argument("--keys", default="", help='keys to press, FRAME:KEY pairs: "40:F3,80:F2,120:P"')
    p.add_argument("--screenshot", help="write the last frame to this .png")
    p.add_argument("--record", help="write every frame to this .gif")
    p.add_argument("--fps", type=float, default=d.fps, help=f"--record playback frames per second (default {d.fps:g})")
    p.add_argument("--save", help="write the final pos and prev to this .npz")
    p.add_argument("--log", help="write one JSON line per frame to this .jsonl")
    p.add_argument("--size", type=size, default=d.size, help="window size WIDTHxHEIGHT (default 1280x720)")
    p.add_argument(
        "--headless",
        action="store_true",
        help="moderngl-window's headless window (EGL): no display needed, nothing shown",
    )
    p.add_argument(
        "--from",
        dest="from_usd",
        metavar="FILE.usd",
        help="play back the frames a `run --export` USD holds instead of simulating (its scene; one frame "
        "per viewer frame unless --steps-per-frame says otherwise)",
    )
    defaults = {k: p.get_default(k) for k in ("scene", "backend", "steps_per_frame")}
    p.set_defaults(func=cmd_view, defaults=defaults)  # --from refuses what sets up a simulation


def _output(path: str | None, suffix: str | None, option: str) -> None:
    if path is None:
        return
    if suffix and Path(path).suffix.lower() != suffix:
        raise ClothbenchError(f"{option} takes a {suffix} file, got {path!r}")
    from clothbench.harness.preflight import check_writable

    folder = Path(path).parent
    if not folder.is_dir():
        raise ClothbenchError(f"{option}: no folder {folder} to write {Path(path).name} into")
    check_writable(path, option)  # now, not after the session


def settings_from_args(args):
    from clothbench.viewer import ViewSettings
    from clothbench.viewer.keys import parse_script

    if args.frames is not None and args.frames < 1:
        raise ClothbenchError(f"--frames must be >= 1, got {args.frames}")
    if args.steps_per_frame < 1:
        raise ClothbenchError(f"--steps-per-frame must be >= 1, got {args.steps_per_frame}")
    keys = parse_script(args.keys)
    late = [f for f in keys if args.frames is not None and f > args.frames]
    if late:
        raise ClothbenchError(f"--keys presses a key at frame {min(late)}, after the last (--frames {args.frames})")
    if args.headless and args.frames is None:
        raise ClothbenchError("--headless needs --frames N: there is no window to close")
    w, h = args.size
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise ClothbenchError(f"--size must be between 64x64 and 8192x8192, got {w}x{h}")
    if not args.fps > 0:
        raise ClothbenchError(f"--fps must be > 0, got {args.fps}")
    for path, suffix, option in (
        (args.screenshot, ".png", "--screenshot"),
        (args.record, ".gif", "--record"),
        (args.save, ".npz", "--save"),
        (args.log, None, "--log"),
    ):
        _output(path, suffix, option)
    return fields_from_args(ViewSettings, args, keys=keys)


def cmd_view(args) -> int:
    from clothbench.backends import BackendOptions, check_name
    from clothbench.harness.preflight import check_memory
    from clothbench.viewer import view

    if args.from_usd is not None:
        return view_from(args)
    check_name(args.backend)
    settings = settings_from_args(args)
    setup = setup_from_args(args)
    check_memory([setup.scene.grid], reference=False)
    options = BackendOptions(strict=args.strict, generic=args.generic)
    report = view(setup.scene, setup.solver, args.backend, options, settings)
    wrote = f"; wrote {', '.join(report.files)}" if report.files else ""
    print(f"viewed {report.frames} frames, {report.step} steps, ending on {report.backend}{wrote}")
    return 0


def view_from(args) -> int:
    """`view --from FILE.usd`: the file's frames in the window, nothing simulated."""
    import dataclasses

    from clothbench.backends import BackendOptions
    from clothbench.reports.export import read_usd, usd_file
    from clothbench.viewer import view
    from clothbench.viewer.playback import Playback

    d = args.defaults
    simulating = {
        "--scene": args.scene != d["scene"],
        "--grid": args.grid is not None,
        "--dt": args.dt is not None,
        "--backend": args.backend != d["backend"],
        "--strict": args.strict,
        "--generic": args.generic,
        "--solver": args.solver is not None,
    }
    if given := [option for option, used in simulating.items() if used]:
        raise ClothbenchError(f"{given[0]} sets up a simulation, and --from plays the file's frames: leave it out")
    settings = settings_from_args(args)
    exported = read_usd(usd_file(args.from_usd))
    if args.steps_per_frame == d["steps_per_frame"]:  # one of the file's frames per viewer frame
        settings = dataclasses.replace(settings, steps_per_frame=exported.info.every)
    source = Playback(exported)
    report = view(exported.scene, exported.solver, source.name, BackendOptions(), settings, source=source)
    wrote = f"; wrote {', '.join(report.files)}" if report.files else ""
    print(f"played {report.frames} frames of {exported.path} ({exported.frames} in it){wrote}")
    return 0
