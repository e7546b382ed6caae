"""Semantic clouds of the simulated site end to end: rendered RGB-D frames of a site camera and of
the robot's head camera, the renderer's exact labels as the segmentation, land on the rendered
surfaces (frames and transforms checked); the edge agent publishes a decodable cloud over real
Zenoh on loopback; the robot camera service publishes in base_link; a source without depth or
without a segmentation model runs on without clouds."""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from typing import Any

import numpy as np
import pytest

pytest.importorskip("moderngl")

from core.geometry import se3_from_planar
from edge_agent.networks import Segmentation
from edge_agent.semantic_cloud import (
    ROBOT_BASE_FRAME,
    SemanticCloudConfig,
    SemanticCloudMaker,
    build_semantic_cloud,
)
from protocol import decode, keys
from protocol.messages import RobotDetections, SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_ID
from tests.conftest import free_port, wait_until

with contextlib.suppress(ImportError):  # the tiny trained segmentation model (session-scoped)
    from tests.edge_agent.conftest import tiny_segmentation  # noqa: F401

FLOOR, WALL = SEMANTIC_CLASS_ID["floor"], SEMANTIC_CLASS_ID["wall"]
ROOM_X, ROOM_Y = (0.0, 20.0), (0.0, 12.0)  # the paper lab's walls


def _live(start_in_s: float = 0.0, epoch_ns: int | None = None):
    from simulation.live import LiveSimSpec, LiveSimulation
    from simulation.scenario import PAPER_SCENARIO

    epoch = epoch_ns if epoch_ns is not None else time.time_ns() + int(start_in_s * 1e9)
    return LiveSimulation(LiveSimSpec(str(PAPER_SCENARIO), "traj3", False, 0, epoch))


def _truth(class_id: np.ndarray, scale: int = 2) -> Segmentation:
    """The renderer's labels as a segmentation at 1/scale resolution (the pixel at each output
    pixel's centre), confidence 1."""
    h, w = class_id.shape
    oh, ow = h // scale, w // scale
    v = np.floor((np.arange(oh) + 0.5) * h / oh).astype(int)
    u = np.floor((np.arange(ow) + 0.5) * w / ow).astype(int)
    cls = class_id[np.ix_(v, u)].astype(np.uint8)
    return Segmentation(cls, np.ones(cls.shape, np.float32), w, h, 0.0)


def _wall_distance(p: np.ndarray) -> np.ndarray:
    return np.min(np.abs(np.stack([p[:, 0] - ROOM_X[0], p[:, 0] - ROOM_X[1],
                                   p[:, 1] - ROOM_Y[0], p[:, 1] - ROOM_Y[1]])), axis=0)


class TruthSegmenter:
    """A segmenter that returns the renderer's labels of the frame last rendered by a
    :class:`simulation.site_cameras.SiteCameraRenderer` (stands in for the network)."""

    model_id = "truth"

    def __init__(self, images: Any, camera_id: str) -> None:
        self.images, self.camera_id = images, camera_id

    def __call__(self, image_rgb: np.ndarray) -> Segmentation:
        out = self.images._clean[self.camera_id][1]
        assert out.color_rgb.shape == image_rgb.shape
        return _truth(out.class_id)


