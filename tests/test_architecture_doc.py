"""docs/architecture.md's package table equals the tree: one row per package (subpackages
included), and each row names every module of its package and no module it does not hold."""

from __future__ import annotations

import re
from pathlib import Path

from tests.conftest import REPO_ROOT

DOC = REPO_ROOT / "docs" / "architecture.md"
TOP_PACKAGES = ("protocol", "core", "edge_agent", "backend_service", "mapper", "robot_bridge",
                "simulation", "calibration", "training", "smartedge", "lab")


def table_rows(text: str) -> dict[str, set[str]]:
    """``{package path: modules named in its row}`` of the floors table."""
    rows: dict[str, set[str]] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) != 4:
            continue
        package = re.fullmatch(r"`([a-z_/]+)/`", cells[1])
        if package is None:
            continue
        rows[package.group(1)] = set(re.findall(r"`([a-z_0-9]+\.py)`", cells[2]))
    return rows


def tree(root: Path) -> dict[str, set[str]]:
    """``{package path: its modules}`` for every package under the top-level packages."""
    out: dict[str, set[str]] = {}
    for top in TOP_PACKAGES:
        for init in sorted((root / top).rglob("__init__.py")):
            pkg = init.parent
            out[pkg.relative_to(root).as_posix()] = {
                p.name for p in pkg.glob("*.py") if not p.name.startswith("__")}
    return out


def differences(rows: dict[str, set[str]], packages: dict[str, set[str]]) -> list[str]:
    problems = [f"package {p}/ has no row" for p in sorted(packages.keys() - rows.keys())]
    problems += [f"row {p}/ names no package" for p in sorted(rows.keys() - packages.keys())]
    for p in sorted(rows.keys() & packages.keys()):
        for m in sorted(packages[p] - rows[p]):
            problems.append(f"{p}/{m} is not named in its row")
        for m in sorted(rows[p] - packages[p]):
            problems.append(f"row {p}/ names {m}, which is not there")
    return problems


def test_the_package_table_equals_the_tree() -> None:
    problems = differences(table_rows(DOC.read_text()), tree(REPO_ROOT))
    assert not problems, "docs/architecture.md's table is out of date:\n" + "\n".join(problems)


def test_the_check_sees_a_missing_row_and_a_stale_module(tmp_path: Path) -> None:
    for rel in ("protocol/__init__.py", "protocol/codec.py", "protocol/new.py",
                "mapper/__init__.py", "mapper/map_io.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    doc = ("| floor | package | holds | may import |\n|---|---|---|---|\n"
           "| ground | `protocol/` | `codec.py`, `gone.py` | numpy |\n")
    problems = differences(table_rows(doc), tree(tmp_path))
    assert problems == ["package mapper/ has no row", "protocol/new.py is not named in its row",
                        "row protocol/ names gone.py, which is not there"]
