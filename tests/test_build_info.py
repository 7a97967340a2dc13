"""Which commit an installed clothbench is: its wheel records the commit of the checkout it was
built from (hatch_build.py), and every row it measures says that commit and its version where
there is no repository to ask. The wheels are built offline from copies of this
tree, by pip without build isolation: the hatchling installed here (clothbench[test])."""

from __future__ import annotations

import shutil
import subprocess
import sys
import types
import zipfile
from pathlib import Path

import pytest

import clothbench
from clothbench import environment

REPO = Path(__file__).resolve().parents[1]
BUILD_INFO = "clothbench/_build_info.py"
# What a build reads: the project, its hook, its readme and the files the wheel takes
BUILT_FROM = ("pyproject.toml", "hatch_build.py", "README.md", ".gitignore", "clothbench", "kernels")


def _copy_of_the_tree(to: Path) -> Path:
    to.mkdir()
    for name in BUILT_FROM:
        source = REPO / name
        if source.is_dir():
            shutil.copytree(source, to / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(source, to / name)
    return to


def _git(root: Path, *args: str) -> str:
    command = ["git", "-C", str(root), "-c", "user.name=test", "-c", "user.email=test@example.invalid", *args]
    return subprocess.run(command, check=True, capture_output=True, text=True, timeout=30).stdout.strip()


def _checkout(to: Path) -> tuple[Path, str]:
    """A git repository of a copy of this tree, one commit: (its root, its short commit)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    root = _copy_of_the_tree(to)
    _git(root, "init", "-q")
    _git(root, "add", "-A")
    _git(root, "commit", "-q", "-m", "a copy of clothbench")
    return root, _git(root, "rev-parse", "--short=12", "HEAD")


def _wheel(source: Path, out: Path) -> Path:
    """The wheel pip builds from `source` (a tree or an sdist), offline."""
    pytest.importorskip("hatchling", reason="hatchling builds the wheel (pip install 'clothbench[test]')")
    command = [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index"]
    built = subprocess.run([*command, "-w", str(out), str(source)], capture_output=True, text=True, timeout=120)
    assert built.returncode == 0, built.stderr
    (wheel,) = out.glob("clothbench-*.whl")
    return wheel


def _built_from(wheel: Path) -> str | None:
    """COMMIT of the wheel's build info; None where the wheel has none."""
    with zipfile.ZipFile(wheel) as z:
        if BUILD_INFO not in z.namelist():
            return None
        found: dict = {}
        exec(z.read(BUILD_INFO).decode(), found)
        return found["COMMIT"]


def test_a_wheel_built_from_a_checkout_names_its_commit_and_an_installed_copy_says_it(tmp_path):
    root, commit = _checkout(tmp_path / "checkout")
    wheel = _wheel(root, tmp_path / "clean")
    assert _built_from(wheel) == commit

    # installed (the wheel unpacked, as pip lays it out), run where no repository is: the rows'
    # git_commit is the build's commit with the version, not "unknown"
    installed = tmp_path / "site-packages"
    zipfile.ZipFile(wheel).extractall(installed)
    code = f"import sys; sys.path.insert(0, {str(installed)!r}); from clothbench import environment as e; " + (
        "print(e.__file__); print(e.machine()['git_commit'])"
    )
    ran = subprocess.run([sys.executable, "-I", "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert ran.returncode == 0, ran.stderr
    where, says = ran.stdout.splitlines()
    assert Path(where).is_relative_to(installed)
    assert says == f"{commit} (version {clothbench.__version__})"

    # a tracked file changed since the commit: the build says so
    with (root / "README.md").open("a") as f:
        f.write("\nchanged after the commit\n")
    assert _built_from(_wheel(root, tmp_path / "dirty")) == f"{commit}+dirty"


def test_a_wheel_built_from_the_checkouts_sdist_keeps_its_commit(tmp_path):
    # what `pip install clothbench-0.1.0.tar.gz` does: the sdist unpacked, with no .git, then built
    root, commit = _checkout(tmp_path / "checkout")
    pytest.importorskip("hatchling", reason="hatchling builds the sdist (pip install 'clothbench[test]')")
    sdist = subprocess.run(
        [sys.executable, "-c", "import sys; from hatchling.build import build_sdist; print(build_sdist(sys.argv[1]))",
         str(tmp_path / "sdist")],
        cwd=root, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert sdist.returncode == 0, sdist.stderr
    archive = tmp_path / "sdist" / sdist.stdout.split()[-1]
    assert _built_from(_wheel(archive, tmp_path / "wheel")) == commit


def test_a_tree_that_is_no_checkout_builds_a_wheel_without_build_info(tmp_path):
    wheel = _wheel(_copy_of_the_tree(tmp_path / "tree"), tmp_path / "wheel")
    assert _built_from(wheel) is None
    with zipfile.ZipFile(wheel) as z:
        assert "clothbench/environment.py" in z.namelist()  # the wheel is whole, only the commit is left out


def test_an_installed_copy_says_its_build_commit_and_version(tmp_path, monkeypatch):
    monkeypatch.setattr(environment, "CHECKOUT", tmp_path)  # no .git: not a checkout
    info = types.ModuleType("clothbench._build_info")
    info.COMMIT = "0123456789ab+dirty"
    monkeypatch.setitem(sys.modules, "clothbench._build_info", info)
    assert environment.git_commit() == f"0123456789ab+dirty (version {clothbench.__version__})"
    monkeypatch.setitem(sys.modules, "clothbench._build_info", None)  # built from no checkout
    assert environment.git_commit() == f"unknown (version {clothbench.__version__})"


def test_a_checkout_says_its_live_commit_not_a_build_info(tmp_path, monkeypatch):
    root, commit = _checkout(tmp_path / "checkout")
    monkeypatch.setattr(environment, "CHECKOUT", root)
    info = types.ModuleType("clothbench._build_info")
    info.COMMIT = "0123456789ab"  # a stale build's: the checkout's git wins
    monkeypatch.setitem(sys.modules, "clothbench._build_info", info)
    assert environment.git_commit() == commit
    (root / "README.md").write_text("changed\n")
    assert environment.git_commit() == f"{commit}+dirty"
