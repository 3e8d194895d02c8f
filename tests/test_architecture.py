"""docs/ARCHITECTURE.md stays true: its list of modules names every module of pipeline/, benchmark/ and
baselines/ (a package's __init__.py where it holds code) and cli.py, and names no module that is gone."""

from __future__ import annotations

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("pipeline", "benchmark", "baselines")


def modules(root: Path) -> set[str]:
    """The modules a newcomer must find: every .py file of the folders, an __init__.py only where it holds
    more than its docstring, and cli.py."""
    found = {"cli.py"}
    for path in (p for folder in FOLDERS for p in (root / folder).rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        body = ast.parse(path.read_text()).body
        only_doc = all(isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant) for n in body)
        if path.name != "__init__.py" or not only_doc:
            found.add(path.relative_to(root).as_posix())
    return found


def named(root: Path) -> set[str]:
    """The module paths docs/ARCHITECTURE.md names, as `folder/.../name.py` or `cli.py` (a placeholder in
    capitals, `baselines/models/NAME.py`, is none)."""
    text = (root / "docs" / "ARCHITECTURE.md").read_text()
    pattern = rf"(?<![\w/.])((?:{'|'.join(FOLDERS)})/[a-z0-9_/]+\.py|cli\.py)"
    return set(re.findall(pattern, text))


def test_architecture_names_every_module_and_no_gone_one():
    existing, listed = modules(REPO), named(REPO)
    assert not existing - listed, f"docs/ARCHITECTURE.md does not name: {sorted(existing - listed)}"
    gone = {name for name in listed if not (REPO / name).is_file()}
    assert not gone, f"docs/ARCHITECTURE.md names modules that do not exist: {sorted(gone)}"


def test_the_check_sees_a_new_and_a_moved_module(tmp_path):
    for folder in FOLDERS:
        (tmp_path / folder).mkdir()
    (tmp_path / "docs").mkdir()
    (tmp_path / "cli.py").write_text('"""cli."""\n')
    (tmp_path / "pipeline" / "io.py").write_text('"""io."""\n')
    (tmp_path / "pipeline" / "__init__.py").write_text('"""Only a docstring."""\n')
    doc = "`cli.py`, `pipeline/io.py`, `benchmark/gone.py`, `pipeline/NAME.py`\n"
    (tmp_path / "docs" / "ARCHITECTURE.md").write_text(doc)
    assert modules(tmp_path) == {"cli.py", "pipeline/io.py"}
    assert named(tmp_path) == {"cli.py", "pipeline/io.py", "benchmark/gone.py"}
    (tmp_path / "benchmark" / "new.py").write_text('"""new."""\n')
    assert modules(tmp_path) - named(tmp_path) == {"benchmark/new.py"}
