"""The command line: the must-show run, backends listing, and one-line errors for bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest

from clothbench.cli import main

from conftest import require

RUN_KEYS = {
    "backend",
    "device",
    "driver",
    "grid",
    "particles",
    "springs",
    "steps",
    "dt",
    "precision",
    "ms_per_step",
    "finite",
    "max_penetration",
}


def test_run_prints_json_from_a_real_process():
    # as a user types it (through the installed package)
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "clothbench",
            "run",
            "--backend",
            "numpy",
            "--scene",
            "sphere",
            "--grid",
            "64",
            "--steps",
            "300",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert RUN_KEYS <= set(result)
    assert result["grid"] == 64 and result["particles"] == 4096 and result["springs"] == 47_380
    assert result["finite"] is True and result["ms_per_step"] > 0
    assert result["max_penetration"] < 1e-6


def test_run_saves_pos_and_prev(tmp_path, capsys):
    path = tmp_path / "state.npz"
    assert main(["run", "--grid", "8", "--steps", "5", "--save", str(path), "--json"]) == 0
    saved = np.load(path)
    assert saved["pos"].shape == (64, 4) and saved["prev"].shape == (64, 4)
    assert saved["pos"].dtype == np.float32


def test_run_table_names_what_was_run(capsys):
    assert main(["run", "--grid", "8", "--steps", "3", "--precision", "f64"]) == 0
    out = capsys.readouterr().out
    assert "numpy (f64)" in out and "8 x 8" in out and "ms/step" in out


def test_backends_lists_every_platform_with_a_reason(capsys):
    assert main(["backends", "--json"]) == 0
    rows = {r["backend"]: r for r in json.loads(capsys.readouterr().out)}
    assert {"numpy", "opencl", "glsl", "glsl-compute", "cuda"} <= set(rows)
    assert rows["numpy"]["usable"]
    for r in rows.values():
        assert r["usable"] or r["reason"], f"{r['backend']} is unusable without a reason"


def test_backends_named_are_the_only_ones_probed(capsys, monkeypatch):
    import clothbench.backends as backends
    from clothbench.cli import backends as command

    probed = []
    real = backends.availability
    monkeypatch.setattr(backends, "availability", lambda name: probed.append(name) or real(name))
    monkeypatch.setattr(command, "opencl_devices", lambda retune: probed.append("opencl devices") or (None, ""))
    assert main(["backends", "numpy", "c", "numpy", "--json"]) == 0
    assert [r["backend"] for r in json.loads(capsys.readouterr().out)] == ["numpy", "c"] == probed
    assert main(["backends", "opencl", "--json"]) == 0
    assert probed[2:] == ["opencl", "opencl devices"]


@pytest.mark.parametrize(
    "argv, words",
    [
        (["backends", "numpy", "fortran"], "unknown backend 'fortran'"),
        (["backends", "numpy", "--retune"], "add opencl to the backends named"),
    ],
)
def test_backends_refuses_an_unknown_name_or_a_retune_without_opencl(argv, words, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("backend", ["c", "opencl", "glsl", "glsl-compute", "cuda"])
def test_backends_lists_the_driver_run_prints(backend, capsys):
    # one fact, said twice: what `backends` lists (the probe's) is what `run` names as the
    # driver of a run with no --device, and it is the run's own (Backend.driver)
    from clothbench.backends import availability
    from clothbench.reports.tables import print_backends

    require(backend)
    assert main(["run", "--backend", backend, "--grid", "8", "--steps", "2", "--json"]) == 0
    ran = json.loads(capsys.readouterr().out)
    probe = availability(backend)
    assert ran["driver"] and ran["driver"] == probe.driver, (ran["driver"], probe.driver)
    row = {"backend": backend, "kind": "clothbench", "usable": True, "device": probe.device, "driver": probe.driver}
    print_backends([row])
    listed = "".join(
        line.split("│")[4].strip() + " " for line in capsys.readouterr().out.splitlines() if line.count("│") == 5
    )
    assert " ".join(f"driver: {probe.driver}".split()) in " ".join(listed.split()), listed


@pytest.mark.parametrize(
    "argv, message",
    [
        (["run", "--backend", "vulkan"], "unknown backend 'vulkan'"),
        (["run", "--grid", "2"], "grid must be an integer >= 3"),
        (["run", "--grid", "ten"], "invalid int value"),
        (["run", "--steps", "0"], "steps must be an integer >= 1"),
        (["run", "--dt", "0"], "dt must be > 0"),
        (["run", "--dt=-1e-3"], "dt must be > 0"),
        # a negative number is a value, so the range check answers
        (["run", "--dt", "-1e-3"], "dt must be > 0"),
        (["run", "--dt", "-inf"], "dt must be a finite number"),
        (["run", "--grid", "-5"], "grid must be an integer >= 3"),
        (["sweep", "--backends", "numpy", "--row-timeout", "-1E+3"], "--row-timeout must be > 0"),
        # item 2: the fix, not where newton runs
        (["run", "--backend", "newton"], "newton has no verlet solver: use --solver pbd"),
        # item 3: which backends run f64, from their Capabilities
        (["run", "--backend", "opencl", "--precision", "f64"], "f64 runs on: numpy, c"),
        # item 10: options that would be ignored are refused
        (["run", "--strict", "--precision", "f64"], "numpy does not take --strict"),
        (["run", "--backend", "numpy", "--strict"], "numpy does not take --strict"),
        (["run", "--pbd-method", "jacobi"], "--pbd-method applies to the pbd solver only"),
        (["run", "--iterations", "4"], "--iterations applies to the pbd and vbd solvers only"),
        (["run", "--retune"], "numpy does not take --retune"),
        (["run", "--dt", "nan"], "dt must be a finite number"),
        (["run", "--scene", "nowhere.toml"], "cannot read scene file"),
        (["run", "--scene", "spheer"], "unknown scene 'spheer'"),
        (["run", "--backend", "numpy", "--local-size", "0"], "--local-size must be >= 1"),
        (["run", "--frobnicate"], "unrecognized arguments"),
        (["fly"], "invalid choice"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(argv, message, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert message in err


@pytest.mark.parametrize(
    "text, message",
    [
        ("[cloth]\nmass = -1.0\n", "mass must be > 0"),
        ("[cloth]\nstiffness = nan\n", "stiffness must be a finite number"),
        ("[pins]\nindices = [5000]\n", "outside the grid"),
        ("[cloth]\ngrid = 16\nstiff = 3\n", "unknown key 'stiff'"),
        ("this is not toml", "not valid TOML"),
    ],
)
def test_bad_scene_file_is_one_line_and_exit_2(tmp_path, text, message, capsys):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    assert main(["run", "--scene", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err


def test_blow_up_exits_3_naming_the_step(tmp_path, capsys):
    path = tmp_path / "stiff.toml"
    path.write_text("[cloth]\ngrid = 8\nstiffness = 100000.0\n[sim]\ndt = 0.002\nsteps = 100\n")
    assert main(["run", "--scene", str(path)]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "blew up at step" in err


# --- install hints that install what they name ---------------------------------------

# backend -> (the module its probe imports, the distribution that provides it)
PYTHON_PACKAGES = {
    "cuda": ("cupy", "cupy-cuda12x"),
    "opencl": ("pyopencl", "pyopencl"),
    "glsl": ("moderngl", "moderngl"),
    "glsl-compute": ("moderngl", "moderngl"),
    "taichi": ("taichi", "taichi"),
    "warp": ("warp", "warp-lang"),
    "numba": ("numba", "numba"),
    "newton": ("newton", "newton"),  # a peer: named by the [peers] extra as the other peers are
}


def _requirement_names(requirements: list[str]) -> set[str]:
    import re

    return {re.match(r"[A-Za-z0-9._-]+", r).group(0).lower() for r in requirements}


@pytest.mark.parametrize("backend", sorted(PYTHON_PACKAGES))
def test_a_missing_package_is_named_with_the_pip_command_that_installs_it(backend, monkeypatch):
    import importlib
    import re
    import shlex
    import tomllib
    from pathlib import Path

    from clothbench.backends import BACKENDS

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())["project"]
    module, distribution = PYTHON_PACKAGES[backend]
    monkeypatch.setitem(sys.modules, module, None)  # as if it were not installed: import fails
    for name in ("ENABLE_TAICHI_HEADER_PRINT", "TI_SKIP_VERSION_CHECK"):  # taichi's probe sets these
        monkeypatch.setenv(name, "x")
    entry = BACKENDS[backend]
    probe = importlib.import_module((entry.verlet or entry.pbd).partition(":")[0]).probe
    reason = probe().reason
    assert f"{module} not installed (pip install " in reason, reason
    # "'clothbench[cuda]' for CUDA 12, 'clothbench[cuda13]' for CUDA 13": each extra is checked
    command = re.search(r"pip install ([^)]*)\)", reason).group(1)
    words = shlex.split(re.sub(r"\bfor CUDA \d+,?", "", command))
    installs: set[str] = set()
    for word in words:
        extras = re.fullmatch(r"clothbench\[([\w,-]+)\]", word)
        if extras:  # an extra of clothbench's: it must exist and list the package
            for extra in extras.group(1).split(","):
                assert extra in project["optional-dependencies"], f"{word}: pyproject.toml has no extra {extra!r}"
                installs |= _requirement_names(project["optional-dependencies"][extra])
        else:  # a package by name: one of clothbench's own dependencies, so its version bound holds
            assert word.lower() in _requirement_names(project["dependencies"]) | {"glcontext"}, word  # (moderngl's)
            installs.add(word.lower())
    assert distribution in installs, f"{reason!r} does not install {distribution}"


def test_warp_says_nothing_about_a_missing_cuda_driver():
    import importlib.util

    if importlib.util.find_spec("warp") is None:
        pytest.skip("warp is not installed (pip install 'clothbench[peers]')")
    out = subprocess.run(
        [sys.executable, "-m", "clothbench", "run", "--backend", "warp", "--grid", "8", "--steps", "2"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "Could not find or load the NVIDIA CUDA driver" not in out.stderr + out.stdout


def test_backends_table_prints_an_install_hint_with_its_brackets(capsys):
    # rich would read "[peers]" as markup and drop it, leaving a command that installs nothing
    from clothbench.reports.tables import print_backends

    print_backends(
        [{"backend": "x", "kind": "peer", "usable": False, "device": "", "reason": "pip install 'clothbench[peers]'"}]
    )
    assert "clothbench[peers]" in capsys.readouterr().out


def test_sweep_columns_names_every_backend_that_runs_f64(capsys):
    # not "numpy only" while c runs f64 too; from the declared Capabilities
    from clothbench.backends import BACKENDS, capabilities

    f64 = [n for n, e in BACKENDS.items() if any("f64" in capabilities(n, s).precisions for s in e.solvers())]
    assert "c" in f64 and "numpy" in f64
    assert main(["sweep", "--columns"]) == 0
    line = next(row for row in capsys.readouterr().out.splitlines() if row.startswith("precision "))
    assert f"runs on: {', '.join(f64)}" in line and "numpy only" not in line


def test_pbd_options_with_the_pbd_solver_still_run(capsys):
    # the item-10 refusals refuse only what would be ignored
    assert main(["run", "--solver", "pbd", "--pbd-method", "jacobi", "--iterations", "2", "--grid", "4",
                 "--steps", "2", "--json"]) == 0  # fmt: skip
    assert main(["run", "--backend", "c", "--precision", "f64", "--strict", "--grid", "4", "--steps", "2",
                 "--json"]) == 0  # fmt: skip


def test_accuracy_help_agrees_with_docs_pbd_on_when_the_methods_meet(capsys):
    # not "they converge to different answers"
    import re
    from pathlib import Path

    with pytest.raises(SystemExit):
        main(["accuracy", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "converge to different answers" not in text
    help_line = re.search(r"--pbd-methods PBD_METHODS (.*?\))", text).group(1)
    docs = " ".join((Path(__file__).parents[1] / "docs" / "pbd.md").read_text().split())
    assert "What Jacobi and Gauss-Seidel converge to" in help_line and "substeps" in help_line
    for figure in ("1.7e-5 m RMS", "2e-4 m"):  # the figures the help quotes are the doc's
        assert figure in help_line
    assert "1.7e-5 m RMS" in docs and "2.0e-4 m away" in docs


DEVICE = {
    "device": "0:0",
    "default": True,
    "name": "Intel(R) Xeon(R) Processor @ 2.10GHz",
    "runtime": "Intel CPU runtime",
    "platform": "Intel(R) OpenCL",
    "platform_version": "OpenCL 3.0 PoCL 3.1+debian Linux, None+Asserts, RELOC, SPIR, LLVM 15.0.6, SLEEF",
    "driver_version": "2026.22.10.0.01_160000",
    "llvm": None,
    "compiles": True,
}


@pytest.mark.parametrize("width", [80, 40])
def test_backends_device_list_fits_a_narrow_terminal_with_every_cell_whole(width, capsys):
    # at 80 columns (or piped) no cell may be cut, as in "Intel… Xeon(… Proce…"
    from clothbench.cli.backends import print_opencl_devices

    print_opencl_devices([DEVICE], "default: 0:0", width=width)
    out = capsys.readouterr().out
    assert "…" not in out
    for cell in (
        DEVICE["name"],
        DEVICE["platform_version"],
        DEVICE["driver_version"],
        "Intel CPU runtime (Intel(R) OpenCL)",
    ):
        assert cell in out, out
    assert "0:0*" in out and out.rstrip().endswith("default: 0:0")


def test_backends_device_list_is_a_table_where_it_fits(capsys):
    from clothbench.cli.backends import print_opencl_devices

    print_opencl_devices([DEVICE], "default: 0:0", width=400)
    out = capsys.readouterr().out
    assert "┃ device" in out and DEVICE["platform_version"] in out and "…" not in out
