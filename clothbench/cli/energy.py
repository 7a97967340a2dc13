"""`clothbench energy`: the drape's energy over a study's length on every backend mode
(analysis/energy_study.py), each row written as measured (harness/study_csv.py).
docs/accuracy.md ("Energy") has the reasoning; results/energy/ the committed study."""

from __future__ import annotations

from pathlib import Path

from clothbench.cli.args import sigterm_interrupts
from clothbench.cli.study_files import add_resume_args, say_interrupted
from clothbench.errors import ClothbenchError

DEFAULT_OUT = "results/energy/energy-drape-8.csv"
STUDY_KEY = ("backend", "label", "case")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "energy", help="the drape's energy: undamped within its band, damped never rising (every backend mode)"
    )
    p.add_argument("--backends", default="all", help="comma-separated names, or all (default)")
    p.add_argument("--scene", default="drape", help="built-in scene name or a .toml file (default drape)")
    p.add_argument("--grid", type=int, default=8, help="particles per side (default 8: k/m per spring is n's alone)")
    p.add_argument("--steps", type=int, default=100_000, help="undamped steps (default 100000: 50 s)")
    p.add_argument("--damped-steps", type=int, default=20_000, help="damped steps (default 20000: 10 s)")
    p.add_argument("--every", type=int, default=100, help="steps between energy readings (default 100)")
    p.add_argument("--out", default=DEFAULT_OUT, help=f"CSV path (rows written as measured; default {DEFAULT_OUT})")
    add_resume_args(p, "the same as --resume, and the failed rows measured again")
    p.set_defaults(func=cmd_energy)


def cmd_energy(args) -> int:
    from clothbench.analysis.energy_study import CASES, EnergyRow, measure_energy
    from clothbench.cli.accuracy import variants_for
    from clothbench.harness.preflight import check_memory, check_writable
    from clothbench.harness.study_csv import StudyFile, cell, cells
    from clothbench.model.scene import load_setup
    from clothbench.progress import LazyProgress

    sigterm_interrupts()
    if args.grid < 3:
        raise ClothbenchError(f"--grid must be >= 3, got {args.grid}")
    if args.every < 1:
        raise ClothbenchError(f"--every must be >= 1, got {args.every}")
    steps = {"undamped": args.steps, "damped": args.damped_steps}
    for case, n in steps.items():
        option = "--steps" if case == "undamped" else "--damped-steps"
        if n < 2 * args.every or n % args.every:
            raise ClothbenchError(f"{option} must be a multiple of --every ({args.every}), two or more, got {n}")
    setup = load_setup(args.scene)
    scene, solver = setup.scene.replace(grid=args.grid), setup.solver
    if solver.name != "verlet":
        raise ClothbenchError(f"scene {args.scene} is stepped by {solver.name}: the energy study is Verlet's")
    out = Path(args.out)
    check_writable(out, make_folders=args.out == DEFAULT_OUT)
    check_memory([scene.grid], ("f64",))
    variants = variants_for(args.backends, [solver])  # Verlet's alone: the only solver asked
    plan = [(v, case) for v in variants for case in CASES]
    key = lambda v, case: (v.backend, v.name, case)  # noqa: E731
    settings = {"scene": scene.name, "grid": cell(scene.grid), "dt": cell(solver.dt), "every": cell(args.every)}
    settings["steps"] = lambda row: cell(steps.get(row.get("case"), ""))  # each case its own length
    columns = list(EnergyRow.__dataclass_fields__)
    resume = args.resume or args.retry_failed
    retry = ("failed",) if args.retry_failed else ()
    planned = {key(v, case) for v, case in plan}
    with StudyFile(out, columns, STUDY_KEY, settings, "energy", resume=resume, retry=retry, planned=planned) as f:
        have = f.keys()
        todo = [(v, case) for v, case in plan if key(v, case) not in have]
        try:
            with LazyProgress(len(todo), "energy") as progress:
                for done, (v, case) in enumerate(todo):
                    progress.update(done, f"{v.name}: {case}, {steps[case]} steps")
                    row = measure_energy(v, scene, solver, case, steps[case], args.every)
                    f.append(cells(row.as_dict()))
                    _print_row(row)
        except KeyboardInterrupt:
            say_interrupted(f)
            raise
    print(f"wrote {out}")
    return 0


def _print_row(r) -> None:
    if r.status != "ok":
        print(f"{r.label} {r.case}: {r.status}")
    elif r.case == "undamped":
        print(f"{r.label} undamped: |E - E0| <= {r.worst_drift_j:.4g} J (band {r.band_j:.4g} J)")
    else:
        print(
            f"{r.label} damped: largest rise {r.max_rise_j:.3g} J (rounding {r.rounding_j:.3g} J), "
            f"lost {r.e0_j - r.e_end_j:.4g} J"
        )
