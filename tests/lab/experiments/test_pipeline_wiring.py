"""The experiments' wiring of the one backend pipeline: stepped message by message as
``smartedge evaluate paper`` does (with the paper's protocol, :func:`paper_pipeline_config`, and
with the service's defaults), it computes the same estimates as the backend service node fed the
same messages over the wire format."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam")

from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig
from backend_service.service import BackendNode
from core.runtime import ScriptedRunner
from lab.experiments import LOCALIZATION_RATE_HZ, paper_pipeline_config
from protocol import encode, keys
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from robot_bridge.service import LOCALIZATION_PERIOD_NS


@pytest.fixture
def stream(traj1_stream):
    # the shared stream carries the bridge's localization rate: the experiments' must be it
    assert LOCALIZATION_RATE_HZ == 1e9 / LOCALIZATION_PERIOD_NS
    return traj1_stream


def _key(site: str, msg: object) -> str:
    if isinstance(msg, RobotDetections):
        return keys.detections_key(site, msg.camera_id)
    if isinstance(msg, Odometry):
        return keys.odom_key(site, msg.robot_id)
    assert isinstance(msg, PoseEstimate)
    return keys.localization_key(site, msg.robot_id)


def _rows(estimates: list[PoseEstimate]) -> np.ndarray:
    return np.array([[e.stamp_ns, e.seq, e.x, e.y, e.theta, *e.covariance.ravel()]
                     for e in estimates])


@pytest.mark.parametrize("paper", [True, False], ids=["paper-protocol", "service-defaults"])
def test_service_node_and_experiment_path_give_identical_estimates(stream, paper: bool) -> None:
    sc, messages = stream
    site = sc.site
    config = paper_pipeline_config(site) if paper else PipelineConfig.from_site(site)

    # the experiment path: the pipeline stepped message by message
    pipeline = BackendPipeline(site, config)
    camera: list[PoseEstimate] = []
    fused: list[PoseEstimate] = []
    for tm in messages:
        out = pipeline.step(tm.message, tm.arrival_ns)
        camera += out.camera
        fused += out.fused

    # the service: the real node, messages encoded and decoded as on the wire
    runner = ScriptedRunner(BackendNode(site, config=config))
    for tm in messages:
        runner.tick(tm.arrival_ns)
        runner.feed(_key(site.name, tm.message), encode(tm.message), tm.arrival_ns)
    node_camera = [o.message for o in runner.published if o.key.endswith("/camera_pose")]
    node_fused = [o.message for o in runner.published if o.key.endswith("/pose")]

    assert len(camera) > 50 and len(fused) > 100
    assert any("multi_frame" in e.flags for e in camera)  # the robot stopped and was averaged
    assert len(node_camera) == len(camera) and len(node_fused) == len(fused)
    np.testing.assert_array_equal(_rows(node_camera), _rows(camera))
    np.testing.assert_array_equal(_rows(node_fused), _rows(fused))
    assert [e.flags for e in node_camera] == [e.flags for e in camera]
