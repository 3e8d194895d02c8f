"""No function body over 60 lines in pipeline/, benchmark/, baselines/ or cli.py: a longer one is split into
named steps. Numba kernels (pipeline/kernels.py's `@kernel`) are exempt: a kernel cannot call plain Python
helpers, and splitting its loops costs calls in the hottest code."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("pipeline", "benchmark", "baselines")
MAX_BODY_LINES = 60


def sources() -> list[Path]:
    found = [p for root in ROOTS for p in (REPO / root).rglob("*.py") if "__pycache__" not in p.parts]
    return sorted(found) + [REPO / "cli.py"]


def is_kernel(decorator: ast.expr) -> bool:
    """`@kernel`, `@kernel(...)`, or either through its module (`@kernels.kernel`)."""
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)
    return name == "kernel"


def body_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the body's first statement (the docstring, if any) to the end of its last."""
    return function.body[-1].end_lineno - function.body[0].lineno + 1


def too_long(source: str, where: Path | str) -> list[str]:
    """Each function or method in source whose body exceeds the cap, not a kernel, as "where::name (N
    lines)"; nested functions are measured on their own too."""
    return [
        f"{where}::{node.name} ({body_lines(node)} lines)"
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and body_lines(node) > MAX_BODY_LINES
        and not any(is_kernel(d) for d in node.decorator_list)
    ]


def test_no_function_body_is_over_60_lines():
    offenders = [found for path in sources() for found in too_long(path.read_text(), path.relative_to(REPO))]
    assert not offenders, f"function bodies over {MAX_BODY_LINES} lines: {', '.join(offenders)}"


def test_the_check_counts_the_body_and_spares_only_kernels():
    def function(decorator: str, name: str, statements: int) -> str:
        body = "".join(f"    x{i} = {i}\n" for i in range(statements - 1))
        return f'{decorator}def {name}():\n    """Docstring."""\n{body}\n'

    source = (
        function("", "at_the_cap", 60)
        + function("", "over_the_cap", 61)
        + function("@kernel\n", "plain_kernel", 90)
        + function("@kernel(inline='always')\n", "inlined_kernel", 90)
        + function("@kernels.kernel\n", "qualified_kernel", 90)
        + function("@functools.cache\n", "cached", 61)
        + "class Holder:\n"
        + "\n".join("    " + line for line in function("", "method", 62).splitlines())
        + "\n"
    )
    assert too_long(source, "m.py") == ["m.py::over_the_cap (61 lines)", "m.py::cached (61 lines)",
                                        "m.py::method (62 lines)"]  # fmt: skip
