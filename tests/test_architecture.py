"""The layout rules of docs/architecture.md, checked on the source tree.

Imports go one way (``benchmarks -> zoo -> datamodules``), no two modules import each other through any
chain (the model registry's import-time registration excepted), no private name crosses a module, and
no source module grows past 600 lines.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("datamodules", "zoo", "benchmarks")
LAYER = {name: level for level, name in enumerate(PACKAGES)}
MAX_LINES = 600
#: the registry imports the nets (to register them) and the nets import the registry's decorator
REGISTRATION = ("zoo.registry", "zoo.nets")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


SOURCES = {_module_name(p): p for package in PACKAGES for p in sorted((REPO / package).rglob("*.py"))}


def _imports(name: str, path: Path) -> list[tuple[str, list[str]]]:
    """(imported module, names taken from it) for every import statement of a module, lazy ones included."""
    found = []
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.append((submodule, []) if submodule in SOURCES else (base, [alias.name]))
    return [(module, names) for module, names in found if module.split(".")[0] in PACKAGES]


GRAPH = {name: _imports(name, path) for name, path in SOURCES.items()}


def _owner(module: str) -> str | None:
    """The source module an import resolves to (the module itself, or the package it names)."""
    while module and module not in SOURCES:
        module = module.rpartition(".")[0]
    return module or None


def test_imports_go_one_way_between_packages():
    upward = [f"{name} imports {module}" for name, edges in GRAPH.items() for module, _ in edges
              if LAYER[module.split(".")[0]] > LAYER[name.split(".")[0]]]
    assert not upward, "imports must go benchmarks -> zoo -> datamodules: " + "; ".join(upward)


def test_no_private_name_is_imported_from_another_module():
    private = [f"{name} takes {module}.{taken}" for name, edges in GRAPH.items() for module, names in edges
               for taken in names if taken.startswith("_") and not taken.startswith("__")]
    assert not private, "make these public in their own module: " + "; ".join(private)


def _edges() -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {name: set() for name in GRAPH}
    for name, imported in GRAPH.items():
        for module, _ in imported:
            target = _owner(module)
            registration = name == REGISTRATION[0] and target and target.startswith(REGISTRATION[1])
            if target and target != name and not registration:
                edges[name].add(target)
    return edges


def _cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """One import circle, as the chain of its modules, or None (depth-first search)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for target in sorted(edges[node]):
            if state.get(target) == 1:
                return stack[stack.index(target):] + [target]
            if target not in state and (found := visit(target)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(edges):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_no_import_circle_between_modules():
    circle = _cycle(_edges())
    assert circle is None, "import circle: " + " -> ".join(circle)


def test_the_circle_check_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_source_module_stays_short(name):
    lines = len(SOURCES[name].read_text().splitlines())
    path = SOURCES[name].relative_to(REPO)
    assert lines <= MAX_LINES, f"{path}: {lines} lines (split it by job, at most {MAX_LINES})"
