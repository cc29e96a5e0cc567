"""The package's layering, as its imports show it: no import cycle between modules, and
no package importing one of a higher layer (README, "What is here").

Every ``import``/``from ... import`` of ``ucom_tools`` counts, wherever it is written: at
the top, inside a function (a lazy import is still a dependency) or under
``TYPE_CHECKING``.  The layers, lowest first; a package may import its own layer's and
lower ones, except that ``ops`` (the PC's operations) and ``virtual`` (the boards they
run against) never import each other, and ``trace`` stays a layer of its own below
``ops``.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "ucom_tools"

LAYERS: tuple[frozenset[str], ...] = (
    frozenset({"errors", "native", "compiled", "plugons", "edgelists", "courtesy",
               "__init__"}),
    frozenset({"wire", "fileio", "signals"}),
    frozenset({"memory"}),
    frozenset({"image", "config", "protocol"}),
    frozenset({"transport", "trace"}),
    frozenset({"ops", "virtual"}),
    frozenset({"conformance", "net", "gateway"}),
    frozenset({"viewers"}),
    frozenset({"cli"}),
    frozenset({"__main__"}),
)
APART: tuple[tuple[str, str], ...] = (("ops", "virtual"), ("virtual", "ops"))


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports() -> dict[str, set[str]]:
    """Each module's imports of other ``ucom_tools`` modules (names resolved to the
    longest module that exists: ``from ucom_tools.ops import flash`` is ops.flash)."""
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    graph: dict[str, set[str]] = defaultdict(set)

    def resolve(name: str) -> str | None:
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    for mod, path in files.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                targets = [f"{base}.{a.name}" for a in node.names]
            for target in targets:
                if target.startswith("ucom_tools"):
                    found = resolve(target)
                    if found is not None and found != mod:
                        graph[mod].add(found)
    for mod in files:
        graph.setdefault(mod, set())
    return graph


def _layer_of(module: str) -> tuple[str, int]:
    parts = module.split(".")
    top = parts[1] if len(parts) > 1 else "__init__"
    for rank, layer in enumerate(LAYERS):
        if top in layer:
            return top, rank
    raise AssertionError(f"{module}: {top!r} is in no layer of tests/test_layers.py "
                         "(a new package: give it its place there and in the README)")


def test_every_package_has_a_layer() -> None:
    for module in _imports():
        _layer_of(module)


def test_nothing_imports_upward() -> None:
    wrong = []
    for module, targets in sorted(_imports().items()):
        top, rank = _layer_of(module)
        for target in sorted(targets):
            other, other_rank = _layer_of(target)
            if other_rank > rank or (top, other) in APART:
                wrong.append(f"{module} imports {target}")
    assert not wrong, "\n".join(wrong)


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = 0

    def visit(start: str) -> None:
        nonlocal counter
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    cycles.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return cycles


def test_no_import_cycle() -> None:
    cycles = _cycles(_imports())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_checks_find_what_they_forbid() -> None:
    """The imports are read (lazy ones too), and a cycle is found where there is one."""
    graph = _imports()
    assert "ucom_tools.wire.mca" in graph["ucom_tools.protocol.mca"]
    assert _layer_of("ucom_tools.wire.mca")[1] < _layer_of("ucom_tools.ops.remote")[1]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
