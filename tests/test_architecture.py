"""The package's layering rules, read from its source (``docs/architecture.md``).

Every ``.py`` under ``vpr_explorer/`` is parsed (never imported) and every import in it,
at module level or inside a function, becomes an edge of the import graph. The rules:

* no import cycle: a shared piece moves down into a module both sides import;
* no module uses another module's private name (``from vpr_explorer.a import _x``, or
  ``a._x`` on an imported ``vpr_explorer`` module): what crosses a module is public;
* streamlit is imported only under ``vpr_explorer/app/``, and not by ``app/__init__.py`` or
  ``app/launch.py``, which the command line imports;
* imports point down the flow (``LAYERS``): a module imports its own layer or lower ones,
  except the imports ``KNOWN_UPWARD`` lists.

Each test reports every offender at once, with the file and line of each import.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass, field
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "vpr_explorer"

LAYERS = {
    "errors": 0, "settings": 0,
    "data": 1,
    "descriptors": 2,
    "method": 3,
    "protocols": 4,
    "views": 5,
    "pipeline": 6,
    "recording": 7,
    "app": 8, "cli": 8,
}
"""Each top-level module or folder of the package by its place in the data flow (``docs/architecture.md``)."""

KNOWN_UPWARD: set[tuple[str, str]] = set()
"""Imports of a higher layer that exist today; a new one fails, and a listed one that is gone must leave the list."""


@dataclass(frozen=True)
class Use:
    """One place a module uses another: the target module, the name used of it, and where."""

    target: str
    name: str | None
    path: Path
    line: int


@dataclass
class Graph:
    """The package's modules and what each imports.

    Attributes:
        files: module name (``vpr_explorer.method.places``) -> its file.
        edges: module -> imported module -> the first line that imports it.
        private: uses of a private name of another module, in file order.
        streamlit: ``(path, line)`` of each streamlit import.
    """

    files: dict[str, Path]
    edges: dict[str, dict[str, int]] = field(default_factory=dict)
    private: list[Use] = field(default_factory=list)
    streamlit: list[tuple[Path, int]] = field(default_factory=list)


def module_name(path: Path, package: Path) -> str:
    """``vpr_explorer/method/places.py`` -> ``vpr_explorer.method.places``; a package's ``__init__`` is the package."""
    parts = path.relative_to(package.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _base(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    """The absolute module an ``ImportFrom`` names (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    parts = module.split(".") if is_package else module.split(".")[:-1]
    parts = parts[: len(parts) - (node.level - 1)]
    return ".".join(parts + ([node.module] if node.module else []))


def _dotted(node: ast.expr) -> str | None:
    """``a.b.c`` of an attribute chain of names, else None."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        head = _dotted(node.value)
        return None if head is None else f"{head}.{node.attr}"
    return None


def read_graph(package: Path = PACKAGE) -> Graph:
    """Parse every module under ``package`` into its import graph and its crossings.

    Args:
        package: the package folder; its name is the top-level module name.

    Returns:
        The graph: an ``import a.b`` is an edge to ``a.b``; ``from a import b`` is an edge to
        ``a.b`` when that is a module, else to ``a``. Imports of modules outside the
        package are no edges.
    """
    graph = Graph({module_name(p, package): p for p in sorted(package.rglob("*.py"))})
    for module in graph.files:
        _read_module(graph, module, package.name)
    return graph


def _read_module(graph: Graph, module: str, top: str) -> None:
    """Add ``module``'s imports, private-name uses and streamlit imports to ``graph``."""
    path = graph.files[module]
    tree = ast.parse(path.read_text(), filename=str(path))
    edges: dict[str, int] = {}
    bound: dict[str, str] = {}  # local name -> the package module it is bound to

    def edge(target: str, line: int) -> None:
        if target != module:
            edges[target] = min(line, edges.get(target, line))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "streamlit":
                    graph.streamlit.append((path, node.lineno))
                if alias.name in graph.files:
                    edge(alias.name, node.lineno)
                    bound[alias.asname or alias.name.split(".")[0]] = alias.name if alias.asname else top
        elif isinstance(node, ast.ImportFrom):
            base = _base(node, module, path.name == "__init__.py")
            if base.split(".")[0] == "streamlit":
                graph.streamlit.append((path, node.lineno))
            if base.split(".")[0] != top:
                continue
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                if submodule in graph.files:
                    edge(submodule, node.lineno)
                    bound[alias.asname or alias.name] = submodule
                elif base in graph.files:
                    edge(base, node.lineno)
                    if is_private(alias.name) and base != module:
                        graph.private.append(Use(base, alias.name, path, node.lineno))
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Attribute) and is_private(node.attr)):
            continue
        head = _dotted(node.value)  # ``a.b`` of ``a.b._x``
        first, _, rest = (head or "").partition(".")
        target = bound.get(first)
        if target is not None and rest:
            target = head if target == top else f"{target}.{rest}"
        if target in graph.files and target != module:
            graph.private.append(Use(target, node.attr, path, node.lineno))
    graph.edges[module] = edges


