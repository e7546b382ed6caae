"""The Rerun view: target parsing and a recording that rerun's own tooling reads."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from protocol.messages import Detection, PoseEstimate, RobotDetections, ServiceStatus

rr_view = pytest.importorskip("smartedge.viewer.rerun_view")


@pytest.mark.parametrize(
    ("spec", "kind", "arg"),
    [
        ("save:out/x.rrd", "save", "out/x.rrd"),
        ("spawn", "spawn", ""),
        ("connect", "connect", ""),
        ("connect:rerun+http://10.0.0.2:9876/proxy", "connect", "rerun+http://10.0.0.2:9876/proxy"),
        ("serve", "serve", ""),
        ("none", "none", ""),
    ],
)
def test_targets_parse(spec: str, kind: str, arg: str) -> None:
    target = rr_view.RerunTarget.parse(spec)
    assert (target.kind, target.arg) == (kind, arg)


@pytest.mark.parametrize("spec", ["save:", "file:x.rrd", "spawn:now", ""])
def test_bad_targets_are_clear_errors(spec: str) -> None:
    with pytest.raises(ValueError, match="--rerun"):
        rr_view.RerunTarget.parse(spec)


def test_saved_recording_verifies_and_holds_the_entities(tmp_path: Path, example_site) -> None:
    path = tmp_path / "view.rrd"
    view = rr_view.RerunView(example_site, rr_view.RerunTarget.parse(f"save:{path}"))
    det = Detection(
        np.array([1.0, 2, 30, 40]), 0.9, np.random.rand(12, 2) * 100, np.random.rand(12)
    )
    t = 1_700_000_000_000_000_000
    view.detections(RobotDetections("cam_sw", t, 0, 848, 480, "m", (det,)))
    cov = np.eye(3) * 1e-4
    view.pose(PoseEstimate("hsr", t, 0, 10.0, 6.0, 0.3, cov, "cameras", ("cam_sw",), 1.2))
    view.pose(PoseEstimate("hsr", t + 5, 0, 10.1, 6.0, 0.3, cov, "fused"))
    view.error("hsr", t, "camera", 0.02)
    view.status(ServiceStatus("backend", "main", t, 0, counters={"invalid": 1}))
    view.close()
    assert not view._failed
    rerun = shutil.which("rerun") or str(Path(sys.executable).with_name("rerun"))
    verify = subprocess.run(
        [rerun, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120
    )
    assert verify.returncode == 0, verify.stderr[-1000:]
    stats = subprocess.run(
        [rerun, "rrd", "stats", str(path)], capture_output=True, text=True, timeout=120
    ).stdout
    for entity in (
        "/world/cameras/cam_sw/image",
        "/world/cameras/cam_sw/image/keypoints",
        "/world/robots/hsr/camera_keypoints",
        "/world/robots/hsr/fused/body",
        "/metrics/hsr/error_cm/camera",
        "/status/backend/main",
    ):
        assert f"{entity}:" in stats, entity
