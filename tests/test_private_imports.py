"""No private names across modules.

A name with a leading underscore (not a dunder) is its module's own: no other module of the
repository imports it (``from x import _name``) or reaches it through an imported module
(``x._name``). A helper two modules need is public, in a module made for it. Every non-test
``.py`` file of the repository's packages, ``scripts/`` and ``examples/`` is parsed (imports
inside functions included); the test fails with ``file:line`` and the name of each violation.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from tests.conftest import REPO_ROOT

#: folders holding scripts rather than packages, checked as well
SCRIPT_DIRS = ("scripts", "examples")
#: never scanned (tests may reach into the module they test; build output; environments)
SKIPPED_DIRS = {"tests", ".venv", "build", "dist", ".git"}


@dataclass(frozen=True)
class Violation:
    """One private name reached from another module."""

    path: Path
    line: int
    name: str
    module: str

    def text(self, root: Path) -> str:
        return f"{self.path.relative_to(root)}:{self.line}: {self.module}.{self.name}"


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def package_roots(root: Path) -> list[Path]:
    """The repository's top-level packages (folders with an ``__init__.py``)."""
    return sorted(p.parent for p in root.glob("*/__init__.py") if p.parent.name not in SKIPPED_DIRS)


def python_files(root: Path) -> Iterator[Path]:
    """Every ``.py`` file of the packages and script folders under ``root``."""
    folders = package_roots(root) + [root / d for d in SCRIPT_DIRS if (root / d).is_dir()]
    for folder in folders:
        for path in sorted(folder.rglob("*.py")):
            if not SKIPPED_DIRS.intersection(path.relative_to(root).parts):
                yield path


def source_files(root: Path) -> Iterator[Path]:
    """The non-test ``.py`` files of the packages and script folders under ``root``."""
    return (p for p in python_files(root) if not p.name.startswith("test_"))


def module_name(root: Path, path: Path) -> str:
    """``a/b/c.py`` → ``a.b.c``; ``a/b/__init__.py`` → ``a.b``."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _resolve(current: str, is_package: bool, level: int, module: str | None) -> str:
    """The absolute module a (possibly relative) ``from`` import names."""
    if level == 0:
        return module or ""
    base = current.split(".")
    if not is_package:
        base = base[:-1]
    base = base[: len(base) - (level - 1)]
    return ".".join(base + ([module] if module else []))


def _module_of(expr: ast.expr, modules: dict[str, str], all_modules: set[str]) -> str | None:
    """The repository module ``expr`` (a name or a dotted attribute chain) stands for, if any;
    ``modules``: local names bound to modules by the file's imports."""
    if isinstance(expr, ast.Name):
        return modules.get(expr.id)
    if isinstance(expr, ast.Attribute):
        parent = _module_of(expr.value, modules, all_modules)
        if parent is not None and f"{parent}.{expr.attr}" in all_modules:
            return f"{parent}.{expr.attr}"
    return None


def violations(root: Path) -> list[Violation]:
    """The private cross-module names used by the source files under ``root``."""
    all_modules = {module_name(root, p) for p in python_files(root)}
    tops = {m.split(".")[0] for m in all_modules}
    found: list[Violation] = []
    for path in source_files(root):
        current = module_name(root, path)
        is_package = path.name == "__init__.py"
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        #: local name → the repository module it is bound to
        modules: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] not in tops:
                        continue
                    if alias.asname:
                        modules[alias.asname] = alias.name
                    else:
                        modules[alias.name.split(".")[0]] = alias.name.split(".")[0]
            elif isinstance(node, ast.ImportFrom):
                source = _resolve(current, is_package, node.level, node.module)
                if source.split(".")[0] not in tops or source == current:
                    continue
                for alias in node.names:
                    if _is_private(alias.name):
                        found.append(Violation(path, node.lineno, alias.name, source))
                    elif f"{source}.{alias.name}" in all_modules:
                        modules[alias.asname or alias.name] = f"{source}.{alias.name}"

        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and _is_private(node.attr):
                owner = _module_of(node.value, modules, all_modules)
                if owner is not None and owner != current:
                    found.append(Violation(path, node.lineno, node.attr, owner))
    return found


def test_no_private_name_crosses_a_module() -> None:
    found = violations(REPO_ROOT)
    assert not found, "private names used outside their module:\n" + "\n".join(
        v.text(REPO_ROOT) for v in found)


def test_the_check_finds_a_violation(tmp_path: Path) -> None:
    """A synthetic package with each kind of violation (and the allowed forms) is reported."""
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "helpers.py").write_text("def _hidden() -> int:\n    return 1\n\n"
                                    "def shown() -> int:\n    return _hidden()\n")
    (pkg / "sub" / "user.py").write_text(
        "from __future__ import annotations\n"
        "from pkg.helpers import _hidden, shown\n"
        "from .. import helpers\n"
        "import pkg.helpers as h\n"
        "def f() -> int:\n"
        "    from ..helpers import _hidden as again\n"
        "    return helpers._hidden() + h._hidden() + again() + shown() + h.__name__.count('')\n")
    (pkg / "tests").mkdir()
    (pkg / "tests" / "test_user.py").write_text("from pkg.helpers import _hidden\n")
    got = sorted((v.path.name, v.line, v.name, v.module) for v in violations(tmp_path))
    assert got == [("user.py", 2, "_hidden", "pkg.helpers"),
                   ("user.py", 6, "_hidden", "pkg.helpers"),
                   ("user.py", 7, "_hidden", "pkg.helpers"),
                   ("user.py", 7, "_hidden", "pkg.helpers")]
    assert violations(tmp_path)[0].text(tmp_path).startswith("pkg/sub/user.py:")
