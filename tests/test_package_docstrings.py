"""Every package's docstring names what the package holds.

Each package of the project (a directory with an ``__init__.py`` under one of the top-level
packages below, subpackages included) has a module docstring in its ``__init__.py`` that names
every module of the package (each ``*.py`` but ``__init__.py`` and ``__main__.py``) and every
direct subpackage, as ``name`` (double backquotes, optionally dotted: ``pkg.name``) or with a
``:mod:`` role (``:mod:`pkg.name```, ``:mod:`.name```). A module added without a word in its
package's docstring fails here.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

TOP_LEVEL = (
    "protocol",
    "core",
    "edge_agent",
    "backend_service",
    "mapper",
    "robot_bridge",
    "simulation",
    "calibration",
    "training",
    "smartedge",
    "lab",
)
NOT_MODULES = frozenset({"__init__.py", "__main__.py"})


def packages(root: Path, tops: tuple[str, ...] = TOP_LEVEL) -> list[Path]:
    """Every package directory under ``root``'s top-level packages ``tops`` (themselves
    included), sorted."""
    found: set[Path] = set()
    for top in tops:
        for init in (root / top).rglob("__init__.py"):
            if "__pycache__" not in init.parts:
                found.add(init.parent)
    return sorted(found)


def members(package: Path) -> list[str]:
    """The names a package's docstring must mention: its modules and its direct subpackages."""
    modules = [p.stem for p in package.glob("*.py") if p.name not in NOT_MODULES]
    subpackages = [p.name for p in package.iterdir() if (p / "__init__.py").is_file()]
    return sorted(modules + subpackages)


def mentions(doc: str, name: str) -> bool:
    """Whether ``doc`` names ``name`` as ``name``/``pkg.name`` or :mod:`[pkg].name`."""
    escaped = re.escape(name)
    literal = rf"``(?:[\w.]+\.)?{escaped}``"
    role = rf":mod:`~?(?:[\w.]*\.)?{escaped}`"
    return re.search(f"{literal}|{role}", doc) is not None


def problems(package: Path, root: Path) -> list[str]:
    """What is wrong with ``package``'s docstring (empty when nothing)."""
    rel = package.relative_to(root).as_posix()
    init = package / "__init__.py"
    doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"), filename=str(init)))
    if not doc:
        return [f"{rel}/__init__.py: no docstring"]
    missing = [name for name in members(package) if not mentions(doc, name)]
    if missing:
        return [f"{rel}/__init__.py: docstring does not name {', '.join(missing)}"]
    return []


def test_every_package_docstring_names_its_modules_and_subpackages() -> None:
    found = packages(REPO_ROOT)
    for top in TOP_LEVEL:  # a top-level package that lost its __init__.py has no docstring
        assert (REPO_ROOT / top) in found, f"{top}/__init__.py is missing"
    bad = [line for package in found for line in problems(package, REPO_ROOT)]
    assert not bad, "package docstrings to complete:\n" + "\n".join(bad)


def test_the_checker_catches_a_missing_name(tmp_path: Path) -> None:
    package = tmp_path / "fake"
    (package / "sub").mkdir(parents=True)
    (package / "sub" / "__init__.py").write_text('"""Sub: ``leaf``."""\n', encoding="utf-8")
    (package / "sub" / "leaf.py").write_text('"""Leaf."""\n', encoding="utf-8")
    (package / "__main__.py").write_text("", encoding="utf-8")
    (package / "named.py").write_text('"""Named."""\n', encoding="utf-8")
    (package / "by_role.py").write_text('"""By role."""\n', encoding="utf-8")
    (package / "forgotten.py").write_text('"""Forgotten."""\n', encoding="utf-8")
    (package / "__init__.py").write_text(
        '"""Fake: ``named``, :mod:`fake.by_role`, ``sub``; codec, not in backquotes: '
        'forgotten."""\n',
        encoding="utf-8",
    )
    assert packages(tmp_path, ("fake",)) == [package, package / "sub"]
    assert members(package) == ["by_role", "forgotten", "named", "sub"]
    assert problems(package / "sub", tmp_path) == []
    assert problems(package, tmp_path) == ["fake/__init__.py: docstring does not name forgotten"]

    (package / "__init__.py").write_text("x = 1\n", encoding="utf-8")
    assert problems(package, tmp_path) == ["fake/__init__.py: no docstring"]


@pytest.mark.parametrize(
    ("doc", "name", "expected"),
    [
        ("``codec``", "codec", True),
        ("``protocol.codec``", "codec", True),
        (":mod:`protocol.codec`", "codec", True),
        (":mod:`.harness`", "harness", True),
        (":mod:`~lab.bench.faults`", "faults", True),
        ("codec", "codec", False),
        ("``codec_v2``", "codec", False),
        ("``mycodec``", "codec", False),
        (":mod:`protocol.codec.x`", "codec", False),
    ],
)
def test_mentions(doc: str, name: str, expected: bool) -> None:
    assert mentions(doc, name) is expected