def test_site_camera_cloud_lands_on_the_floor_and_the_walls() -> None:
    """cam1 of the paper lab, noise-free depth, the true camera: floor points at world z = 0
    (mm, growing with the range as the renderer's depth sampling does), wall points on the wall
    planes; with the *calibrated* camera and noisy depth (what the edge agent sends) still
    within a few cm."""
    from simulation.site_cameras import DepthNoise, SiteCameraRenderer

    live = _live()
    images = SiteCameraRenderer(live.scenario, depth_noise=DepthNoise(sigma_per_m=0.0))
    try:
        pose = live.ground_truth(live.spec.epoch_ns)
        out = images.render_output("cam1", pose)
        true_cam = images.camera("cam1")
        config = SemanticCloudConfig(max_range_m=20.0, voxel_m=0.05, max_points=200_000)
        depth = images.depth("cam1", pose)
        cloud = build_semantic_cloud(_truth(out.class_id), depth, true_cam, sensor_id="cam1",
                                     stamp_ns=1, seq=0, frame_id="map",
                                     T_frame_sensor=true_cam.T_world_cam, config=config)
        p = cloud.points_xyz.astype(np.float64)
        floor, wall = cloud.class_ids == FLOOR, cloud.class_ids == WALL
        assert floor.sum() > 2000 and wall.sum() > 200, (floor.sum(), wall.sum())
        # the renderer's depth at a pixel is its nearest internal-render pixel's (up to half a
        # pixel, ~1.2 mrad, off this pixel's ray): allow that much times the range
        tol = 0.002 + 1.5e-3 * np.linalg.norm(p - true_cam.position_world, axis=1)
        assert np.percentile(np.abs(p[floor, 2]) / tol[floor], 99.5) < 1.0
        assert np.percentile(np.abs(p[floor, 2]), 50) < 0.004
        assert np.percentile(_wall_distance(p[wall]) / tol[wall], 99) < 1.0
        assert not np.isin(cloud.class_ids, [SEMANTIC_CLASS_ID["robot"], 0]).any()
        # the same frame as the edge agent sends it: calibrated extrinsics, noisy depth
        cal = live.site.camera("cam1")
        noisy = DepthNoise().apply(out.depth_m, np.random.default_rng(1))
        cloud = build_semantic_cloud(_truth(out.class_id), noisy, cal, sensor_id="cam1",
                                     stamp_ns=1, seq=0, frame_id="map",
                                     T_frame_sensor=cal.T_world_cam, config=SemanticCloudConfig())
        p = cloud.points_xyz.astype(np.float64)
        floor = cloud.class_ids == FLOOR
        assert np.median(np.abs(p[floor, 2])) < 0.03
        assert np.all(np.linalg.norm(p - cal.position_world, axis=1) < 6.0 + 0.1)
    finally:
        images.release()


def test_head_camera_cloud_in_base_link_lands_on_the_site_with_the_true_pose() -> None:
    """The head camera rendered from the robot's true pose; the cloud in base_link, moved with
    that pose, has its floor at z = 0 and its walls on the wall planes; in base_link itself the
    floor is at z = 0 too and everything is in front of the robot."""
    from simulation.live import HeadCameraFeed
    from simulation.site_cameras import DepthNoise

    live = _live()
    feed = HeadCameraFeed(live, rate_hz=1.0, depth_noise=DepthNoise(sigma_per_m=0.0))
    try:
        head = feed.head
        maker_config = SemanticCloudConfig(max_range_m=15.0, max_points=200_000)
        for t_s in (5.0, 40.0):
            stamp = live.spec.epoch_ns + int(t_s * 1e9)
            image, depth, class_id = feed.render(stamp)
            assert image.shape == (480, 640, 3) and depth.shape == (480, 640)
            assert not (class_id == SEMANTIC_CLASS_ID["robot"]).any()  # it does not see itself
            cloud = build_semantic_cloud(_truth(class_id), depth, feed.camera, sensor_id="hsr",
                                         stamp_ns=stamp, seq=0, frame_id=ROBOT_BASE_FRAME,
                                         T_frame_sensor=head.T_base_cam, config=maker_config)
            p_base = cloud.points_xyz.astype(np.float64)
            floor, wall = cloud.class_ids == FLOOR, cloud.class_ids == WALL
            assert floor.sum() > 1000
            assert np.percentile(np.abs(p_base[floor, 2]), 99) < 0.005
            assert np.all(p_base[:, 0] > 0.3)  # in front of the robot
            T = se3_from_planar(*live.ground_truth(stamp))
            p_world = p_base @ T[:3, :3].T + T[:3, 3]
            assert np.percentile(np.abs(p_world[floor, 2]), 99) < 0.005
            if wall.sum() > 50:
                assert np.percentile(_wall_distance(p_world[wall]), 99) < 0.03
            # a wrong pose would not fit: 10 cm off puts the walls off their planes
            if wall.sum() > 50:
                off = p_world[wall] + [0.1, 0.1, 0.0]
                assert np.median(_wall_distance(off)) > 0.05
    finally:
        feed.release()


class _StubPipeline:
    """Stands in for the detector + keypoint networks (not what this test is about)."""

    model_id = "stub"

    def process(self, frame: Any) -> tuple[RobotDetections, Any]:
        from edge_agent.pipeline import StageLatency

        h, w = frame.image_rgb.shape[:2]
        return (RobotDetections("cam1", frame.stamp_ns, frame.seq, w, h, "stub", ()),
                StageLatency(0.0, 0.0))


