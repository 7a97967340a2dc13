"""`clothbench render`: draw a scene as it runs, into a PNG, a folder of PNG frames or a GIF."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from clothbench.cli.args import add_documented_command, add_scene_args, setup_from_args
from clothbench.errors import ClothbenchError
from clothbench.variant_names import GL_PROVIDERS

EPILOG = """\
A frame is drawn after every --every steps, --frames times: frame f shows the cloth after
f x EVERY steps (f = 1 .. FRAMES; precisely, as the last of those steps read it, which is
what its normals belong to). --out decides what is written: cloth.png (the last frame only),
cloth.gif (every frame, looping) or frames/ (frame_0001.png, ...). The glsl and
glsl-compute backends are drawn from their own textures / buffers on the GPU; other
backends' positions are read back and uploaded each frame. Without --backend the scene is
stepped on glsl, or on numpy where glsl does not take the scene (a mesh or a motion: said in
a note). Mesh colliders are drawn with their own triangles, moving colliders where they are
at the frame's time. Example:
  clothbench render --scene sphere --frames 60 --out cloth.gif"""


DEFAULT_BACKEND = "glsl"  # draws from its own textures: nothing read back
FALLBACK_BACKEND = "numpy"  # the reference, which takes every scene


def size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"--size takes WIDTHxHEIGHT in pixels, like 640x480, got {text!r}")
    return int(match.group(1)), int(match.group(2))


def register(subparsers) -> None:
    from clothbench.reports.render import RenderSettings

    d = RenderSettings()
    p = add_documented_command(
        subparsers,
        "render",
        "draw the cloth and colliders offscreen into a PNG, PNG frames or an animated GIF",
        __doc__,
        EPILOG,
    )
    add_scene_args(p, run_length=False)
    p.add_argument(
        "--backend",
        help=f"the backend that simulates (default {DEFAULT_BACKEND}, or {FALLBACK_BACKEND} for a scene it does not take)",
    )
    p.add_argument("--frames", type=int, default=d.frames, help=f"frames to draw (default {d.frames})")
    p.add_argument(
        "--every",
        "--steps-per-frame",
        dest="every",
        type=int,
        default=d.every,
        help=f"steps between frames (default {d.every})",
    )
    p.add_argument("--out", default="cloth.gif", help="cloth.png, cloth.gif or frames/ (default cloth.gif)")
    p.add_argument("--size", type=size, default=d.size, help="image size WIDTHxHEIGHT (default 640x480)")
    p.add_argument("--fps", type=float, default=d.fps, help=f"GIF frames per second (default {d.fps:g})")
    p.add_argument("--strict", action="store_true", help="simulate bit-exact with the numpy f32 reference")
    p.add_argument("--generic", action="store_true", help="GL backends: one kernel for every scene")
    p.add_argument("--gl", choices=GL_PROVIDERS, default=GL_PROVIDERS[0], help="GL context provider")
    p.add_argument(
        "--from",
        dest="from_usd",
        metavar="FILE.usd",
        help="draw the frames a `run --export` USD holds instead of simulating: its scene, grid and colliders "
        "(a .png: one frame, --frame; a .gif or folder/: every frame)",
    )
    p.add_argument(
        "--frame", type=int, help="with --from and a .png: the frame to draw (0 the start; default the last)"
    )
    p.set_defaults(func=cmd_render, default_scene=p.get_default("scene"))  # --from refuses another


def cmd_render(args) -> int:
    if args.from_usd is not None:
        return render_from(args)
    if args.frame is not None:
        raise ClothbenchError("--frame picks a frame of --from FILE.usd: add --from")
    from clothbench.backends import BackendOptions, check_name
    from clothbench.progress import LazyProgress
    from clothbench.harness.preflight import check_memory, check_writable
    from clothbench.reports.render import RenderSettings, check_settings, output_kind, render

    if args.backend is not None:
        check_name(args.backend)
    output_kind(args.out)  # bad input fails before any work
    settings = RenderSettings(frames=args.frames, every=args.every, size=args.size, fps=args.fps)
    check_settings(settings)
    setup = setup_from_args(args)
    scene, solver = setup.scene, setup.solver
    if args.backend is None:
        args.backend = default_backend(scene, solver.name)
    check_memory([scene.grid], reference=False)  # before any work, as every output path is
    folder = output_kind(args.out) == "folder"
    first = Path(args.out) / "frame_0001.png" if folder else Path(args.out)
    check_writable(first, "--out", new_folder=folder)
    options = BackendOptions(strict=args.strict, generic=args.generic, gl=args.gl)
    with LazyProgress(settings.frames, f"render {scene.name} on {args.backend}") as progress:
        report = render(scene, solver, args.backend, options, settings, args.out, on_frame=progress.update)
    for note in report.notes:
        print(f"note: {note}", file=sys.stderr)
    w, h = settings.size
    where = args.out if len(report.files) == 1 else f"{len(report.files)} PNGs in {args.out}"
    simulated = report.steps * solver.dt
    print(
        f"wrote {where}: {scene.name} on {args.backend}, n={scene.grid}, {settings.frames} frames "
        f"x {settings.every} steps ({simulated:.3g} s simulated), {w}x{h}; "
        f"simulate {report.simulate_s:.2f} s, draw {report.draw_s:.2f} s, write {report.write_s:.2f} s"
    )
    return 0


def render_from(args) -> int:
    """`render --from FILE.usd`: the file's frames drawn, nothing simulated."""
    from clothbench.harness.preflight import check_writable
    from clothbench.reports.export import read_usd, usd_file
    from clothbench.reports.render import RenderSettings, check_settings, output_kind, render_exported

    d = RenderSettings()
    simulating = {
        "--scene": args.scene != args.default_scene,
        "--grid": args.grid is not None,
        "--dt": args.dt is not None,
        "--backend": args.backend is not None,
        "--strict": args.strict,
        "--generic": args.generic,
        "--solver": args.solver is not None,
        "--frames": args.frames != d.frames,
        "--every": args.every != d.every,
    }
    if given := [option for option, used in simulating.items() if used]:
        raise ClothbenchError(f"{given[0]} sets up a simulation, and --from draws the file's frames: leave it out")
    kind = output_kind(args.out)
    if args.frame is not None and kind != "png":
        raise ClothbenchError(f"--frame draws one frame into a .png, and --out {args.out} is a {kind}")
    settings = RenderSettings(size=args.size, fps=args.fps)
    check_settings(settings)
    first = Path(args.out) / "frame_0000.png" if kind == "folder" else Path(args.out)
    check_writable(first, "--out", new_folder=kind == "folder")
    exported = read_usd(usd_file(args.from_usd))
    if args.frame is not None:
        exported.check_frame(args.frame)
    report = render_exported(exported, settings.size, args.out, args.frame, settings.fps, args.gl)
    w, h = settings.size
    where = args.out if len(report.files) == 1 else f"{len(report.files)} PNGs in {args.out}"
    print(
        f"wrote {where}: {report.frames} of the {exported.frames} frames of {exported.path} "
        f"({exported.scene.name}, n={exported.scene.grid}, last drawn after step {report.steps}), {w}x{h}"
    )
    return 0


def default_backend(scene, solver: str) -> str:
    """glsl, or numpy (said in a note on stderr) where glsl does not take the scene."""
    from clothbench.backends import capabilities

    refusal = capabilities(DEFAULT_BACKEND, solver).scene_refusal(DEFAULT_BACKEND, scene, solver)
    if refusal is None:
        return DEFAULT_BACKEND
    print(f"note: {refusal}: stepped on {FALLBACK_BACKEND} (choose another with --backend)", file=sys.stderr)
    return FALLBACK_BACKEND
