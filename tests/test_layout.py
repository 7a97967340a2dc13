"""The architecture, as statements that fail when the layout drifts: layers import only
downwards, no module grows past a size a reader can hold, no half-written branches."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import clothbench

PACKAGE = Path(clothbench.__file__).parent
MAX_LINES = 500

# Lower layers never import higher ones. The model and its solver settings sit at the
# bottom; backends (clothbench's and the peers) run one step; the harness times and checks
# them; analysis measures with the harness; reports draw what was measured; the CLI drives all.
LAYERS = {
    "scene": 0, "colliders": 0, "solver": 0, "errors": 0, "environment": 0, "constraints": 0, "kernel_source": 0,
    "native": 0, "machine_load": 0,
    "backends": 1, "peers": 1,
    "harness": 2,
    "analysis": 3,
    "reports": 4,
    "cli": 5, "__main__": 5,
}  # fmt: skip


def modules() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def layer_of(dotted: str) -> int | None:
    parts = dotted.split(".")
    if parts[0] != "clothbench":
        return None
    if len(parts) == 1:
        return 0  # the package itself: __version__
    return LAYERS[parts[1].removesuffix(".py")]


def imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append(node.module)
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names]
    return found


def test_every_module_belongs_to_a_layer():
    for path in modules():
        top = path.relative_to(PACKAGE).parts[0].removesuffix(".py")
        assert top == "__init__" or top in LAYERS, f"{path.relative_to(PACKAGE)} is in no layer of LAYERS"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_run_downwards(path):
    rel = path.relative_to(PACKAGE)
    own = 0 if rel.parts[0] == "__init__.py" else LAYERS[rel.parts[0].removesuffix(".py")]
    upward = [m for m in imports(path) if (layer_of(m) or 0) > own]
    assert not upward, f"{rel} (layer {own}) imports from a higher layer: {upward}"


@pytest.mark.parametrize("path", modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_module_is_longer_than_a_reader_can_hold(path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, f"{path.relative_to(PACKAGE)} has {lines} lines (at most {MAX_LINES})"


def test_no_placeholder_branches():
    for path in modules():
        text = path.read_text().lower()
        for phrase in ("not implemented yet", "not written yet", "being written"):
            assert phrase not in text, f"{path.relative_to(PACKAGE)} still says {phrase!r}"