def test_edge_agent_publishes_a_decodable_cloud_over_zenoh_loopback() -> None:
    """The sim-render source's RGB-D frames through the edge agent's cloud path, published by
    the real Zenoh runner and received by another session: a SemanticCloud in the world frame
    with the camera's T_world_cam, on the floor; counters and latencies in the agent's stats."""
    import zenoh

    from core.runtime import ZenohRunner
    from core.session import loopback_config
    from edge_agent.service import EdgeAgentNode
    from simulation.live import RenderedCameraFeed
    from smartedge.simulated_site import RenderedCameraSource

    live = _live(start_in_s=-5.0)
    feed = RenderedCameraFeed(live, "cam1", rate_hz=5.0)
    source = RenderedCameraSource(feed, _StubPipeline(), live.site)
    camera = live.site.camera("cam1")
    maker = SemanticCloudMaker(TruthSegmenter(feed.images, "cam1"), camera, sensor_id="cam1",
                               frame_id=live.site.world_frame,
                               T_frame_sensor=camera.T_world_cam, rate_hz=2.0)
    node = EdgeAgentNode(live.site, "cam1", source, clouds=maker)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    received: list[tuple[str, bytes]] = []
    sub_session = zenoh.open(loopback_config(listen=[endpoint]))
    sub = sub_session.declare_subscriber(
        keys.edge_cloud_key(live.site.name, "cam1"),
        lambda s: received.append((str(s.key_expr), s.payload.to_bytes())))
    runner = ZenohRunner(node, loopback_config(connect=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    try:
        assert wait_until(lambda: len(received) >= 2, timeout_s=20.0), node.stats.counters
    finally:
        runner.stop()
        thread.join(10)
        sub.undeclare()
        sub_session.close()
    key, payload = received[0]
    assert key == keys.edge_cloud_key(live.site.name, "cam1")
    cloud = decode(payload)
    assert isinstance(cloud, SemanticCloud)
    assert cloud.sensor_id == "cam1" and cloud.frame_id == "map"
    assert np.allclose(cloud.T_frame_sensor, camera.T_world_cam)
    floor = cloud.class_ids == FLOOR
    assert floor.sum() > 500 and np.median(np.abs(cloud.points_xyz[floor, 2])) < 0.03
    second = decode(received[1][1])
    assert second.seq == cloud.seq + 1 and second.stamp_ns - cloud.stamp_ns >= 5e8
    assert node.stats.counters["clouds_published"] >= 2
    assert "segmentation" in node.stats.percentiles_ms(0.5)


def test_robot_camera_service_publishes_clouds_in_base_link() -> None:
    from simulation.live import LiveSimSpec
    from smartedge.simulated_head_camera import build_node, build_parser

    epoch = time.time_ns() - 3 * 10**9
    argv = ["--cloud-rate", "2", *LiveSimSpec(epoch_ns=epoch).to_argv()]
    args = build_parser().parse_args(argv)
    holder: dict[str, Any] = {}

    def segmenter(image: np.ndarray) -> Segmentation:
        return _truth(holder["node"].feed.last_class_id)

    node = build_node(args, segmenter=segmenter)
    holder["node"] = node
    feed = node.feed
    render = feed.render

    def render_and_keep(stamp_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        image, depth, class_id = render(stamp_ns)
        feed.last_class_id = class_id
        return image, depth, class_id

    feed.render = render_and_keep
    try:
        now = epoch + 3_010_000_000  # just after the frame at 3.0 s
        out = list(node.tick(now))
        assert len(out) == 1 and out[0].reliable
        assert out[0].key == keys.robot_cloud_key("paper_lab", "hsr")
        cloud = out[0].message
        assert isinstance(cloud, SemanticCloud) and cloud.frame_id == "base_link"
        assert np.allclose(cloud.T_frame_sensor, node.clouds.T_frame_sensor)
        assert len(cloud.points_xyz) > 1000
        assert list(node.tick(now + 400_000_000)) == []  # the next frame is 0.5 s later
        assert len(list(node.tick(now + 500_000_000))) == 1
        assert node.state()[0] == "ok" and "sim-head-camera" in node.state()[1]
        assert node.stats.counters["clouds_published"] == 2
    finally:
        node.close()


def test_robot_camera_without_a_model_or_a_head_camera(tmp_path, caplog) -> None:
    import yaml

    from protocol.errors import UsageError
    from simulation.scenario import PAPER_SCENARIO
    from smartedge.simulated_head_camera import build_node, build_parser

    caplog.set_level(logging.ERROR)
    args = build_parser().parse_args(["--segmentation-model", str(tmp_path / "none.onnx")])
    node = build_node(args)
    try:
        assert node.clouds is None and list(node.tick(time.time_ns() + 10**10)) == []
        state, detail = node.state()
        assert state == "degraded" and "no clouds" in detail
        assert "no robot clouds" in caplog.text
    finally:
        node.close()
    site = yaml.safe_load((PAPER_SCENARIO.parent / "paper_lab.yaml").read_text())
    del site["robot_models"]["hsr"]["head_camera"]
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(site))
    with pytest.raises(UsageError, match="head_camera"):
        build_node(build_parser().parse_args(["--site", str(path)]))


def test_edge_agent_source_without_depth_logs_once_and_runs_without_clouds(caplog) -> None:
    from edge_agent.service import build_node, build_parser
    from smartedge.simulated_site import register_sim_source

    register_sim_source()
    caplog.set_level(logging.INFO)
    args = build_parser().parse_args(["--camera", "cam1", "--source", "sim", "--detections",
                                      "noise", "--cloud-rate", "1"])
    node = build_node(args)
    assert node.clouds is None
    assert sum("gives no depth" in r.getMessage() for r in caplog.records) == 1
    for _ in range(3):
        for item in node.tick(time.time_ns() + 5 * 10**9):
            assert isinstance(item.message, RobotDetections)
    # the default (no --cloud-rate) is off for a source without depth, silently
    caplog.clear()
    node = build_node(build_parser().parse_args(["--camera", "cam1", "--source", "sim"]))
    assert node.clouds is None and "depth" not in caplog.text


def test_edge_agent_without_a_segmentation_model_logs_and_runs_without_clouds(
        tmp_path, caplog) -> None:
    from edge_agent.service import build_cloud_maker, build_parser

    caplog.set_level(logging.ERROR)
    live = _live()
    args = build_parser().parse_args(["--camera", "cam1", "--segmentation-model",
                                      str(tmp_path / "missing.onnx")])

    class DepthSource:
        provides_depth = True
        label = "rgbd"

    assert build_cloud_maker(args, live.site, "cam1", DepthSource()) is None
    assert "no semantic clouds" in caplog.text
    maker = build_cloud_maker(args, live.site, "cam1", DepthSource(), segmenter=lambda im: None)
    assert maker is not None and maker.frame_id == "map" and maker.rate_hz == 1.0
    assert np.allclose(maker.T_frame_sensor, live.site.camera("cam1").T_world_cam)


def test_the_segmentation_network_feeds_the_cloud_builder() -> None:
    """The real :class:`SemanticSegmenter` (onnxruntime, the shipped model) on a rendered RGB-D
    frame: its output, at its own scale, becomes a valid cloud in the world frame within the
    camera's range, of the legend's classes, without dynamic ones."""
    from edge_agent.networks import SemanticSegmenter
    from protocol.semantic_classes import NUM_SEMANTIC_CLASSES
    from simulation.live import RenderedCameraFeed

    segmenter = SemanticSegmenter(threads=1)
    live = _live()
    feed = RenderedCameraFeed(live, "cam1")
    camera = live.site.camera("cam1")
    config = SemanticCloudConfig(min_confidence=0.0)
    maker = SemanticCloudMaker(segmenter, camera, sensor_id="cam1", frame_id="map",
                               T_frame_sensor=camera.T_world_cam, config=config)
    stamp = live.spec.epoch_ns + 5 * 10**9
    image = feed.render(stamp)
    seg = segmenter(image)
    assert (seg.image_width, seg.image_height) == (camera.width, camera.height)
    cloud, timing = maker.make(image, feed.depth(stamp), stamp)
    assert timing.segmentation_ms > 0.0 and cloud.frame_id == "map"
    p = cloud.points_xyz.astype(np.float64)
    if len(p):
        r = np.linalg.norm(p - camera.position_world, axis=1)
        assert np.all((r > 0.25) & (r < 6.0 + 0.3))
        assert int(cloud.class_ids.max()) < NUM_SEMANTIC_CLASSES
        assert not np.isin(cloud.class_ids, config.drop_class_ids).any()
    # every labelled output pixel with depth is accounted for: no points beyond the pixels
    assert len(p) <= seg.class_ids.size
