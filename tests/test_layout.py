"""The package's import graph: library code never imports an entry point, and nothing imports in a cycle.

Every module under ``matl/`` is parsed with :mod:`ast` (nothing is imported). Every ``import`` counts,
also those inside functions (a cycle hidden in a function is still a cycle); only imports under
``if TYPE_CHECKING:`` are left out, since they never run.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "matl"


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def is_entry_point(name: str) -> bool:
    """``python -m matl.<name>``: a top-level module that runs ``main()`` when executed."""
    if name.count(".") != 1:
        return False
    tree = ast.parse(MODULES[name].read_text())
    return any(isinstance(node, ast.If) and "__main__" in ast.unparse(node.test) for node in tree.body)


ENTRY_POINTS = sorted(name for name in MODULES if is_entry_point(name))


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skipped: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test) in ("TYPE_CHECKING", "typing.TYPE_CHECKING"):
            skipped.update(id(child) for stmt in node.body for child in ast.walk(stmt))
    return skipped


def imports_of(name: str, source: str | None = None) -> set[str]:
    """The ``matl`` modules that module ``name`` imports (``from package import submodule`` names the submodule)."""
    path = MODULES[name]
    tree = ast.parse(path.read_text() if source is None else source)
    skipped = _type_checking_nodes(tree)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "matl")
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            if base.split(".")[0] != "matl":
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if sub in MODULES else base)
    return {m for m in found if m in MODULES and m != name}


GRAPH = {name: imports_of(name) for name in MODULES}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of modules (first == last), or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return [*stack[stack.index(nxt):], nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)):
            return cycle
    return None


def test_every_command_is_an_entry_point() -> None:
    commands = {"train", "eval", "predict", "render", "report", "score", "unseen", "bench", "export"}
    assert {name.split(".")[1] for name in ENTRY_POINTS} == commands


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_module_imports_an_entry_point(name: str) -> None:
    offending = sorted(GRAPH[name] & set(ENTRY_POINTS))
    assert not offending, f"{name} imports the entry point(s) {offending}: move what it needs into the library"


def test_import_graph_has_no_cycle() -> None:
    cycle = find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_cycle_finder_finds_a_planted_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_imports_are_resolved_to_modules() -> None:
    source = """
from typing import TYPE_CHECKING
from matl.geometry import homography, warp_image
from . import config
import matl.metrics.pose
if TYPE_CHECKING:
    from matl.train import main
def f():
    from ..data import gallery
"""
    assert imports_of("matl.utils.io", source) == {
        "matl.geometry.homography", "matl.geometry", "matl.utils.config", "matl.metrics.pose", "matl.data.gallery"}
