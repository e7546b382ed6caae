"""The edge runs on Python 3.10 (JetPack 6 = Ubuntu 22.04): ``requires-python`` allows it,
and what an edge board runs (``protocol``, ``edge_agent`` and every module of the top floor
that ``smartedge edge-agent`` loads) parses with the 3.10 grammar and names nothing of the
standard library that is newer than 3.10.

The grammar check is ``ast.parse(..., feature_version=(3, 10))`` (``except*``, PEP 695 type
parameters and ``type`` aliases, PEP 701 f-strings fail it). The library check walks the
syntax tree, outside ``if TYPE_CHECKING:``, for the names in :data:`NEWER_THAN_310`
(``import tomllib``, ``from typing import Self``, ``datetime.UTC``, ``ExceptionGroup``,
``exc.add_note(...)``...) and for generic NamedTuples (``class X(NamedTuple, Generic[T])``
imports fine on 3.11 and raises ``TypeError`` on 3.10: found in ``core/history.py``
this way). When a ``python3.10`` that runs is on the PATH, the same files are also
byte-compiled by it.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

EDGE_PACKAGES = ("protocol", "core", "edge_agent")
#: standard-library names that Python 3.10 lacks: module → names added in 3.11 or later
#: (``""``: the module itself is new)
NEWER_THAN_310: dict[str, frozenset[str]] = {
    "tomllib": frozenset({""}),
    "wsgiref.types": frozenset({""}),
    "typing": frozenset({"Self", "LiteralString", "Never", "assert_never", "assert_type",
                         "reveal_type", "Required", "NotRequired", "TypeVarTuple", "Unpack",
                         "dataclass_transform", "override", "TypeAliasType", "get_overloads",
                         "clear_overloads", "ReadOnly", "TypeIs", "NoDefault"}),
    "datetime": frozenset({"UTC"}),
    "enum": frozenset({"StrEnum", "ReprEnum", "verify", "member", "nonmember", "property",
                       "global_enum", "EnumCheck", "FlagBoundary", "show_flag_values"}),
    "asyncio": frozenset({"TaskGroup", "timeout", "timeout_at", "Runner", "Barrier",
                          "BrokenBarrierError", "Timeout", "eager_task_factory"}),
    "contextlib": frozenset({"chdir"}),
    "hashlib": frozenset({"file_digest"}),
    "math": frozenset({"cbrt", "exp2", "sumprod", "fma"}),
    "itertools": frozenset({"batched"}),
    "operator": frozenset({"call"}),
    "logging": frozenset({"getLevelNamesMapping", "getHandlerByName", "getHandlerNames"}),
    "inspect": frozenset({"markcoroutinefunction", "getmembers_static"}),
    "re": frozenset({"NOFLAG"}),
    "sys": frozenset({"exception", "activate_stack_trampoline", "monitoring"}),
}
#: builtins and methods that Python 3.10 lacks
NEWER_BUILTINS = frozenset({"ExceptionGroup", "BaseExceptionGroup"})
NEWER_METHODS = frozenset({"add_note", "walk_up"})


def _package_files(package: str) -> list[Path]:
    return sorted(p for p in (REPO_ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)


def _edge_agent_cli_files() -> list[Path]:
    """The repository's modules a fresh ``smartedge edge-agent --help`` loads (the top-floor
    entry point and the source plug-ins it registers)."""
    code = textwrap.dedent("""
        import contextlib, io, sys
        from smartedge.cli import main
        with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
            main(["edge-agent", "--help"])
        for m in list(sys.modules.values()):
            f = getattr(m, "__file__", None)
            if f:
                print(f)
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True,
                         text=True, timeout=120, check=True).stdout
    root = REPO_ROOT.resolve()
    files = {Path(line).resolve() for line in out.splitlines() if line.endswith(".py")}
    return sorted(f for f in files if root in f.parents and ".venv" not in f.parts)


@pytest.fixture(scope="module")
def edge_files() -> list[Path]:
    files = {f for package in EDGE_PACKAGES for f in _package_files(package)}
    files |= set(_edge_agent_cli_files())
    return sorted(files)


def test_requires_python_allows_310() -> None:
    tomllib = pytest.importorskip("tomllib")
    specifiers = pytest.importorskip("packaging.specifiers")
    meta = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    spec = specifiers.SpecifierSet(meta["project"]["requires-python"])
    assert "3.10.12" in spec, f"requires-python {spec} excludes JetPack 6's Python 3.10.12"
    assert meta["tool"]["ruff"]["target-version"] == "py310"


def test_the_edge_agent_cli_loads_the_top_floor_files_checked_here(
        edge_files: list[Path]) -> None:
    names = {f.relative_to(REPO_ROOT).as_posix() for f in edge_files}
    assert "smartedge/cli.py" in names and "edge_agent/service.py" in names
    assert "protocol/codec.py" in names


def test_edge_code_parses_with_the_310_grammar(edge_files: list[Path]) -> None:
    bad = []
    for path in edge_files:
        try:
            ast.parse(path.read_text(encoding="utf-8"), str(path), feature_version=(3, 10))
        except SyntaxError as exc:
            bad.append(f"{path.relative_to(REPO_ROOT)}:{exc.lineno}: {exc.msg}")
    assert not bad, "not Python 3.10 syntax:\n" + "\n".join(bad)


