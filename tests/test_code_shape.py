"""The package's code stays readable: no function over MAX_LINES lines, and every public function
or method has a docstring (docs/ARCHITECTURE.md: the docstring states tensor shapes)."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchvol"
MAX_LINES = 60


def _functions(tree: ast.AST, prefix: str = "", in_function: bool = False, private_class: bool = False):
    """(qualified name, node, public) for every function in `tree`: public unless its name starts
    with "_", it is nested in a function, or its class's name starts with "_"."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            public = not node.name.startswith("_") and not in_function and not private_class
            yield prefix + node.name, node, public
            yield from _functions(node, prefix + node.name + ".", True, private_class)
        elif isinstance(node, ast.ClassDef):
            yield from _functions(node, prefix + node.name + ".", in_function,
                                  private_class or node.name.startswith("_"))


def _offenders() -> tuple[list[str], list[str]]:
    long, undocumented = [], []
    for path in sorted(PACKAGE.rglob("*.py")):
        where = path.relative_to(PACKAGE.parent)
        for name, node, public in _functions(ast.parse(path.read_text(), str(path))):
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_LINES:
                long.append(f"{where}:{node.lineno} {name} ({lines} lines)")
            if public and ast.get_docstring(node) is None:
                undocumented.append(f"{where}:{node.lineno} {name}")
    return long, undocumented


def test_no_function_is_longer_than_max_lines():
    long, _ = _offenders()
    assert not long, f"functions over {MAX_LINES} lines (split them):\n" + "\n".join(long)


def test_every_public_function_has_a_docstring():
    _, undocumented = _offenders()
    assert not undocumented, "public functions without a docstring:\n" + "\n".join(undocumented)
