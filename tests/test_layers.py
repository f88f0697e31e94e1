"""The package's imports point down its layers (`torchvol.layers.LAYERS`) and form no cycle.

Every `import` and `from ... import` of every module counts, function-local and TYPE_CHECKING ones
too: an import hidden in a function is still a dependency a reader has to follow."""

import ast
from pathlib import Path

import pytest

from torchvol.layers import LAYERS

PACKAGE = Path(__file__).resolve().parents[1] / "torchvol"
RANK = {entry: tier for tier, entries in enumerate(LAYERS) for entry in entries}


def module_name(path: Path) -> str:
    parts = ["torchvol", *path.relative_to(PACKAGE).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imported(name: str, node: ast.AST) -> list[str]:
    """The torchvol modules an import node of module `name` loads (a name imported from a package
    that is itself a module counts as that module)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names if a.name.split(".")[0] == "torchvol"]
    package = name.split(".") if MODULES[name].name == "__init__.py" else name.split(".")[:-1]
    if node.level:
        base = ".".join(package[:len(package) - node.level + 1] + ([node.module] if node.module else []))
    else:
        base = node.module or ""
    if base.split(".")[0] != "torchvol":
        return []
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]


def edges() -> dict[str, list[tuple[str, int]]]:
    """module -> [(imported module, line)], torchvol's modules only."""
    out = {}
    for name, path in MODULES.items():
        found = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in imported(name, node):
                    while target not in MODULES and "." in target:
                        target = target.rsplit(".", 1)[0]
                    # a module's own package (its __init__) runs first anyway: no dependency of its own
                    if target != name and not name.startswith(target + "."):
                        found.append((target, node.lineno))
        out[name] = found
    return out


def entry(name: str) -> str | None:
    """The layer-table entry of a module: its top-level package or module (None: the package's
    own __init__, the public façade above every layer)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_top_level_module_has_a_layer():
    missing = sorted({entry(n) for n in MODULES if entry(n) is not None and entry(n) not in RANK})
    assert not missing, f"add these to torchvol/layers.py's LAYERS: {missing}"


def test_imports_point_down_the_layers():
    wrong = []
    for name, targets in edges().items():
        source = entry(name)
        if source is None:
            continue
        for target, line in targets:
            dest = entry(target)
            if dest is None:
                wrong.append(f"{MODULES[name].relative_to(PACKAGE.parent)}:{line} imports the package façade `torchvol`")
            elif dest != source and RANK[dest] >= RANK[source]:
                how = "up" if RANK[dest] > RANK[source] else "sideways"
                wrong.append(f"{MODULES[name].relative_to(PACKAGE.parent)}:{line} imports {target} ({how}: "
                             f"{source} is in tier {RANK[source]}, {dest} in tier {RANK[dest]})")
    assert not wrong, "imports against torchvol/layers.py:\n" + "\n".join(wrong)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles():
    graph = {name: {t for t, _ in targets} for name, targets in edges().items()}
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


@pytest.mark.parametrize("graph, expected", [
    ({"a": {"b"}, "b": {"a"}, "c": set()}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c"]]),
])
def test_the_cycle_finder_finds_cycles(graph, expected):
    assert cycles(graph) == expected
