"""The house's layer order, read from the imports themselves (docs: design, "Layers").

A module may import only from its own layer or the layers below it, and no set of modules may import
each other in a circle. Function-level imports count too: a lazy import is still a dependency. Imports
under ``if TYPE_CHECKING:`` are annotations only and do not count.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "drago"

#: Lowest first. A module's layer is the longest prefix of its dotted name listed in LAYER_OF.
LAYERS = ("core", "envs", "config", "agent", "continual", "training", "eval", "report", "study", "api", "cli")
LAYER_OF = {
    "drago.seeding": "core",
    "drago.plugins": "core",
    "drago.envs": "envs",
    "drago.config": "config",
    "drago.settings_docs": "config",
    "drago.agent": "agent",
    "drago.continual": "continual",
    "drago.training": "training",
    "drago.eval": "eval",
    "drago.report": "report",
    "drago.study": "study",
    "drago.api": "api",
    "drago": "api",  # the package itself: lazy re-exports of drago.api
    "drago.cli": "cli",
    "drago.__main__": "cli",
}

#: Inside the study layer, lowest first: the plan knows no backend, and the local backend nothing of SLURM. A
#: module's part is the longest prefix listed (``drago.study`` itself, the package's re-exports, is the top).
STUDY_PARTS = ("drago.study.plan", "drago.study.report", "drago.study.local", "drago.study.slurm",
               "drago.study.command", "drago.study")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> str:
    for prefix in sorted(LAYER_OF, key=len, reverse=True):
        if module == prefix or module.startswith(prefix + "."):
            return LAYER_OF[prefix]
    raise AssertionError(f"{module} has no layer: add it to LAYER_OF in tests/test_layers.py")


def _type_checking_only(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The drago modules a file imports, anywhere in it (``from drago.x import y`` counts y when it is a module)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.If) and _type_checking_only(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == "drago")
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.split(".")[0] == "drago":
            for alias in node.names:
                child = f"{node.module}.{alias.name}"
                found.add(child if child in modules else node.module)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return {name for name in found if name in modules}


def import_graph() -> dict[str, set[str]]:
    files = {module_name(path): path for path in PACKAGE.rglob("*.py")}
    modules = set(files)
    return {name: imports_of(path, modules) - {name} for name, path in files.items()}


def test_every_module_has_a_layer():
    for module in import_graph():
        layer(module)


def test_no_module_imports_from_a_layer_above_its_own():
    rank = {name: i for i, name in enumerate(LAYERS)}
    upward = sorted(f"{module} ({layer(module)}) imports {target} ({layer(target)})"
                    for module, targets in import_graph().items() for target in targets
                    if rank[layer(target)] > rank[layer(module)])
    assert not upward, "imports against the layer order:\n" + "\n".join(upward)


def test_inside_the_study_no_module_imports_from_a_part_above_its_own():
    def part(module: str) -> int:
        found = [p for p in STUDY_PARTS if module == p or module.startswith(p + ".")]
        assert found, f"{module} has no part of the study: add it to STUDY_PARTS in tests/test_layers.py"
        return STUDY_PARTS.index(max(found, key=len))

    upward = sorted(f"{module} imports {target}" for module, targets in import_graph().items()
                    if layer(module) == "study" for target in targets
                    if layer(target) == "study" and part(target) > part(module))
    assert not upward, "imports against the study's order:\n" + "\n".join(upward)


def test_no_import_circles():
    circles = strongly_connected(import_graph())
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(sorted(c)) for c in circles)


def strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm: the components of more than one module."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[set[str]] = []
    counter = [0]

    def connect(node: str) -> None:
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for target in graph.get(node, ()):
            if target not in index:
                connect(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = set()
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.add(member)
                if member == node:
                    break
            if len(component) > 1:
                components.append(component)

    for node in sorted(graph):
        if node not in index:
            connect(node)
    return components


def test_the_check_sees_an_upward_import_and_a_circle(tmp_path):
    upward = tmp_path / "upward.py"
    upward.write_text("def f():\n    from drago.cli import main\n")
    assert imports_of(upward, {"drago.cli"}) == {"drago.cli"}
    hinted = tmp_path / "hinted.py"
    hinted.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from drago.cli import main\n")
    assert imports_of(hinted, {"drago.cli"}) == set()
    assert strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
