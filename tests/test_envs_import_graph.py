"""The modules of ``sg_torchrl.envs`` import each other without circles, and each stays under ~500 lines.

The graph is read from the source with ``ast``: every import a module can run (at module level, in a class
or inside a function; not those under ``if TYPE_CHECKING:``), of another module of ``sg_torchrl.envs``.
A circle there would mean two modules that can only be understood (and loaded) together.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ENVS = Path(__file__).resolve().parents[1] / "sg_torchrl" / "envs"
MAX_LINES = 500


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ENVS.parents[1]).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(path): path for path in sorted(ENVS.rglob("*.py"))}


def imported_modules(path: Path) -> set[str]:
    """The ``sg_torchrl.envs`` modules that ``path`` may import (``from m import x`` counts ``m`` and ``m.x``)."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return {name for name in found if name in MODULES}


def import_graph() -> dict[str, set[str]]:
    """Module -> the envs modules it imports, with the packages they live in (importing ``a.b.c`` runs
    ``a.b``'s ``__init__``) unless the importer is inside that package already."""
    graph = {}
    for name, path in MODULES.items():
        edges = set()
        for target in imported_modules(path) - {name}:
            edges.add(target)
            parts = target.split(".")
            for end in range(3, len(parts)):
                package = ".".join(parts[:end])
                if package in MODULES and package != name and not name.startswith(package + "."):
                    edges.add(package)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` (its modules in order), or ``None``."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def walk(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for target in sorted(graph[node]):
            if state.get(target) == 1:
                return path[path.index(target):] + [target]
            if target not in state:
                cycle = walk(target)
                if cycle:
                    return cycle
        state[node] = 2
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = walk(node)
            if cycle:
                return cycle
    return None


def test_the_graph_covers_the_envs_packages():
    graph = import_graph()
    assert "sg_torchrl.envs.base" in graph and "sg_torchrl.envs.hands.env" in graph
    assert "sg_torchrl.envs.base" in graph["sg_torchrl.envs.mujoco_env"]
    assert "sg_torchrl.envs.agent_group" in graph["sg_torchrl.envs.hands.multi_agent"]


def test_the_cycle_finder_finds_a_circle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_envs_modules_import_each_other_without_circles():
    cycle = find_cycle(import_graph())
    assert cycle is None, " -> ".join(cycle)


@pytest.mark.parametrize("name", sorted(MODULES))
def test_envs_modules_stay_under_the_size_limit(name):
    lines = len(MODULES[name].read_text().splitlines())
    assert lines <= MAX_LINES, f"{name}: {lines} lines"
