"""The closed-loop simulated camera: ``--source sim --detections cnn`` renders the site from the
camera's true pose with the robot at its ground-truth pose and runs the edge's ONNX pipeline on
the image (tiny models here; the shipped ones in the demo)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("moderngl")
pytest.importorskip("onnxruntime")

from protocol.messages import RobotDetections, SemanticCloud


def _live(start_in_s: float = 0.0):
    from simulation.live import LiveSimSpec, LiveSimulation
    from simulation.scenario import PAPER_SCENARIO

    spec = LiveSimSpec(str(PAPER_SCENARIO), "traj3", False, 0,
                       time.time_ns() + int(start_in_s * 1e9))
    return LiveSimulation(spec)


def test_rendered_feed_schedule_takes_the_newest_frame_and_counts_skips() -> None:
    """Frames are due at the scenario's phase and ``rate_hz``; a caller that polls late gets
    the newest due frame once, and the frames in between are counted as skipped."""
    from simulation.live import RenderedCameraFeed

    live = _live()
    feed = RenderedCameraFeed(live, "cam1", rate_hz=10.0)
    t0 = feed._capture_ns(0)
    assert feed.due(t0 - 1) is None
    assert feed.due(t0) == t0
    assert feed.due(t0 + 50_000_000) is None  # the next frame is 100 ms later
    late = t0 + 450_000_000  # frames 1..4 are due; 4 is the newest
    assert feed.due(late) == feed._capture_ns(4)
    assert feed.skipped == 3 and feed.seq == 2
    assert feed.due(late) is None


def test_rendered_feed_renders_the_true_camera_view() -> None:
    """The image has the camera's size, is not blank, and changes when the robot moves."""
    from simulation.live import RenderedCameraFeed

    live = _live()
    feed = RenderedCameraFeed(live, "cam1", rate_hz=10.0)
    a = feed.render(live.spec.epoch_ns)
    b = feed.render(live.spec.epoch_ns + 20 * 10**9)
    cam = live.site.cameras["cam1"]
    assert a.shape == (cam.height, cam.width, 3) and a.dtype == np.uint8
    assert a.std() > 5.0
    assert np.abs(a.astype(int) - b.astype(int)).sum() > 0


def test_edge_agent_sim_cnn_source_publishes_detections(tiny_models: Path) -> None:
    """``--source sim --detections cnn --model DIR`` builds an edge agent whose ticks publish
    RobotDetections of the rendered frames (full image size, the model's id) and whose status
    names the rendered source; render and network latencies are recorded."""
    from edge_agent.service import build_node, build_parser
    from smartedge.simulated_site import register_sim_source

    register_sim_source()
    args = build_parser().parse_args(["--camera", "cam2", "--source", "sim", "--detections",
                                      "cnn", "--model", str(tiny_models), "--render-rate", "20"])
    node = build_node(args)
    try:
        msgs: list[RobotDetections] = []
        others: list[object] = []
        deadline = time.monotonic() + 20.0
        while len(msgs) < 3 and time.monotonic() < deadline:
            for o in node.tick(time.time_ns()):
                (msgs if isinstance(o.message, RobotDetections) else others).append(o.message)
            time.sleep(0.02)
        assert len(msgs) >= 3
        # the rendered source has depth: semantic clouds (1 Hz by default) may come along
        assert all(isinstance(m, SemanticCloud) for m in others), others
        assert msgs[0].camera_id == "cam2" and (msgs[0].image_width, msgs[0].image_height) == (
            848, 480)
        assert msgs[0].model_id.startswith("hsr/")
        assert [m.seq for m in msgs] == sorted(m.seq for m in msgs)
        state, detail = node.state()
        assert state == "ok" and "sim-render" in detail
    finally:
        node.close()
