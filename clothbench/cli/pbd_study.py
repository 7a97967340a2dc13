"""`clothbench pbd-study`: substeps against iterations at equal cost (analysis/pbd_study.py),
each row written as measured (harness/study_csv.py), and its figure: error against cost, one
line per substep count. docs/pbd-study.md has the reasoning and the measured answer."""

from __future__ import annotations

import math
import sys
from pathlib import Path

from clothbench.cli.args import int_list, sigterm_interrupts
from clothbench.cli.study_files import add_resume_args, say_interrupted
from clothbench.errors import ClothbenchError

DEFAULT_OUT = "results/pbd-study/pbd-study.csv"

STUDY_KEY = ("scene", "method", "substeps", "iterations")
STUDY_GRID = 32  # the accuracy study's grid: the reference runs in seconds, the ranking is the same at 64
STUDY_TIME_S = 0.5  # 30 frames: the curtain is on the sphere, the drape in its first swing


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "pbd-study", help="PBD substeps against iterations at equal cost: error against a converged reference"
    )
    p.add_argument("--scenes", default="drape,curtain", help="comma-separated scenes (default drape,curtain)")
    p.add_argument(
        "--costs",
        type=int_list("--costs", 1),
        default=[5, 10, 20, 40],
        help="comma-separated substeps x iterations products; every divisor pair of each is run (default 5,10,20,40)",
    )
    p.add_argument(
        "--methods",
        default="jacobi,coloured",
        help="PBD methods (default jacobi,coloured); newton: the Newton XPBD peer, timed on its own run",
    )
    p.add_argument("--grid", type=int, default=STUDY_GRID, help=f"particles per side (default {STUDY_GRID})")
    p.add_argument("--time", type=float, default=STUDY_TIME_S, help=f"simulated time, s (default {STUDY_TIME_S})")
    p.add_argument(
        "--damping",
        type=float,
        default=0.0,
        help="b (N s/m), default 0: PBD's drag and the springs' differ at the edges (docs/pbd-study.md)",
    )
    p.add_argument(
        "--cost-backends",
        default="numpy,opencl",
        help="backends whose float32 ms/step is measured (default numpy,opencl; 'none' for error only)",
    )
    p.add_argument("--out", default=DEFAULT_OUT, help="CSV path (rows written as measured); PNG beside")
    add_resume_args(p, "the same as --resume: an unstable pair is a row, so nothing is retried")
    p.set_defaults(func=cmd_pbd_study)


def _names(text: str, what: str, known) -> list[str]:
    names = list(dict.fromkeys(s.strip() for s in text.split(",") if s.strip()))
    bad = [n for n in names if n not in known]
    if not names or bad:
        raise ClothbenchError(f"{what} takes {', '.join(known)} (comma-separated), got {text!r}")
    return names


