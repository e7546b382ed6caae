"""Import floors, checked in fresh interpreters.

An edge board installs only ``smartedge[edge]``: protocol and edge_agent must import without
casadi, gtsam, open3d, rerun or torch, and ``smartedge edge-agent`` (the simulated source
registered) must not load them either, nor the other services.

Service packages never import ``simulation``, ``smartedge`` or each other: every module of each
service package is imported in a fresh interpreter and nothing of those may be loaded, and no
import statement in the package (lazy ones inside functions included) may name them. The
simulation (a plug-in wired in from the top floor) names no service and no top floor either.

Each heavy dependency is imported in exactly one package (:data:`HEAVY_OWNERS`: open3d only in
``mapper``, casadi and gtsam only in ``backend_service``, ...); a service package neither names
nor loads another package's.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

BLOCKED = ("casadi", "gtsam", "open3d", "rerun", "torch", "scipy", "matplotlib", "rosbags")
SERVICES = ("edge_agent", "robot_bridge", "backend_service", "mapper")
#: top-level packages no service package may import (besides the other services)
ABOVE_SERVICES = ("simulation", "calibration", "training", "smartedge", "lab")
#: each heavy dependency and the one package of the project that imports it
HEAVY_OWNERS = {
    "casadi": "backend_service",
    "gtsam": "backend_service",
    "open3d": "mapper",
    "torch": "training",  # the train extra
    "moderngl": "simulation",
    "rerun": "smartedge",
}
PACKAGES = ("protocol", "core", *SERVICES, "simulation", "calibration", "training", "smartedge",
            "lab")

EDGE_SCRIPT = textwrap.dedent(
    """
    import importlib, pkgutil, sys
    BLOCKED = {blocked!r}

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"blocked on an edge board: {{name}}")
            return None

    sys.meta_path.insert(0, Block())
    import protocol, core, edge_agent
    for pkg in (protocol, core, edge_agent):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            importlib.import_module(info.name)
    import smartedge.cli
    # what `smartedge edge-agent` loads: the composition root and the simulated source
    import smartedge.services
    from smartedge.simulated_site import register_sim_source
    register_sim_source()
    from edge_agent.service import build_parser
    build_parser().parse_args(["--camera", "cam1", "--source", "sim"])
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    assert not leaked, leaked
    services = ("backend_service", "mapper", "robot_bridge")
    others = sorted(m for m in sys.modules if m.split(".")[0] in services)
    assert not others, others
    print("ok")
    """
)

SERVICE_SCRIPT = textwrap.dedent(
    """
    import importlib, pkgutil, sys
    PACKAGE = {package!r}
    FORBIDDEN = {forbidden!r}
    pkg = importlib.import_module(PACKAGE)
    importlib.import_module(PACKAGE + ".service")
    for info in pkgutil.walk_packages(pkg.__path__, PACKAGE + "."):
        importlib.import_module(info.name)
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in FORBIDDEN)
    assert not leaked, leaked
    print("ok")
    """
)


def _python(script: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", script], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120
    )


def test_protocol_and_edge_agent_import_with_edge_extra_only() -> None:
    proc = _python(EDGE_SCRIPT.format(blocked=BLOCKED))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("ok")


def _forbidden(package: str) -> tuple[str, ...]:
    """What a service package may neither name nor load: the floors above, the other services
    and the other packages' heavy dependencies."""
    return (ABOVE_SERVICES + tuple(s for s in SERVICES if s != package)
            + tuple(dep for dep, owner in HEAVY_OWNERS.items() if owner != package))


@pytest.mark.parametrize("package", SERVICES)
def test_service_package_loads_no_simulation_top_floor_or_other_service(package: str) -> None:
    proc = _python(SERVICE_SCRIPT.format(package=package, forbidden=_forbidden(package)))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("ok")


@functools.cache
def _imported_names(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in ``path`` (parsed once per test process: the
    heavy-dependency checks read every file of the repo once each)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module))
    return out


@pytest.mark.parametrize("package", [*SERVICES, "simulation"])
def test_package_names_no_forbidden_import(package: str) -> None:
    """Also the imports inside functions, which loading the modules does not run. The
    simulation is a plug-in: it imports only ``protocol`` of the project."""
    forbidden = (*ABOVE_SERVICES, *SERVICES) if package == "simulation" else _forbidden(package)
    forbidden = tuple(f for f in forbidden if f != package)
    bad = [
        f"{path.relative_to(REPO_ROOT)}:{line}: {name}"
        for path in sorted((REPO_ROOT / package).rglob("*.py"))
        for line, name in _imported_names(path)
        if name.split(".")[0] in forbidden
    ]
    assert not bad, bad


@pytest.mark.parametrize(("dependency", "owner"), sorted(HEAVY_OWNERS.items()))
def test_each_heavy_dependency_is_imported_in_one_package(dependency: str, owner: str) -> None:
    """Lazy imports inside functions included. A benchmark (``lab/bench/``) may import one as
    the peer it measures the project against (``bench calibration-solver``: GTSAM)."""
    where = sorted({
        package
        for package in PACKAGES
        for path in (REPO_ROOT / package).rglob("*.py")
        if not path.is_relative_to(REPO_ROOT / "lab" / "bench")
        for _, name in _imported_names(path)
        if name.split(".")[0] == dependency
    })
    assert where == [owner], f"{dependency} imported in {where}, expected only in {owner}"