class _RunTimeOnly(ast.NodeTransformer):
    """Drops the bodies of ``if TYPE_CHECKING:`` (never run), keeping their ``else``."""

    def visit_If(self, node: ast.If) -> ast.AST | list[ast.stmt]:
        test = node.test
        if (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
                isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"):
            return [self.visit(n) for n in node.orelse]
        self.generic_visit(node)
        return node


def _is_generic_namedtuple(node: ast.ClassDef) -> bool:
    names = {b.id if isinstance(b, ast.Name) else b.attr if isinstance(b, ast.Attribute) else
             "" for b in node.bases}
    generic = any(isinstance(b, ast.Subscript) for b in node.bases)
    return "NamedTuple" in names and (generic or "Generic" in names)


def newer_than_310(source: str) -> list[tuple[int, str]]:
    """(line, what) for each use of a standard-library name Python 3.10 lacks, and each
    generic ``NamedTuple`` (``class X(NamedTuple, Generic[T])``: a ``TypeError`` on 3.10),
    outside ``if TYPE_CHECKING:``."""
    tree = _RunTimeOnly().visit(ast.parse(source))
    aliases: dict[str, str] = {}  # local name → module, for `import datetime as dt`
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if "" in NEWER_THAN_310.get(a.name, frozenset()):
                    found.append((node.lineno, f"import {a.name}"))
                aliases[a.asname or a.name] = a.name
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            new = NEWER_THAN_310.get(node.module, frozenset())
            if "" in new:
                found.append((node.lineno, f"from {node.module} import ..."))
            found += [(node.lineno, f"from {node.module} import {a.name}")
                      for a in node.names if a.name in new]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            module = aliases.get(node.value.id)
            if module and node.attr in NEWER_THAN_310.get(module, frozenset()):
                found.append((node.lineno, f"{module}.{node.attr}"))
        if isinstance(node, ast.Name) and node.id in NEWER_BUILTINS:
            found.append((node.lineno, node.id))
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in NEWER_METHODS):
            found.append((node.lineno, f".{node.func.attr}()"))
        if isinstance(node, ast.ClassDef) and _is_generic_namedtuple(node):
            found.append((node.lineno, f"generic NamedTuple {node.name}"))
    return sorted(found)


def test_the_scan_finds_what_310_lacks() -> None:
    """The scanner itself, on code that uses 3.11+ names in each way it looks for."""
    source = textwrap.dedent("""
        import tomllib
        import datetime as dt
        from typing import Self, Any
        from enum import StrEnum
        stamp = dt.datetime.now(dt.UTC)
        try:
            pass
        except ExceptionGroup:
            pass
        err = ValueError()
        err.add_note("why")
        class Pair(NamedTuple, Generic[T]):
            a: T
    """)
    found = [what for _, what in newer_than_310(source)]
    assert found == ["import tomllib", "from typing import Self", "from enum import StrEnum",
                     "datetime.UTC", "ExceptionGroup", ".add_note()", "generic NamedTuple Pair"]
    ok = textwrap.dedent("""
        import datetime
        from typing import TYPE_CHECKING, Any, NamedTuple
        x = datetime.timezone.utc
        if TYPE_CHECKING:
            from typing import Self
            class Pair(NamedTuple, Generic[T]):
                a: T
        else:
            class Pair(NamedTuple):
                a: Any
    """)
    assert newer_than_310(ok) == []


def test_edge_code_uses_no_standard_library_newer_than_310(edge_files: list[Path]) -> None:
    bad = [f"{path.relative_to(REPO_ROOT)}:{line}: {what}"
           for path in edge_files
           for line, what in newer_than_310(path.read_text(encoding="utf-8"))]
    assert not bad, "Python 3.11+ only (JetPack 6 has 3.10):\n" + "\n".join(bad)


def _python310() -> str | None:
    exe = shutil.which("python3.10")
    if exe is None:
        return None
    probe = subprocess.run([exe, "-c", "import sys; print(sys.version_info[:2])"],
                           capture_output=True, text=True, timeout=30, check=False)
    return exe if probe.returncode == 0 and probe.stdout.strip() == "(3, 10)" else None


def test_a_real_python310_compiles_the_edge_code(edge_files: list[Path],
                                                 tmp_path: Path) -> None:
    exe = _python310()
    if exe is None:
        pytest.skip("no runnable python3.10 on the PATH (the grammar check above still ran)")
    listing = tmp_path / "files.txt"
    listing.write_text("\n".join(str(f) for f in edge_files) + "\n", encoding="utf-8")
    code = ("import py_compile, sys\n"
            "bad = []\n"
            "for f in open(sys.argv[1]).read().split():\n"
            "    try:\n"
            "        py_compile.compile(f, cfile=sys.argv[2] + '/x.pyc', doraise=True)\n"
            "    except py_compile.PyCompileError as e:\n"
            "        bad.append(str(e))\n"
            "print('\\n'.join(bad)); sys.exit(1 if bad else 0)\n")
    done = subprocess.run([exe, "-c", code, str(listing), str(tmp_path)], capture_output=True,
                          text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
