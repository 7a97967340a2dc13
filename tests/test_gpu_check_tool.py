"""tools/gpu-check and tools/build-wheelhouse: bad input in one line, the wheelhouse's size
limit, which tests the GPU run selects, and, on a machine without a GPU, a summary that says
for every GPU part why it was skipped while the CPU backends are still swept."""

from __future__ import annotations

import csv
import importlib.machinery
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from clothbench.backends import BACKENDS, availability

TOOLS = Path(__file__).resolve().parent.parent / "tools"
GPU_CHECK = TOOLS / "gpu-check"
BUILD_WHEELHOUSE = TOOLS / "build-wheelhouse"


def load_tool(path: Path):
    """A tool script (no .py suffix) as a module, for its functions."""
    loader = importlib.machinery.SourceFileLoader(path.name.replace("-", "_"), str(path))
    spec = importlib.util.spec_from_loader(loader.name, loader)
    module = importlib.util.module_from_spec(spec)
    sys.modules[loader.name] = module  # its dataclasses look their module up there
    loader.exec_module(module)
    return module


def run_tool(path: Path, *argv: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(path), *argv], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--grids", "32,x"], "--grids takes comma-separated integers"),
        (["--grids", "2"], "--grids must name grids of at least 3"),
        (["--skip", "probe"], "--skip takes install, tests, sweep, plot"),
        (["--time-limit", "0"], "--time-limit must be > 0"),
        (["--wheelhouse", "/nonexistent/wheelhouse"], "is not a folder"),
        (["--no-such-option"], "unrecognized arguments"),
    ],
)
def test_gpu_check_bad_input_is_one_line_and_exit_2(argv, message):
    result = run_tool(GPU_CHECK, *argv)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("gpu-check: "), result.stderr
    assert message in result.stderr
    assert result.stdout == ""


def test_build_wheelhouse_bad_input_is_one_line_and_exit_2(tmp_path):
    for argv, message in (
        (["--max-mib", "0"], "--max-mib must be > 0"),
        (["--check", "--out", str(tmp_path / "absent")], "is not a folder"),
    ):
        result = run_tool(BUILD_WHEELHOUSE, *argv)
        assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
        assert result.stderr.startswith("build-wheelhouse: ") and message in result.stderr


def test_wheelhouse_size_limit_counts_every_file(tmp_path):
    tool = load_tool(BUILD_WHEELHOUSE)
    (tmp_path / "a.whl").write_bytes(b"\0" * 2**20)
    (tmp_path / "b.deb").write_bytes(b"\0" * (2**20 + 1))  # 2 MiB and one byte in all
    assert tool.size_problem(tmp_path, 3) is None
    problem = tool.size_problem(tmp_path, 2)
    assert problem is not None and "2.0 MiB, over the 2 MiB limit" in problem
    assert tool.size_problem(tmp_path, 2 + 1 / 2**20) is None  # exactly at the limit is within it


def test_wheelhouse_over_its_limit_fails_in_one_line(tmp_path):
    (tmp_path / "big.whl").write_bytes(b"\0" * 3 * 2**20)
    over = run_tool(BUILD_WHEELHOUSE, "--check", "--out", str(tmp_path), "--max-mib", "2")
    assert over.returncode == 1 and over.stderr.count("\n") == 1 and "over the 2 MiB limit" in over.stderr
    within = run_tool(BUILD_WHEELHOUSE, "--check", "--out", str(tmp_path), "--max-mib", "4")
    assert within.returncode == 0 and "3.00 MiB  in 1 files" in within.stdout


def test_wheels_for_another_python_are_recognised():
    tool = load_tool(GPU_CHECK)
    here = f"cp{sys.version_info.major}{sys.version_info.minor}"
    names = [
        f"moderngl-5.13.0-{here}-{here}-manylinux2014_x86_64.whl",
        "pytools-2026.1.1-py3-none-any.whl",
        "glcontext-3.1.0-cp29-cp29-manylinux1_x86_64.whl",
    ]
    assert tool.foreign_wheels([Path(n) for n in names]) == ["glcontext-3.1.0-cp29-cp29-manylinux1_x86_64.whl"]


