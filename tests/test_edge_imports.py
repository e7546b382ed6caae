"""An edge board installs only ``smartedge[edge]``: protocol and edge_agent must import without
casadi, gtsam, open3d, rerun or torch. A fresh interpreter blocks those imports to prove it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from tests.conftest import REPO_ROOT

BLOCKED = ("casadi", "gtsam", "open3d", "rerun", "torch", "scipy", "matplotlib", "rosbags")

SCRIPT = textwrap.dedent(
    """
    import importlib, pkgutil, sys
    BLOCKED = {blocked!r}

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ImportError(f"blocked on an edge board: {{name}}")
            return None

    sys.meta_path.insert(0, Block())
    import protocol, edge_agent
    for pkg in (protocol, edge_agent):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            if info.name.split(".")[-1].startswith(("bench", "training")):
                continue  # benchmarks and the optional training pipeline may use more
            importlib.import_module(info.name)
    import smartedge.cli
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    assert not leaked, leaked
    print("ok")
    """
)


def test_protocol_and_edge_agent_import_with_edge_extra_only() -> None:
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(blocked=BLOCKED)],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().endswith("ok")
