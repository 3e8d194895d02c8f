"""The house of docs/ARCHITECTURE.md: the layers import only downwards (pipeline < benchmark < baselines <
cli and tools), no package imports itself in a circle, no module exceeds 700 lines, no folder holds more
than 16 modules directly, and every module opens with a docstring."""

from __future__ import annotations

import ast
from pathlib import Path

import networkx as nx
import pytest

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("pipeline", "benchmark", "baselines", "tools")  # tools and cli.py stand on top
PACKAGES = [REPO / layer for layer in LAYERS]
MODULES = sorted(p for package in PACKAGES for p in package.rglob("*.py") if "__pycache__" not in p.parts)


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path) -> set[str]:
    """The project's modules that `path` imports, at its top or inside a function."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
            names |= {f"{node.module}.{alias.name}" for alias in node.names}
    return {name for name in names if name.split(".")[0] in LAYERS or name == "cli"}


def test_the_layers_import_only_downwards():
    rank = {layer: i for i, layer in enumerate(LAYERS)} | {"cli": len(LAYERS)}
    upwards = [
        f"{module_name(path)} imports {name}"
        for path in MODULES
        for name in imported(path)
        if rank[name.split(".")[0]] > rank[path.relative_to(REPO).parts[0]]
    ]
    assert not upwards, upwards


def test_no_circle_of_imports_between_modules():
    known = {module_name(path) for path in MODULES}
    graph = nx.DiGraph()
    for path in MODULES:
        for name in imported(path):
            if name in known and name != module_name(path) and not REPO.joinpath(*name.split(".")).is_dir():
                graph.add_edge(module_name(path), name)
    assert not list(nx.simple_cycles(graph)), list(nx.simple_cycles(graph))


@pytest.mark.parametrize("path", MODULES + [REPO / "cli.py"], ids=lambda p: str(p.relative_to(REPO)))
def test_a_module_fits_700_lines_and_says_what_it_holds(path):
    text = path.read_text()
    assert len(text.splitlines()) <= 700
    assert ast.get_docstring(ast.parse(text)), "no module docstring"


def test_no_folder_holds_more_than_16_modules():
    folders = {path.parent for path in MODULES}
    crowded = {
        str(folder.relative_to(REPO)): count
        for folder in folders
        if (count := sum(1 for p in folder.glob("*.py") if p.name != "__init__.py")) > 16
    }
    assert not crowded, crowded