def test_the_gpu_run_leaves_out_only_the_cpu_backends_contract_tests():
    tool = load_tool(GPU_CHECK)
    base = "tests/contract/test_verlet_contract.py::test_strict_matches_numpy_f32_bit_for_bit"
    assert tool.cpu_only_test(f"{base}[numpy-sphere-1]") and tool.cpu_only_test(f"{base}[c]")
    assert tool.cpu_only_test(f"{base}[c-generic-drape-500]")
    for kept in ("cuda-sphere-1", "cupy-sphere-1", "glsl-compute-generic-drape-1", "opencl", "numba-cuda-x"):
        assert not tool.cpu_only_test(f"{base}[{kept}]"), kept


def test_junit_counts_read_skip_reasons_and_failures(tmp_path):
    tool = load_tool(GPU_CHECK)
    xml = tmp_path / "t.xml"
    xml.write_text(
        '<testsuites><testsuite><testcase classname="a" name="ok"/>'
        '<testcase classname="a" name="s1"><skipped message="cuda unavailable: no CUDA device"/></testcase>'
        '<testcase classname="a" name="s2"><skipped message="cuda unavailable: no CUDA device"/></testcase>'
        '<testcase classname="b" name="bad"><failure message="x"/></testcase></testsuite></testsuites>'
    )
    counts = tool.junit_counts(xml)
    assert (counts["passed"], counts["skipped"], counts["failed"]) == (1, 2, 1)
    assert counts["skip_reasons"] == {"cuda unavailable: no CUDA device": 2} and counts["failures"] == ["b::bad"]
    assert tool.junit_counts(tmp_path / "absent.xml")["passed"] == 0


@pytest.mark.full  # gpu-check's whole quick run
@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="an NVIDIA driver is here: the GPU parts run")
def test_without_a_gpu_the_summary_says_why_each_gpu_part_was_skipped_and_the_cpu_rows_are_swept(tmp_path):
    # .ci/run runs `gpu-check --quick` before the tests and names its folder in
    # CLOTHBENCH_GPU_CHECK_RUN: that run is read rather than made twice. Elsewhere, the smallest
    # run: no install, no figures, one 8x8 grid; probe, GPU tests (they all skip) and sweep
    if os.environ.get("CLOTHBENCH_GPU_CHECK_RUN"):
        out = Path(os.environ["CLOTHBENCH_GPU_CHECK_RUN"])
    else:
        out = tmp_path / "check"
        result = run_tool(
            GPU_CHECK, "--quick", "--skip", "install,plot", "--grids", "8", "--out", str(out), timeout=300
        )
        assert result.returncode == 0, result.stderr[-2000:]
    summary = (out / "summary.md").read_text()
    gpu_parts = summary.split("## GPU parts")[1].split("\n## ")[0]
    for part in (
        "CUDA backend",
        "GL fragment on the NVIDIA driver",
        "GL compute on the NVIDIA driver",
        "OpenCL on the NVIDIA ICD",
        "GPU copy bandwidth",
        "GPU tests",
        "GPU peers in the sweep",
    ):
        line = next((row for row in gpu_parts.splitlines() if row.startswith(f"- {part}")), None)
        assert line is not None, f"{part} missing from:\n{gpu_parts}"
        assert "skipped: nvidia-smi not found" in line, line
    parts = json.loads((out / "parts.json").read_text())
    assert parts["tests"]["passed"] == 0 and parts["tests"]["skipped"] > 0 and parts["tests"]["failed"] == 0
    with open(out / parts["csv"], newline="") as f:
        swept = {r["backend"] for r in csv.DictReader(f) if r["status"] == "ok"}
    # the sweep is a Verlet sweep: a PBD-only peer (newton) has no row in it
    usable = {name for name, entry in BACKENDS.items() if entry.verlet and availability(name).usable}
    assert usable <= swept, f"usable here but not swept: {usable - swept}"
