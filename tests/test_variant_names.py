"""A variant's names are spelled and read back in one place (clothbench/variant_names.py):
for every variant the plan produces, reading a name back gives the variant's words and
spelling them again gives the same name; every mode a committed CSV holds reads back to
itself; and the command line advise prints, read by the CLI's own parser, runs the variant it
names. Option choices are one list each, the CLI's and the backends' alike."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

import clothbench.harness.plan as plan_module
from clothbench.analysis.advise import Configuration
from clothbench.backends import BACKENDS, BackendOptions, backend_class
from clothbench.backends.base import MESH_COLLISIONS, Availability, Capabilities
from clothbench.cli import build_parser
from clothbench.cli.args import options_from_args, setup_from_args
from clothbench.harness.plan import Variant, plan_variants
from clothbench.model.scene import load_setup
from clothbench.model.solver import ITERATIVE
from clothbench.variant_names import (
    GL_PROVIDERS,
    PRECISIONS,
    TRANSFERS,
    Mode,
    VariantName,
    base_mode,
    model_name,
    model_short,
    solver_model,
)

REPO = Path(__file__).resolve().parents[1]
# our own backends, whose classes load without their runtimes: each must be in the plan below
OWN = ("numpy", "c", "opencl", "glsl", "glsl-compute", "cuda")


def every_variant(monkeypatch) -> list[tuple[str, Variant]]:
    """(scene, variant) for every registry backend whose class loads here, usable or not:
    each solver (PBD and VBD with substeps too), local sizes, generic twins, normals, osmesa, and on a
    mesh scene each mesh algorithm."""
    monkeypatch.setattr(plan_module, "availability", lambda name: Availability(True))
    out = []
    for scene_name, collisions in (("drape", ()), ("torus", MESH_COLLISIONS)):
        setup = load_setup(scene_name)
        solvers = [
            setup.solver_for("verlet"),
            setup.solver_for("pbd-jacobi"),
            setup.solver_for("pbd-coloured").replace(substeps=2),
            setup.solver_for("vbd"),
            setup.solver_for("vbd").replace(iterations=40, substeps=3),
        ]
        for base in (BackendOptions(), BackendOptions(normals=True, gl="osmesa")):
            variants, _ = plan_variants(BACKENDS, solvers, base, (32,), "both", setup.scene, collisions)
            out += [(scene_name, v) for v in variants]
    assert {v.backend for _, v in out} >= set(OWN)
    assert any(v.solver.name == "vbd" for _, v in out)
    return out


def test_every_planned_variant_reads_back_to_its_words_and_spells_back_to_its_name(monkeypatch):
    for _, v in every_variant(monkeypatch):
        assert Mode.parse(v.mode) == v.mode_words, v.mode
        assert Mode.parse(v.mode).spell() == v.mode
        iterative = v.solver.name in ITERATIVE
        words = VariantName(
            v.backend, v.mode_words, v.solver.iterations if iterative else None, v.solver.substeps if iterative else 1
        )
        assert VariantName.parse(v.name) == words, v.name
        assert VariantName.parse(v.name).spell() == v.name


def test_the_model_key_without_its_constants_is_the_solver_model():
    setup = load_setup("drape")
    for spec in ("verlet", "pbd-jacobi", "pbd-coloured", "vbd"):
        solver = setup.solver_for(spec).replace(substeps=2) if spec != "verlet" else setup.solver_for(spec)
        iterations = getattr(solver, "iterations", None)
        assert model_short(model_name(solver)) == solver_model(spec, iterations, getattr(solver, "substeps", 1))
    assert model_name(setup.solver_for("pbd-jacobi")) == "pbd-jacobi/10it, relaxation 1.5"
    assert model_name(setup.solver_for("vbd").replace(chebyshev_rho=0.9)) == "vbd/10it, chebyshev_rho 0.9"


def test_a_vbd_name_reads_back_to_its_words():
    name = VariantName.parse("numpy f32/vbd/40itx3")
    assert name == VariantName("numpy", Mode(precision="f32", vbd=True), 40, 3)
    assert name.spell() == "numpy f32/vbd/40itx3"


def committed_modes() -> set[str]:
    modes = set()
    for path in [*REPO.glob("results/**/*.csv"), *REPO.glob("tests/data/*.csv")]:
        with open(path, newline="") as f:
            modes |= {r["mode"] for r in csv.DictReader(f) if r.get("mode") not in (None, "", "?")}
    return modes


def test_every_mode_in_a_committed_csv_spells_back_to_itself():
    modes = committed_modes()
    assert len(modes) > 50  # the sweeps, accuracy and stability runs under results/
    for mode in modes:
        assert Mode.parse(mode).spell() == mode


@pytest.mark.parametrize(
    "mode, base",
    [
        ("fast/resident/ls=32/rows/v16/wg=32", "fast/resident"),
        ("f32/strict/threads=2", "f32/strict"),
        ("strict/ls=64/wg=64/mesh=naive", "strict"),
        ("strict/osmesa", "strict/osmesa"),
        ("default", "default"),
    ],
)
def test_the_base_mode_drops_the_kernel_shape_tuned_for_the_grid(mode, base):
    assert base_mode(mode) == base


def test_advises_command_line_runs_the_variant_it_names(monkeypatch):
    parser = build_parser()
    for scene_name, v in every_variant(monkeypatch):
        config = Configuration(v.backend, v.options, v.solver, grid=8, steps=3, label=v.name)
        argv = config.run_args(scene_name)
        args = parser.parse_args(argv[1:])
        options, solver = options_from_args(args), setup_from_args(args).solver
        assert (args.backend, options, solver) == (v.backend, v.options, v.solver), " ".join(argv)
        assert Variant(args.backend, options, solver).name == config.label


def test_each_option_is_offered_from_its_one_list():
    run = next(a for a in build_parser()._actions if a.dest == "command").choices["run"]
    choices = {a.dest: a.choices for a in run._actions}
    assert tuple(choices["precision"]) == PRECISIONS and tuple(choices["gl"]) == GL_PROVIDERS
    for name in BACKENDS:
        for solver in BACKENDS[name].solvers():
            try:
                caps = backend_class(name, solver).capabilities
            except Exception:  # a peer whose package is missing here declares nothing here
                continue
            assert set(caps.precisions) <= set(PRECISIONS)
            assert caps.transfers == (TRANSFERS.get(name, ()) if solver == "verlet" else ()), (name, solver)
    refusal = Capabilities(gl=True).refusal("glsl", BackendOptions(gl="wayland"))
    assert refusal == f"glsl does not take --gl wayland (it takes: {', '.join(GL_PROVIDERS)})"
