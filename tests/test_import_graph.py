"""The package's import graph has no circle, and no experiment module is over 400 lines.

An import circle (``a`` imports ``b``, which imports ``a`` back, at module level or inside a
function) means neither module can be read, tested or moved without the other. The walk reads
every ``import`` statement of ``smcd_rl`` as text (nothing is imported), resolves ``from pkg import
name`` to the module ``pkg.name`` where that is a module, and looks for strongly connected
components. Imports only a type checker sees (under ``if TYPE_CHECKING:``) count too: a module
that needs another's types to be read depends on it. A package's implicit import of its parents
is not an edge, as for every Python tool.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "smcd_rl"

#: The longest an experiment module may be: longer ones are split by what they do.
MAX_EXPERIMENT_LINES = 400


def _modules() -> dict[str, Path]:
    """Dotted module name -> its file, for every module of ``smcd_rl`` (packages by ``__init__``)."""
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of ``smcd_rl`` that module ``name`` imports anywhere in its code."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return {target for target in found if target in modules and target != name}


def import_graph() -> dict[str, set[str]]:
    """Module -> the ``smcd_rl`` modules it imports."""
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_walk_finds_a_circle() -> None:
    """The check can fail: a two-module loop and a three-module loop are both reported."""
    graph = {"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"e"}, "e": {"c"}, "f": {"a"}}
    assert circles(graph) == [["a", "b"], ["c", "d", "e"]]


def test_the_walk_sees_imports_in_functions_and_for_type_checkers() -> None:
    """``from pkg import module`` is an edge to the module; lazy and TYPE_CHECKING imports are edges."""
    graph = import_graph()
    assert "smcd_rl.experiments.shared.harness" in graph["smcd_rl.experiments.two_link.run"]
    assert "smcd_rl.experiments.shared.runtime" in graph["smcd_rl.experiments.shared.config"]  # in validate()
    assert "smcd_rl.experiments.two_link.config" in graph["smcd_rl.experiments.shared.two_link_lookahead"]


def test_no_import_circle_in_the_package() -> None:
    found = circles(import_graph())
    assert not found, "import circles (each: modules that import each other in a loop): " + "; ".join(
        " <-> ".join(component) for component in found
    )


def test_no_experiment_module_is_over_400_lines() -> None:
    long = {
        str(path.relative_to(ROOT)): n
        for path in (PACKAGE / "experiments").rglob("*.py")
        if (n := len(path.read_text().splitlines())) > MAX_EXPERIMENT_LINES
    }
    assert not long, f"split these by what they do (at most {MAX_EXPERIMENT_LINES} lines each): {long}"