def _shortest_cycle(edges: dict[str, dict[str, int]], members: set[str], start: str) -> list[str]:
    """A shortest cycle from ``start`` back to it within ``members`` (breadth first)."""
    previous: dict[str, str] = {}
    frontier = [start]
    while start not in previous:
        reached = []
        for v in frontier:
            for w in sorted(edges.get(v, ())):
                if w in members and w not in previous:
                    previous[w] = v
                    reached.append(w)
        frontier = reached
    path = [start]
    while True:
        path.append(previous[path[-1]])
        if path[-1] == start:
            return path[::-1]


def cycles(edges: dict[str, dict[str, int]]) -> list[list[str]]:
    """A shortest cycle through each module that lies on one, each cycle listed once.

    Returns:
        Each cycle as the modules in import order, the first repeated at the end; sorted.
    """
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []

    def connect(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                connect(w)
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
                components.append(component)

    for v in sorted(edges):
        if v not in index:
            connect(v)
    found: list[list[str]] = []
    for component in components:
        members = set(component)
        for start in sorted(component):  # a shortest cycle through each member, each cycle once
            cycle = _shortest_cycle(edges, members, start)
            first = cycle.index(min(cycle))
            cycle = cycle[first:-1] + cycle[:first] + [cycle[first]]  # rotated to start at its least name
            if cycle not in found:
                found.append(cycle)
    return sorted(found)


def _where(path: Path, line: int) -> str:
    return f"{path.relative_to(PACKAGE.parent) if PACKAGE.parent in path.parents else path}:{line}"


def cycle_problems(graph: Graph) -> list[str]:
    """Each import cycle, named with the line of each import in it."""
    problems = []
    for cycle in cycles(graph.edges):
        steps = [f"{a} -> {b} ({_where(graph.files[a], graph.edges[a][b])})" for a, b in zip(cycle, cycle[1:])]
        problems.append("cycle " + " -> ".join(cycle) + ":\n    " + "\n    ".join(steps))
    return problems


def private_problems(graph: Graph) -> list[str]:
    """Each use of another module's private name."""
    uses = sorted(graph.private, key=lambda u: (u.path, u.line, u.name))
    return [f"{_where(u.path, u.line)}: uses {u.target}.{u.name}" for u in uses]


def streamlit_problems(graph: Graph, package: Path = PACKAGE) -> list[str]:
    """Each streamlit import outside the app's server-side modules."""
    app = package / "app"
    allowed = [p for p in app.rglob("*.py") if p not in (app / "__init__.py", app / "launch.py")]
    return [f"{_where(path, line)}: imports streamlit" for path, line in graph.streamlit if path not in allowed]


def layer_problems(graph: Graph) -> list[str]:
    """Each module outside ``LAYERS``, each import of a higher layer not in ``KNOWN_UPWARD``, each stale entry."""
    top = PACKAGE.name
    unplaced = sorted({m.split(".")[1] for m in graph.files if m != top and m.split(".")[1] not in LAYERS})
    problems = [f"{top}.{name}: not placed in LAYERS" for name in unplaced]
    upward = set()
    for a, imports in sorted(graph.edges.items()):
        for b, line in sorted(imports.items()):
            if a != top and b != top and LAYERS.get(b.split(".")[1], -1) > LAYERS.get(a.split(".")[1], -1):
                upward.add((a, b))
                if (a, b) not in KNOWN_UPWARD:
                    problems.append(f"{_where(graph.files[a], line)}: {a} imports the higher layer {b}")
    problems += [f"KNOWN_UPWARD lists {a} -> {b}, which no longer exists: remove it" for a, b in
                 sorted(KNOWN_UPWARD - upward)]
    return problems


@pytest.fixture(scope="module")
def graph() -> Graph:
    return read_graph()


def test_the_graph_holds_every_module_and_function_level_imports(graph):
    assert len(graph.files) > 50 and "vpr_explorer.method.places" in graph.files
    assert "vpr_explorer.errors" in graph.edges["vpr_explorer.method.places"]
    assert sum(map(len, graph.edges.values())) > 3 * len(graph.files)


def test_no_import_cycle(graph):
    problems = cycle_problems(graph)
    if problems:
        pytest.fail(f"{len(problems)} import cycle(s):\n" + "\n".join(problems), pytrace=False)


def test_no_module_uses_another_modules_private_name(graph):
    problems = private_problems(graph)
    if problems:
        pytest.fail(f"{len(problems)} private name(s) cross modules:\n" + "\n".join(problems), pytrace=False)


def test_imports_point_down_the_flow(graph):
    problems = layer_problems(graph)
    if problems:
        pytest.fail(f"{len(problems)} layering problem(s):\n" + "\n".join(problems), pytrace=False)


def test_only_the_app_imports_streamlit(graph):
    problems = streamlit_problems(graph)
    if problems:
        pytest.fail(f"{len(problems)} streamlit import(s) outside the app:\n" + "\n".join(problems), pytrace=False)


def test_the_rules_find_each_kind_of_offender(tmp_path):
    """A small package with one of each offence: the walker finds all of them."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "app").mkdir()
    files = {
        "__init__.py": "",
        "a.py": "from pkg.sub import b\n_hidden = 1\n",
        "sub/__init__.py": "from . import b\n",
        "sub/b.py": "def f():\n    from pkg.a import _hidden\n    import pkg.c as c\n    return c._x\n",
        "c.py": "import pkg.a\n_x = 2\ny = pkg.a._hidden\n",
        "d.py": "import streamlit as st\n",
        "app/__init__.py": "",
        "app/page.py": "import streamlit\nfrom pkg import c\nc.y\n",
    }
    for name, text in files.items():
        (pkg / name).write_text(text)
    g = read_graph(pkg)
    assert set(g.edges["pkg.sub.b"]) == {"pkg.a", "pkg.c"}  # function-level imports count
    assert g.edges["pkg.sub"] == {"pkg.sub.b": 1}  # relative import of a submodule
    assert cycles(g.edges) == [["pkg.a", "pkg.sub.b", "pkg.a"], ["pkg.a", "pkg.sub.b", "pkg.c", "pkg.a"]]
    assert sorted((u.path.name, u.target, u.name) for u in g.private) == [
        ("b.py", "pkg.a", "_hidden"), ("b.py", "pkg.c", "_x"), ("c.py", "pkg.a", "_hidden")]
    assert sorted(g.streamlit) == sorted([(pkg / "d.py", 1), (pkg / "app" / "page.py", 1)])
    assert [s.split(":")[0] for s in streamlit_problems(g, pkg)] == [str(pkg / "d.py")]


def floors(edges: dict[str, dict[str, int]]) -> int:
    """The longest chain of imports between the package's modules (1: a module that imports none of them)."""
    inside = {m: [t for t in targets if t in edges and t != m] for m, targets in edges.items()}
    depth: dict[str, int] = {}

    def of(m: str) -> int:
        if m not in depth:
            depth[m] = 0  # a cycle stops here instead of recursing for ever
            depth[m] = 1 + max((of(t) for t in inside[m]), default=0)
        return depth[m]

    return max((of(m) for m in inside), default=0)


def test_floors_count_the_longest_chain():
    assert floors({"a": {"b": 1}, "b": {"c": 1}, "c": {}, "d": {"c": 1}}) == 3
    assert floors({"a": {}}) == 1


if __name__ == "__main__":  # python tests/test_architecture.py [PACKAGE]: the graph in one line
    import sys

    g = read_graph(Path(sys.argv[1]) if len(sys.argv) > 1 else PACKAGE)
    print(f"{len(g.edges)} modules, {floors(g.edges)} floors, {len(cycles(g.edges))} cycles")
