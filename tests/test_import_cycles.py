"""No import cycles between the modules of the repo's packages.

Every import statement of every module counts: top-level ones, lazy ones inside functions, ones
under ``if TYPE_CHECKING:`` (a cycle only type checkers follow still ties two modules into one
idea) and ``importlib.import_module("literal")`` calls; an ``import_module`` of a computed name
(the CLI's lazy command table) is not seen. A cycle is a set
of modules each of which reaches the others through such imports (a strongly connected
component of the import graph with more than one module). Edges are resolved precisely:

* ``import a.b.c`` and ``from a.b import c`` (``c`` a submodule) point at ``a.b.c``;
* ``from a.b import Name`` where ``a/b/__init__.py`` re-exports ``Name`` from a submodule points
  at the submodule that defines ``Name`` (a package's re-exports are the package itself, so
  ``pkg/__init__`` importing ``pkg.sub`` and ``pkg.other`` importing a re-exported name is no
  cycle); a name the ``__init__`` defines itself points at the package;
* the implicit import of parent packages (``a`` and ``a.b`` when ``a.b.c`` is imported) is not
  counted: a package's ``__init__`` importing its submodules is normal.

Run as a script (``python tests/test_import_cycles.py``) to print every cycle with the import
lines that make it.
"""

from __future__ import annotations

import ast
import dataclasses
import itertools
import sys
import textwrap
from collections.abc import Iterable, Iterator
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the repo's own top-level packages (the ones that exist are checked)
PACKAGES = (
    "protocol", "core", "edge_agent", "backend_service", "mapper", "robot_bridge", "simulation",
    "calibration", "training", "smartedge", "lab",
)


@dataclasses.dataclass(frozen=True)
class Edge:
    """One import: ``source`` imports ``target`` at ``path:line`` (path relative to the root)."""

    source: str
    target: str
    path: str
    line: int


