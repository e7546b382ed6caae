"""The one backend pipeline: the service node and the experiments compute the same estimates."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("gtsam")

from backend_service.pipeline import BackendPipeline, PipelineConfig
from backend_service.service import BackendNode
from protocol import encode, keys
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from protocol.runtime import ScriptedRunner
from simulation.runner import SimulationRun
from simulation.scenario import load_scenario
from smartedge.experiments import LOCALIZATION_RATE_HZ, paper_pipeline_config

SIM_S = 40.0


@pytest.fixture(scope="module")
def stream():
    sc = load_scenario()
    sim = SimulationRun(sc, "traj1", seed=7)
    return sc, list(sim.messages(until_s=SIM_S, localization_rate_hz=LOCALIZATION_RATE_HZ))


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


def test_prior_comes_from_the_configured_source(stream) -> None:
    sc, messages = stream
    site = sc.site
    sources: dict[str, set[str]] = {}
    for prior in ("fused", "localization"):
        pipeline = BackendPipeline(site, PipelineConfig.from_site(site, prior=prior))
        seen: set[str] = set()
        for tm in messages:
            seen.update(r.prior_source for r in pipeline.step(tm.message, tm.arrival_ns).solves)
        sources[prior] = seen
    assert "localization" in sources["localization"] and "fused" not in sources["localization"]
    assert "fused" in sources["fused"]


def test_fuse_while_moving_off_fuses_only_averages(stream) -> None:
    sc, messages = stream
    site = sc.site
    counts = {}
    for moving in (True, False):
        config = dataclasses.replace(PipelineConfig.from_site(site), fuse_while_moving=moving)
        pipeline = BackendPipeline(site, config)
        estimates = averages = 0
        for tm in messages:
            for rec in pipeline.step(tm.message, tm.arrival_ns).solves:
                estimates += rec.result.ok
                averages += rec.averaged is not None
        fusion = pipeline.tracks[sc.robot_id].fusion
        counts[moving] = (fusion.counters["camera_received"], estimates, averages)  # type: ignore[union-attr]
    received, estimates, averages = counts[False]
    assert 0 < averages == received  # only the averages taken while static
    received, estimates, averages = counts[True]
    assert received > averages and received <= estimates


def test_bad_config_is_a_clear_error() -> None:
    with pytest.raises(ValueError, match="prior"):
        PipelineConfig(prior="gps")


def test_prior_covariance_is_passed_only_for_the_robots_localization(stream) -> None:
    sc, messages = stream
    site = sc.site
    for prior in ("fused", "localization"):
        pipeline = BackendPipeline(site, PipelineConfig.from_site(site, prior=prior))
        records = []
        for tm in messages:
            records += pipeline.step(tm.message, tm.arrival_ns).solves
        by_source = {r.prior_source for r in records}
        assert prior in by_source
        for r in records:
            if r.prior_source == "localization":
                # the simulated localization reports its own covariance: it reaches the solve
                assert r.prior_covariance is not None and r.prior_covariance.shape == (3, 3)
                assert np.all(np.linalg.eigvalsh(r.prior_covariance) > 0)
            else:  # the pose graph combines camera estimates itself: no double counting
                assert r.prior_covariance is None
            if r.result.ok and "map_prior" in r.result.estimate.flags:
                assert r.prior_source == "localization"
                assert "single_camera" in r.result.estimate.flags
