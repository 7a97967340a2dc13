"""The architecture, as statements that fail when the layout drifts: layers import only
downwards, no two modules import each other (however indirectly, however deep in a function),
no module reaches into another's private names, no half-written branches, a size alarm, and
README's Layout naming what is there and every folder of the package."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import clothbench

PACKAGE = Path(clothbench.__file__).parent
# A smell alarm, not a rule to split by: a module this long probably holds two concepts.
# Split by concept when it rings, never to get under the number.
MAX_LINES = 900

# Lower layers never import higher ones. The model and its solver settings sit at the
# bottom; backends (clothbench's and the peers) run one step; the harness times and checks
# them; analysis measures with the harness; reports draw what was measured; the viewer is an
# application beside the CLI (it runs backends live in its own window); the CLI drives all.
LAYERS = {
    "model": 0, "errors": 0, "environment": 0, "kernel_source": 0,
    "native": 0, "machine_load": 0, "machine_fitness": 0, "progress": 0, "_build_info": 0, "variant_names": 0,
    "backends": 1, "peers": 1,
    "harness": 2,
    "analysis": 3,
    "reports": 4,
    "viewer": 5,
    "cli": 6, "__main__": 6,
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


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imported_names(path: Path) -> list[tuple[str, str | None]]:
    """Every import anywhere in the module, function-level ones included, as (module, name):
    name is what a `from module import name` takes, None for a plain `import module`.
    Relative imports are resolved against the module's package."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[tuple[str, str | None]] = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(a.name, None) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            found += [(source, a.name) for a in node.names]
    return found


def import_graph() -> dict[str, set[str]]:
    """Module to the clothbench modules it imports: `from pkg import name` is an edge to
    pkg.name when that is a module, else to pkg."""
    known = {module_name(p) for p in modules()}
    graph: dict[str, set[str]] = {m: set() for m in known}
    for path in modules():
        own = module_name(path)
        for source, name in imported_names(path):
            target = f"{source}.{name}" if name and f"{source}.{name}" in known else source
            if target in known and target != own:
                graph[own].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in sorted(graph[node]):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


# Cycles not yet taken apart, each named so that any new one fails;
# an entry leaves this list with the change that removes it (a stale entry fails too).
KNOWN_CYCLES = {
    ("clothbench.backends", "clothbench.backends.base"),
    ("clothbench.backends.opencl.device", "clothbench.backends.opencl.isolated", "clothbench.backends.opencl.verlet"),
}


def test_no_import_cycle():
    found = {tuple(c) for c in cycles(import_graph())}
    new = sorted(found - KNOWN_CYCLES)
    assert not new, "modules that import each other (move the shared piece down, or join them): " + "; ".join(
        " <-> ".join(c) for c in new
    )
    assert not KNOWN_CYCLES - found, f"KNOWN_CYCLES names cycles that are gone: {sorted(KNOWN_CYCLES - found)}"


def test_no_private_name_is_imported_from_another_module():
    known = {module_name(p) for p in modules()}
    reached = set()
    for path in modules():
        for source, name in imported_names(path):
            if source in known and name and name.startswith("_") and not name.startswith("__"):
                reached.add(f"{path.relative_to(PACKAGE)} imports {name} from {source}")
    assert not reached, "private names used outside their module (make them public, or move the code): " + "; ".join(
        sorted(reached)
    )


def test_no_private_name_is_reached_through_another_module():
    """`import clothbench.x as m` then `m._name`: the same reach as importing _name, which the
    test above cannot see."""
    known = {module_name(p) for p in modules()}
    reached = set()
    for path in modules():
        tree = ast.parse(path.read_text())
        aliases = {}  # a name bound in this module -> the clothbench module it is
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                aliases |= {a.asname or a.name: a.name for a in node.names if a.name in known}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                bound = {a.asname or a.name: f"{node.module}.{a.name}" for a in node.names}
                aliases |= {alias: full for alias, full in bound.items() if full in known}
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in aliases:
                target = aliases[node.value.id]
                if node.attr.startswith("_") and not node.attr.startswith("__") and target != module_name(path):
                    reached.add(f"{path.relative_to(PACKAGE)} reaches {target}.{node.attr}")
    assert not reached, "private names used outside their module (make them public, or move the code): " + "; ".join(
        sorted(reached)
    )


def test_no_placeholder_branches():
    for path in modules():
        text = path.read_text().lower()
        for phrase in ("not implemented yet", "not written yet", "being written"):
            assert phrase not in text, f"{path.relative_to(PACKAGE)} still says {phrase!r}"


ROOT = Path(__file__).resolve().parent.parent
# a file name as README's Layout writes one in a description: analytic.py, kernels/verlet_cloth.c
FILE_NAME = re.compile(r"(?<![\w./-])((?:[\w-]+/)*[\w-]+\.(?:py|md|toml|cl|cu|cuh|c|comp|vert|frag|glsl))\b")
FOLDER_NAME = re.compile(r"(?<![\w./-])((?:[\w-]+/)+)(?![\w.])")  # shim/, tests/contract/


def readme_layout() -> dict[str, str]:
    """README's Layout block as path (from the repository root) -> its description: a line
    at the margin names a path, one indented by four a path in the folder above it, and a
    line indented further continues the description. A path named twice fails here."""
    section = (ROOT / "README.md").read_text().split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```\n", 2)[1]
    entries: dict[str, str] = {}
    top = path = ""
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        if indent > 4:
            entries[path] += " " + line.strip()
            continue
        name, _, text = line.strip().partition("  ")
        path = name if indent == 0 else top + name
        top = path if indent == 0 else top
        assert path not in entries, f"README's Layout names {path} twice"
        entries[path] = text.strip()
    return entries


def folder_of(path: str) -> Path:
    return ROOT / path if path.endswith("/") else (ROOT / path).parent


def test_every_path_readme_s_layout_names_is_there():
    missing = []
    for path, text in readme_layout().items():
        if not (ROOT / path).exists():
            missing.append(path)
        folder = folder_of(path)
        for name in FILE_NAME.findall(text) + FOLDER_NAME.findall(text):
            # a name with a folder in it is written from the root or from clothbench/; a bare
            # one is in the entry's folder or below it (colliders/: analytic.py)
            if "/" in name.rstrip("/"):
                there = (ROOT / name).exists() or (PACKAGE / name).exists()
            else:
                there = any(folder.rglob(name.rstrip("/")))
            if not there:
                missing.append(f"{name} (in {path}'s description)")
    assert not missing, f"README's Layout names what is not there: {missing}"


def test_every_folder_of_the_package_is_in_readme_s_layout():
    entries = readme_layout()
    unnamed = []
    for folder in sorted(p for p in PACKAGE.rglob("*") if p.is_dir() and "__pycache__" not in p.parts):
        if not any(f.is_file() for f in folder.iterdir()):
            continue  # only __pycache__ left behind by a folder that moved
        path = folder.relative_to(PACKAGE.parent).as_posix() + "/"
        parent = folder.parent.relative_to(PACKAGE.parent).as_posix() + "/"
        if path not in entries and folder.name + "/" not in FOLDER_NAME.findall(entries.get(parent, "")):
            unnamed.append(path)
    assert not unnamed, f"folders of clothbench/ that README's Layout does not name: {unnamed}"
