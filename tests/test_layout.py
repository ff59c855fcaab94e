"""The package's import graph and names: imports run down the layers, never in a cycle; one ``Recognizer``.

Every module under ``matl/`` is parsed with :mod:`ast` (nothing is imported). Every ``import`` counts:
those inside functions (a cycle hidden in a function is still a cycle) and those under
``if TYPE_CHECKING:`` (an annotation is a dependency too).
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
TREES = {name: ast.parse(path.read_text()) for name, path in MODULES.items()}


def is_entry_point(name: str) -> bool:
    """``python -m matl.<name>``: a top-level module that runs ``main()`` when executed."""
    if name.count(".") != 1:
        return False
    return any(isinstance(node, ast.If) and "__main__" in ast.unparse(node.test) for node in TREES[name].body)


ENTRY_POINTS = sorted(name for name in MODULES if is_entry_point(name))

#: the layers from the bottom up: a module imports its own package and the packages of lower layers only
#: (two packages of one layer do not import each other). ``matl`` is the package itself (``from matl import
#: Recognizer``), above everything but the commands, which sit on top of all.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("utils", "geometry", "paper"),
    ("data", "losses", "metrics"),
    ("models",),
    ("baselines",),
    ("inference",),
    ("training", "reporting"),
    ("evaluation",),
    ("matl",),
    ("commands",),
)
RANK = {package: rank for rank, packages in enumerate(LAYERS) for package in packages}


def imports_of(name: str, source: str | None = None) -> set[str]:
    """The ``matl`` modules that module ``name`` imports (``from package import submodule`` names the submodule)."""
    path = MODULES[name]
    tree = TREES[name] if source is None else ast.parse(source)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
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


def layer_of(name: str) -> str:
    """The layer name of a module: its subpackage (``matl.models.stn`` -> ``models``), ``commands`` for an entry
    point, its own name for another top-level module (``matl.paper`` -> ``paper``), ``matl`` for the package."""
    if name in ENTRY_POINTS:
        return "commands"
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else "matl"


def upward_imports(graph: dict[str, set[str]], layer: dict[str, str] | None = None) -> list[str]:
    """Every import of ``graph`` that leaves its package for one not below it, as ``"a -> b (la -> lb)"``."""
    found = []
    for name, imported in sorted(graph.items()):
        for other in sorted(imported):
            src, dst = (layer_of(name), layer_of(other)) if layer is None else (layer[name], layer[other])
            if src != dst and RANK[dst] >= RANK[src]:
                found.append(f"{name} -> {other} ({src} -> {dst})")
    return found


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
    commands = {"train", "eval", "predict", "enrol", "render", "report", "score", "unseen", "bench", "export",
                "train_foreground"}
    assert {name.split(".")[1] for name in ENTRY_POINTS} == commands


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_module_imports_an_entry_point(name: str) -> None:
    offending = sorted(GRAPH[name] & set(ENTRY_POINTS))
    assert not offending, f"{name} imports the entry point(s) {offending}: move what it needs into the library"


def test_every_module_has_a_layer() -> None:
    missing = sorted({layer_of(name) for name in MODULES} - set(RANK))
    assert not missing, f"no layer for {missing}: add them to LAYERS where their imports put them"


def test_imports_run_down_the_layers() -> None:
    upward = upward_imports(GRAPH)
    assert not upward, "imports that run up or across the layers:\n" + "\n".join(upward)


@pytest.mark.parametrize("low", ["models", "data", "geometry", "utils"])
def test_models_and_below_never_reach_the_serving_side(low: str) -> None:
    served = {"inference", "evaluation", "baselines"}
    offending = sorted(f"{name} -> {other}" for name in GRAPH if layer_of(name) == low
                       for other in GRAPH[name] if layer_of(other) in served)
    assert not offending, f"matl.{low} imports the serving side: {offending}"


def test_import_graph_has_no_cycle() -> None:
    cycle = find_cycle(GRAPH)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_one_class_is_named_recognizer() -> None:
    defined = sorted(name for name, tree in TREES.items() for node in ast.walk(tree)
                     if isinstance(node, ast.ClassDef) and node.name == "Recognizer")
    assert defined == ["matl.inference.api"], f"classes named Recognizer in {defined}: only matl.Recognizer is"


def test_cycle_finder_finds_a_planted_cycle() -> None:
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_layer_check_finds_planted_violations() -> None:
    layer = {"m": "models", "i": "inference", "d": "data", "l": "losses"}
    graph = {"m": {"i", "d"}, "i": {"m"}, "d": {"l"}, "l": set()}
    assert upward_imports(graph, layer) == ["d -> l (data -> losses)", "m -> i (models -> inference)"]


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
        "matl.geometry.homography", "matl.geometry", "matl.utils.config", "matl.metrics.pose", "matl.data.gallery",
        "matl.train"}