def cmd_pbd_study(args) -> int:
    from clothbench.analysis.convergence import steps_for
    from clothbench.analysis.pbd_study import (
        FRAME_DT,
        PEER_METHODS,
        PbdStudyRow,
        measure_pair,
        pairs_at,
        study_reference,
    )
    from clothbench.backends import BACKENDS
    from clothbench.harness.preflight import check_writable
    from clothbench.harness.study_csv import StudyFile, cell, cells, from_cells
    from clothbench.progress import LazyProgress
    from clothbench.model.scene import builtin_scenes, load_scene
    from clothbench.model.solver import PBD_METHODS

    sigterm_interrupts()
    methods = _names(args.methods, "--methods", PBD_METHODS + PEER_METHODS)
    if args.grid < 4:
        raise ClothbenchError(f"--grid must be >= 4, got {args.grid}")
    if not (math.isfinite(args.time) and args.time > 0):
        raise ClothbenchError(f"--time must be > 0, got {args.time}")
    steps_for(args.time, FRAME_DT)  # a time that is not whole frames, refused before any work
    if not (math.isfinite(args.damping) and args.damping >= 0):
        raise ClothbenchError(f"--damping must be >= 0, got {args.damping}")
    cost_backends = (
        []
        if args.cost_backends.strip() == "none"
        else _names(args.cost_backends, "--cost-backends", [n for n, e in BACKENDS.items() if e.pbd is not None])
    )
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    if not names:
        raise ClothbenchError(f"--scenes names no scene (give e.g. {','.join(builtin_scenes())})")
    scenes = [load_scene(n).replace(grid=args.grid, damping=args.damping) for n in names]
    out = Path(args.out)
    png = out.with_suffix(".png")
    for path in (out, png):
        check_writable(path, make_folders=args.out == DEFAULT_OUT)  # results/pbd-study/ made
    plan = [(s, m, sub, it) for s in scenes for m in methods for c in args.costs for sub, it in pairs_at(c)]
    plan = list({(s.name, m, sub, it): (s, m, sub, it) for s, m, sub, it in plan}.values())  # 20 = 2 x 10 = ...
    key = lambda name, m, sub, it: (name, m, cell(sub), cell(it))  # noqa: E731
    settings = {
        "grid": cell(args.grid),
        "damping": cell(args.damping),
        "time_s": cell(args.time),
        "frame_dt": cell(FRAME_DT),
    }
    columns = [f.name for f in PbdStudyRow.__dataclass_fields__.values()]
    resume = args.resume or args.retry_failed
    planned = {key(s.name, m, sub, it) for s, m, sub, it in plan}
    with StudyFile(out, columns, STUDY_KEY, settings, "pbd-study", resume=resume, planned=planned) as f:
        have = f.keys()
        todo = [p for p in plan if key(p[0].name, *p[1:]) not in have]
        refs = {}
        measured = {}
        try:
            with LazyProgress(len(todo) + len(scenes), "pbd-study") as progress:
                done = 0
                for scene, method, sub, it in todo:
                    if scene.name not in refs:
                        progress.update(done, f"{scene.name}: converged float64 mass-spring reference")
                        refs[scene.name] = study_reference(scene, args.time)
                    progress.update(done, f"{scene.name} {method} {sub} substeps x {it} iterations")
                    row = measure_pair(scene, method, sub, it, args.time, refs[scene.name], cost_backends)
                    f.append(cells(row.as_dict()))
                    measured[key(scene.name, method, sub, it)] = row
                    done += 1
        except KeyboardInterrupt:
            say_interrupted(f)
            raise
        by_key = {f.key(r): r for r in f.rows}
        rows = [measured.get(k) or from_cells(PbdStudyRow, by_key[k]) for k in (key(s.name, *p) for s, *p in plan)]
        f.rewrite([cells(r.as_dict()) for r in rows])
    plot_study(rows, png)
    _print_study(rows)
    print(f"wrote {out}, {png}")
    return 0


def _print_study(rows) -> None:
    from clothbench.analysis.pbd_study import best_per_cost, how_busy

    r0 = rows[0]
    print(
        f"clothbench pbd-study: {r0.grid}x{r0.grid}, dt = 1/60 s, t = {r0.time_s:g} s, b = {r0.damping:g}; "
        f"error: RMS distance to the converged float64 mass-spring answer"
    )
    print(
        f"{'scene':<9}{'method':<10}{'cost':>5}{'substeps':>9}{'iters':>6}{'rms (mm)':>10}{'max (mm)':>10}"
        f"{'numpy ms':>10}{'opencl ms':>10}{'newton ms':>10}"
    )
    for r in rows:
        err = f"{r.rms * 1e3:>10.2f}{r.max * 1e3:>10.2f}" if r.status == "ok" else f"{r.status:>20}"
        print(
            f"{r.scene:<9}{r.method:<10}{r.cost:>5}{r.substeps:>9}{r.iterations:>6}{err}"
            f"{r.ms_numpy:>10.3f}{r.ms_opencl:>10.3f}{r.ms_newton:>10.3f}"
        )
    print("best pair per cost (smallest RMS):")
    for (scene, method, cost), r in best_per_cost(rows).items():
        print(f"  {scene} {method} cost {cost}: {r.substeps} x {r.iterations} ({r.rms * 1e3:.2f} mm)")
    if any(r.busy for r in rows):  # as `run` warns: the figures are printed, and said not to hold
        print(f"clothbench: warning: the ms may not hold: {how_busy(rows)}", file=sys.stderr)


def plot_study(rows, path: Path) -> None:
    """The study's figure (reports/accuracy_plots.py's pbd_study_figure) as the PNG at `path`."""
    from matplotlib import rc_context

    from clothbench.reports.accuracy_plots import pbd_study_figure
    from clothbench.reports.figures_common import REPRODUCIBLE

    fig = pbd_study_figure(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    with rc_context(REPRODUCIBLE):
        fig.savefig(path, dpi=130)