def discover_modules(root: Path, packages: Iterable[str]) -> dict[str, Path]:
    """Dotted module name → file for every ``.py`` file of ``packages`` under ``root``
    (``pkg/__init__.py`` is ``pkg``)."""
    modules: dict[str, Path] = {}
    for package in packages:
        base = root / package
        if not (base / "__init__.py").is_file():
            continue
        for path in sorted(base.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            modules[".".join(parts)] = path
    return modules


def _is_package(path: Path) -> bool:
    return path.name == "__init__.py"


def _absolute(module: str, path: Path, node: ast.ImportFrom) -> str:
    """The absolute module name a ``from ... import`` statement names."""
    if not node.level:
        return node.module or ""
    package = module if _is_package(path) else module.rpartition(".")[0]
    for _ in range(node.level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{node.module}" if node.module else package


def _known_prefix(name: str, modules: dict[str, Path]) -> str | None:
    """The longest dotted prefix of ``name`` that is one of ``modules`` (``None``: external)."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        candidate = ".".join(parts[:n])
        if candidate in modules:
            return candidate
    return None


def _literal_import(node: ast.Call) -> str | None:
    """The module of ``importlib.import_module("a.b")`` / ``__import__("a.b")``, else None."""
    func = node.func
    name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    if isinstance(arg, ast.Constant) and isinstance(arg.value, str) and not arg.value.startswith(
            "."):
        return arg.value
    return None


class ImportGraph:
    """The import graph of ``packages`` under ``root`` (see the module docstring)."""

    def __init__(self, root: Path, packages: Iterable[str] = PACKAGES) -> None:
        self.root = root
        self.modules = discover_modules(root, packages)
        self._trees = {name: ast.parse(path.read_text(encoding="utf-8"), str(path))
                       for name, path in self.modules.items()}
        self._exports = {name: self._package_exports(name)
                         for name, path in self.modules.items() if _is_package(path)}
        self.edges = [edge for name in self.modules for edge in self._module_edges(name)]

    def _package_exports(self, package: str) -> dict[str, tuple[str, str]]:
        """Names a package's ``__init__`` imports from elsewhere: name → (module, its name)."""
        exports: dict[str, tuple[str, str]] = {}
        path = self.modules[package]
        for node in ast.walk(self._trees[package]):
            if isinstance(node, ast.ImportFrom):
                base = _absolute(package, path, node)
                for alias in node.names:
                    if alias.name != "*":
                        exports[alias.asname or alias.name] = (base, alias.name)
        return exports

    def _resolve_name(self, base: str, name: str, seen: frozenset[str] = frozenset()) -> str | None:
        """The module that ``from base import name`` depends on (``None``: external)."""
        submodule = f"{base}.{name}"
        if submodule in self.modules:
            return submodule
        if base in self._exports and base not in seen and name in self._exports[base]:
            origin, origin_name = self._exports[base][name]
            resolved = self._resolve_name(origin, origin_name, seen | {base})
            if resolved is not None:
                return resolved
        return _known_prefix(base, self.modules)

    def _module_edges(self, module: str) -> Iterator[Edge]:
        path = self.modules[module]
        rel = path.relative_to(self.root).as_posix()
        for node in ast.walk(self._trees[module]):
            targets: list[str | None] = []
            if isinstance(node, ast.Import):
                targets = [_known_prefix(alias.name, self.modules) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _absolute(module, path, node)
                targets = [_known_prefix(base, self.modules) if alias.name == "*"
                           else self._resolve_name(base, alias.name) for alias in node.names]
            elif isinstance(node, ast.Call) and (literal := _literal_import(node)):
                targets = [_known_prefix(literal, self.modules)]
            for target in targets:
                if target is not None and target != module:
                    yield Edge(module, target, rel, node.lineno)

    def adjacency(self) -> dict[str, set[str]]:
        """Module → the modules it imports."""
        graph: dict[str, set[str]] = {name: set() for name in self.modules}
        for edge in self.edges:
            graph[edge.source].add(edge.target)
        return graph

    def cycles(self) -> list[list[str]]:
        """The strongly connected components with more than one module, each sorted, the list
        sorted; empty when the graph is acyclic."""
        return sorted(sorted(c) for c in _strongly_connected(self.adjacency()) if len(c) > 1)

    def describe(self, component: list[str]) -> str:
        """One cycle through ``component`` (shortest from its first module), with the import
        lines that make it."""
        graph = self.adjacency()
        members = set(component)
        start = component[0]
        # breadth-first from start's successors back to start, inside the component
        parents: dict[str, str] = {}
        frontier = [start]
        while frontier and start not in parents:
            nxt = []
            for node in frontier:
                for target in sorted(graph[node] & members):
                    if target not in parents:
                        parents[target] = node
                        nxt.append(target)
            frontier = nxt
        path = [start]
        while True:
            path.append(parents[path[-1]])
            if path[-1] == start:
                break
        path.reverse()
        lines = []
        for source, target in itertools.pairwise(path):
            where = next(e for e in self.edges if e.source == source and e.target == target)
            lines.append(f"  {source} -> {target}  ({where.path}:{where.line})")
        return f"cycle of {len(component)} modules: {', '.join(component)}\n" + "\n".join(lines)


def _strongly_connected(graph: dict[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm, iterative (import graphs can be deep)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[set[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            advanced = False
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = counter
                    counter += 1
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(sorted(graph[succ]))))
                    advanced = True
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = set()
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.add(member)
                    if member == node:
                        break
                out.append(component)
    return out


# --------------------------------------------------------------------------------------------
# tests
# --------------------------------------------------------------------------------------------


def test_no_import_cycles_in_the_repo() -> None:
    graph = ImportGraph(REPO_ROOT)
    # the scan did see the repo: every package, and an import known to be there
    assert {name.split(".")[0] for name in graph.modules} >= {
        "protocol", "core", "edge_agent", "backend_service", "robot_bridge", "simulation",
        "smartedge", "lab", "calibration", "training"}
    pairs = {(edge.source, edge.target) for edge in graph.edges}
    assert ("robot_bridge.adapters.registry", "robot_bridge.adapters.rmw_zenoh") in pairs
    cycles = graph.cycles()
    assert not cycles, "import cycles:\n" + "\n".join(graph.describe(c) for c in cycles)


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text), encoding="utf-8")


def test_checker_finds_a_lazy_cycle_and_names_its_lines(tmp_path: Path) -> None:
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a.py": "from pkg.b import thing\n",
        "pkg/b.py": "thing = 1\n\ndef late():\n    from pkg import a\n    return a\n",
        "pkg/c.py": "import pkg.a\n",  # reaches the cycle, is not part of it
    })
    graph = ImportGraph(tmp_path, ("pkg",))
    assert graph.cycles() == [["pkg.a", "pkg.b"]]
    text = graph.describe(["pkg.a", "pkg.b"])
    assert "pkg/a.py:1" in text and "pkg/b.py:4" in text


def test_checker_counts_relative_type_checking_and_importlib_imports(tmp_path: Path) -> None:
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/sub/__init__.py": "",
        "pkg/sub/x.py": "from ..y import f\n",
        "pkg/y.py": """\
            from typing import TYPE_CHECKING
            if TYPE_CHECKING:
                from pkg.z import Z
            def f():
                pass
            """,
        "pkg/z.py": """\
            import importlib
            def load():
                return importlib.import_module("pkg.sub.x")
            """,
    })
    graph = ImportGraph(tmp_path, ("pkg",))
    assert graph.cycles() == [["pkg.sub.x", "pkg.y", "pkg.z"]]


def test_checker_resolves_package_reexports_to_their_submodule(tmp_path: Path) -> None:
    files = {
        "pkg/__init__.py": "from pkg.base import Base\nfrom pkg.impl import Impl\nLOCAL = 1\n",
        "pkg/base.py": "class Base: ...\n",
        "pkg/impl.py": "from pkg import Base\n\nclass Impl(Base): ...\n",
        "other/__init__.py": "",
        "other/user.py": "import json\nfrom pkg import Impl\nfrom other import *\n",
    }
    _write(tmp_path, files)
    graph = ImportGraph(tmp_path, ("pkg", "other"))
    assert graph.cycles() == []  # pkg -> pkg.impl -> pkg.base, not back to pkg
    targets = {(e.source, e.target) for e in graph.edges}
    assert ("pkg.impl", "pkg.base") in targets and ("other.user", "pkg.impl") in targets
    # a name the __init__ defines itself is the package: that is a real cycle
    _write(tmp_path, {"pkg/impl.py": "from pkg import Base, LOCAL\n\nclass Impl(Base): ...\n"})
    assert ImportGraph(tmp_path, ("pkg", "other")).cycles() == [["pkg", "pkg.impl"]]


if __name__ == "__main__":
    found = ImportGraph(REPO_ROOT)
    print(f"{len(found.modules)} modules, {len(found.edges)} imports", file=sys.stderr)
    for component in found.cycles():
        print(found.describe(component))
    sys.exit(1 if found.cycles() else 0)
