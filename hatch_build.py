"""Hatchling build hook: a wheel or sdist records the commit it was built from.

An installed clothbench has no repository to ask which commit it is, so every row it measures
would say "unknown". Built from a git checkout, the wheel and the sdist carry
clothbench/_build_info.py (COMMIT: the checkout's short commit, '+dirty' if tracked files had
changes), which clothbench.environment.git_commit reads where there is no checkout. Nothing is
written where the tree built is no checkout: a wheel built from an unpacked sdist keeps the sdist's
file. An editable install runs from the checkout, whose commit git says live: nothing is written.

The file is written outside the tree and force-included, never into clothbench/: it needs no
.gitignore entry, and must have none (an sdist carries .gitignore, and a wheel built from it
would leave an ignored _build_info.py out).
"""

from __future__ import annotations

import importlib.util
import shutil
import tempfile
from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface

BUILD_INFO = "clothbench/_build_info.py"


def _checkout_commit(root: Path) -> str | None:
    """clothbench.environment.checkout_commit, loaded from the tree being built: the build's
    environment has hatchling, not clothbench's dependencies (environment.py needs none)."""
    spec = importlib.util.spec_from_file_location("_clothbench_environment", root / "clothbench" / "environment.py")
    environment = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(environment)
    return environment.checkout_commit(root)


class BuildInfoHook(BuildHookInterface):
    def initialize(self, version: str, build_data: dict) -> None:
        self._folder = None
        if version == "editable":
            return
        commit = _checkout_commit(Path(self.root))
        if commit is None:
            return
        self._folder = Path(tempfile.mkdtemp(prefix="clothbench-build-info-"))
        info = self._folder / "_build_info.py"
        info.write_text(
            "# Written by hatch_build.py when this copy of clothbench was built: the commit of the checkout it\n"
            "# was built from, which clothbench.environment.git_commit says where there is no checkout to ask.\n"
            f"COMMIT = {commit!r}\n"
        )
        build_data["force_include"][str(info)] = BUILD_INFO

    def finalize(self, version: str, build_data: dict, artifact_path: str) -> None:
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
