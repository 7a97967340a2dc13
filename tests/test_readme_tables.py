"""README's performance numbers are the committed sweep's: each table is regenerated from the
CSV it names and must appear in README.md as it is, and the tables' arithmetic is checked
on rows made up for the purpose."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest

from clothbench.reports.readme_tables import limits_markdown, limits_rows, ms_markdown
from clothbench.reports.tables import peer_ratio_markdown

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"


def readme_sweep() -> Path:
    """The sweep README's performance section is written from (the file it names first)."""
    section = README.read_text().split("## Performance on one machine", 1)[1].split("\n## ", 1)[0]
    name = re.search(r"`(results/[^`]+\.csv)`", section)
    assert name, "README's performance section names no results/*.csv"
    return ROOT / name.group(1)


@pytest.fixture(scope="module")
def committed() -> list[dict[str, str]]:
    path = readme_sweep()
    if not path.exists():
        pytest.skip(f"{path.name} is not in this checkout")
    return list(csv.DictReader(path.open()))


@pytest.mark.parametrize("table", [limits_markdown, ms_markdown, peer_ratio_markdown], ids=lambda f: f.__name__)
def test_every_performance_table_in_readme_is_the_committed_sweeps(committed, table):
    text = table(committed)
    assert text.count("\n") >= 3, f"{table.__name__}: the sweep has too few rows for a table"
    assert text in README.read_text(), f"README's {table.__name__} table differs from {readme_sweep().name}"


def test_the_committed_sweep_is_one_run_on_one_machine(committed):
    # ratios between rows mean something only within one run on one machine
    assert len({r["cpu"] for r in committed}) == 1
    assert len({r["git_commit"] for r in committed}) == 1
    assert all(r["bound_ms"] for r in committed if r["status"] == "ok" and r["solver"] == "verlet")


def test_readme_names_the_cpu_and_drivers_of_the_committed_sweep(committed):
    section = README.read_text().split("## Performance on one machine", 1)[1].split("\n## ", 1)[0]
    assert committed[0]["cpu"] in section
    drivers = {r["driver"] for r in committed if r["backend"] in ("opencl", "glsl") and r["status"] == "ok"}
    for driver in drivers:
        version = re.search(r"(PoCL|Mesa) [\d.]+", driver)
        assert version and version.group(0) in section, f"README does not name {driver!r}"


def performance_section() -> str:
    return README.read_text().split("## Performance on one machine", 1)[1].split("\n## ", 1)[0]


def test_every_registered_backend_the_committed_sweep_lacks_is_said_why(committed):
    # a backend that runs here but has no row reads as forgotten unless said
    from clothbench.backends import BACKENDS

    swept = {r["backend"] for r in committed}
    missing = [name for name in BACKENDS if name not in swept]
    prose = " ".join(performance_section().split())  # the paragraph's lines joined
    for name in missing:
        said = re.search(rf"(^|[\s,`(]){re.escape(name)}[\s,`)][^.]*?(skipped|not in it)", prose)
        assert said, f"README's performance section does not say why {name} has no row in {readme_sweep().name}"


def test_readme_says_which_opencl_runtime_the_quick_start_gets(committed):
    # the quick start installs Intel's runtime, the tables ran on Debian's PoCL
    quick = README.read_text().split("## Quick start", 1)[1].split("\n## ", 1)[0]
    assert "intel-opencl" in quick
    assert {r["driver"].split(":")[0] for r in committed if r["backend"] == "opencl"} == {"Portable Computing Language"}
    prose = " ".join(performance_section().split())
    assert re.search(
        r"The quick start installs Intel's runtime and no system PoCL[^.]*not of the Debian PoCL line", prose
    )


def row(backend: str, grid: int, ms: float, peer: bool = False, **extra) -> dict[str, str]:
    out = {
        "backend": backend,
        "peer": "true" if peer else "false",
        "mode": "fast",
        "status": "ok",
        "grid": str(grid),
        "solver": "verlet",
        "local_size": "",
        "precision": "f32",
        "ms_median": str(ms),
        "bound_ms": "",
        "bound_kind": "",
        "bound_fraction": "",
        "vs_c": "",
    }
    out.update(extra)
    return out


def test_limits_take_the_fastest_of_each_kind_per_grid():
    rows = [
        row("c", 256, 0.30),
        row("opencl", 256, 0.24, bound_ms="0.12", bound_kind="memory", bound_fraction="0.5"),
        row("glsl", 256, 1.5),
        row("numpy", 256, 3.0),
        row("numba", 256, 1.2, peer=True),
        row("taichi", 256, 2.0, peer=True),
        row("opencl", 256, 0.01, local_size="16"),  # a local-size row is another study
        row("opencl", 512, 1.0),  # no c row at 512: no line
    ]
    (line,) = limits_rows(rows)
    assert (line["grid"], line["best"], line["peer"]) == (256, "opencl fast", "numba fast")
    assert line["vs_c"] == pytest.approx(0.8) and line["peer_ratio"] == pytest.approx(5.0)
    assert line["bound_ms"] == 0.12 and line["fraction"] == 0.5 and line["fastest_any"] == "opencl fast"
    # the fastest row is the GPU-style row already named: not named twice
    assert (
        "| 256×256 | 0.300 | opencl fast | 0.240 | 0.80× | numba fast | 1.200 | 5.0× | 0.120 (memory) | 50 % (the same row) |"
        in limits_markdown(rows)
    )
    # where the fastest row is another (here the c line), it is named
    faster_c = [r if r["backend"] != "c" else row("c", 256, 0.20, bound_fraction="0.6") for r in rows]
    assert "| 0.120 (memory) | 60 % (c fast) |" in limits_markdown(faster_c)
