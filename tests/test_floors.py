"""The floors of the house (docs/architecture.md): which of the project's packages each package
may import. Every import statement counts, lazy ones inside functions included.

- the ground floor: the wire contract (``protocol``) imports none of the project, the shared
  core (``core``) only the contract;
- the services, calibration and the simulation import only the ground floor; training imports
  the ground floor and the edge agent it trains for (its crops and model cards);
- the app (``smartedge``) imports the floors below it and never the lab;
- nothing outside the lab imports it (the lab's commands reach ``smartedge`` through an entry
  point, not an import).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

GROUND = frozenset({"protocol", "core"})
SERVICES = frozenset({"edge_agent", "backend_service", "mapper", "robot_bridge"})
#: package → the project's packages it may import (besides itself)
MAY_IMPORT: dict[str, frozenset[str]] = {
    "protocol": frozenset(),
    "core": frozenset({"protocol"}),
    **{service: GROUND for service in SERVICES},
    "calibration": GROUND,
    "training": GROUND | {"edge_agent"},
    "simulation": GROUND,
    "smartedge": GROUND | SERVICES | {"calibration", "simulation"},
    "lab": GROUND | SERVICES | {"calibration", "training", "simulation", "smartedge"},
}
PROJECT = frozenset(MAY_IMPORT)


def imported_packages(path: Path) -> list[tuple[int, str]]:
    """(line, top-level package) of every absolute import statement in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name.split(".")[0]) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module.split(".")[0]))
    return out


def violations(root: Path, package: str, allowed: frozenset[str]) -> list[str]:
    """``path:line: imports X`` for each import of a project package ``package`` may not use."""
    return [
        f"{path.relative_to(root).as_posix()}:{line}: imports {name}"
        for path in sorted((root / package).rglob("*.py"))
        for line, name in imported_packages(path)
        if name in PROJECT and name != package and name not in allowed
    ]


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_each_package_imports_only_its_floors(package: str) -> None:
    assert (REPO_ROOT / package / "__init__.py").is_file(), f"{package}/ is gone: update the table"
    bad = violations(REPO_ROOT, package, MAY_IMPORT[package])
    assert not bad, f"{package} may import only {sorted(MAY_IMPORT[package])}:\n" + "\n".join(bad)


def test_every_top_level_package_has_a_floor() -> None:
    packages = {p.parent.name for p in REPO_ROOT.glob("*/__init__.py")} - {"tests"}
    assert packages == set(MAY_IMPORT)


def test_nothing_outside_the_lab_and_the_tests_imports_the_lab() -> None:
    bad = [
        f"{path.relative_to(REPO_ROOT).as_posix()}:{line}"
        for top in ("examples", "deploy")
        for path in sorted((REPO_ROOT / top).rglob("*.py"))
        for line, name in imported_packages(path)
        if name == "lab"
    ]
    assert not bad, bad


def test_the_check_finds_a_lazy_import_of_the_lab_in_the_app(tmp_path: Path) -> None:
    (tmp_path / "smartedge").mkdir()
    (tmp_path / "smartedge" / "tool.py").write_text(
        "import protocol\n\ndef run():\n    from lab.demo import main\n    return main\n")
    assert violations(tmp_path, "smartedge", MAY_IMPORT["smartedge"]) == [
        "smartedge/tool.py:4: imports lab"]
