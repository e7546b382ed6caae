"""The viewer node: a sink that draws what the services publish (real Rerun recording)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rerun")

from core.runtime import ScriptedRunner
from protocol import encode, keys
from protocol.messages import Odometry, PoseCorrection, PoseEstimate
from smartedge.viewer.node import ViewerNode
from smartedge.viewer.rerun_view import RerunTarget, RerunView

T0 = 1_700_000_000_000_000_000


def _entities(path: Path) -> set[str]:
    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    out = subprocess.run([rerun, "rrd", "stats", str(path)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-1000:]
    return set(re.findall(r"^(/\S+): \d+$", out.stdout, flags=re.MULTILINE))


def test_viewer_draws_poses_odometry_truth_and_errors(tmp_path: Path, example_site) -> None:
    truth_calls: list[int] = []

    def truth(robot_id: str, stamp_ns: int) -> np.ndarray | None:
        truth_calls.append(stamp_ns)
        return np.array([10.0, 6.0, 0.3]) if robot_id == "hsr" else None

    path = tmp_path / "view.rrd"
    view = RerunView(example_site, RerunTarget.parse(f"save:{path}"))
    node = ViewerNode(example_site, view, truth=truth)
    runner = ScriptedRunner(node)
    site = example_site.name
    cov = np.eye(3) * 1e-4
    for k in range(5):
        t = T0 + k * 100_000_000
        odom = Odometry("hsr", t, k, 0.1 * k, 0.0, 0.0, 0.1, 0.0, 0.0)
        runner.feed(keys.odom_key(site, "hsr"), encode(odom), t)
        fused = PoseEstimate("hsr", t, k, 10.0 + 0.01 * k, 6.0, 0.3, cov, "fused")
        runner.feed(keys.pose_key(site, "hsr"), encode(fused), t + 1000)
    cam = PoseEstimate("hsr", T0, 0, 10.02, 6.0, 0.3, cov, "cameras", ("cam_sw",), 1.0)
    runner.feed(keys.camera_pose_key(site, "hsr"), encode(cam), T0 + 5_000_000)
    corr = PoseCorrection("hsr", T0, 0, 10.0, 6.0, 0.3, cov, "correction", 0.1, 0.01)
    runner.feed(keys.correction_key(site, "hsr"), encode(corr), T0)
    node.close()
    assert runner.published == [] and node.stats.snapshot_counters().get("invalid", 0) == 0
    assert truth_calls  # errors are computed against the truth at each estimate's stamp
    entities = _entities(path)
    for entity in ("/world/robots/hsr/fused", "/world/robots/hsr/odometry",
                   "/world/robots/hsr/ground_truth", "/world/robots/hsr/camera",
                   "/world/robots/hsr/corrections", "/metrics/hsr/error_cm/fused",
                   "/metrics/hsr/error_cm/camera", "/metrics/latency_ms/stamp_to_view"):
        assert entity in entities, entity


def test_viewer_without_truth_draws_no_errors(tmp_path: Path, example_site) -> None:
    path = tmp_path / "view.rrd"
    node = ViewerNode(example_site, RerunView(example_site, RerunTarget.parse(f"save:{path}")))
    runner = ScriptedRunner(node)
    est = PoseEstimate("hsr", T0, 0, 10.0, 6.0, 0.3, np.eye(3) * 1e-4, "fused")
    runner.feed(keys.pose_key(example_site.name, "hsr"), encode(est), T0)
    runner.feed(keys.pose_key(example_site.name, "hsr"), b"\x00garbage", T0)
    node.close()
    assert node.stats.snapshot_counters()["invalid"] == 1
    assert not any(e.startswith("/metrics/hsr/error_cm") for e in _entities(path))
