"""Preview images for the viewer: the edge agent sends the frame its detections came from as a
JPEG ``CameraImage`` at ``--preview-rate``, never more often, never twice, never by default;
the viewer node draws it under the detections."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from core.site import load_site
from edge_agent.frames import Frame
from edge_agent.preview import encode_preview
from edge_agent.service import EdgeAgentNode, build_node, build_parser
from protocol import codec, keys
from protocol.errors import UsageError, ValidationError
from protocol.messages import CameraImage, RobotDetections
from tests.conftest import REPO_ROOT

SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
CAMERA = "cam1"


class _Source:
    """A frame source that 'detects' nothing in a synthetic frame per poll (test double for
    the frame input only: the node, encoding and wire are the real ones)."""

    label = "test"

    def __init__(self, width: int = 320, height: int = 240) -> None:
        self.w, self.h = width, height
        self.seq = 0
        self.last_frame: Frame | None = None

    def poll(self, now_ns: int) -> list[RobotDetections]:
        self.seq += 1
        img = np.zeros((self.h, self.w, 3), np.uint8)
        img[:, : self.w // 2] = (200, 30, 30)  # left half red (RGB)
        self.last_frame = Frame(img, now_ns, self.seq)
        return [RobotDetections(CAMERA, now_ns, self.seq, self.w, self.h, "m", ())]


def _node(rate_hz: float) -> EdgeAgentNode:
    return EdgeAgentNode(load_site(SITE), CAMERA, _Source(), preview_rate_hz=rate_hz)


def test_preview_is_a_full_size_jpeg_of_the_frame_with_its_stamp() -> None:
    img = np.zeros((48, 64, 3), np.uint8)
    img[:, :32] = (255, 0, 0)
    msg = encode_preview(Frame(img, 123, 7), CAMERA)
    assert (msg.camera_id, msg.stamp_ns, msg.seq) == (CAMERA, 123, 7)
    assert (msg.image_width, msg.image_height, msg.encoding) == (64, 48, "jpeg")
    back = codec.decode(codec.encode(msg), CameraImage)
    bgr = cv2.imdecode(back.data, cv2.IMREAD_COLOR)
    assert bgr.shape == (48, 64, 3)
    # colours survive the RGB -> BGR -> JPEG round trip (left red, right black)
    assert bgr[24, 10, 2] > 200 and bgr[24, 10, 0] < 40
    assert bgr[24, 50].max() < 40


def test_no_preview_by_default() -> None:
    node = _node(0.0)
    out = list(node.tick(time.time_ns())) + list(node.tick(time.time_ns() + 10**9))
    assert all(o.key == keys.detections_key("paper_lab", CAMERA) for o in out)
    assert "previews" not in node.stats.snapshot_counters()


def test_preview_at_most_at_the_rate_and_with_the_detections_stamp() -> None:
    node = _node(2.0)  # every 0.5 s at most
    t0 = 1_000_000_000_000
    previews = []
    for k in range(30):  # 3 s at 10 Hz
        out = list(node.tick(t0 + k * 100_000_000))
        dets = [o.message for o in out if isinstance(o.message, RobotDetections)]
        imgs = [o for o in out if isinstance(o.message, CameraImage)]
        for o in imgs:
            assert o.key == keys.image_key("paper_lab", CAMERA) and o.reliable is False
            assert o.message.stamp_ns == dets[-1].stamp_ns  # the frame of these detections
            previews.append(o.message.stamp_ns)
    gaps = np.diff(previews)
    assert 5 <= len(previews) <= 7, previews
    assert gaps.min() >= 500_000_000
    assert node.stats.snapshot_counters()["previews"] == len(previews)


def test_same_frame_is_never_sent_twice() -> None:
    node = _node(100.0)
    src = node.source
    t = 2_000_000_000_000
    out = list(node.tick(t))
    assert sum(isinstance(o.message, CameraImage) for o in out) == 1
    # no new frame: the source returns nothing and keeps its last frame
    src.poll = lambda now_ns: []  # type: ignore[method-assign]
    assert list(node.tick(t + 10**9)) == []


def test_preview_rate_option() -> None:
    args = build_parser().parse_args(["--site", str(SITE), "--camera", CAMERA, "--source",
                                      "camera", "--images", "/nonexistent", "--preview-rate",
                                      "-1"])
    with pytest.raises(UsageError):
        build_node(args)


def test_hostile_preview_messages_are_rejected() -> None:
    with pytest.raises(ValidationError):
        CameraImage(CAMERA, 1, 0, 10, 10, "png", np.zeros(4, np.uint8))
    with pytest.raises(ValidationError):
        CameraImage(CAMERA, 1, 0, 10, 10, "jpeg", np.zeros(0, np.uint8))
    with pytest.raises(ValidationError):
        CameraImage(CAMERA, 1, 0, 10, 10, "jpeg", np.zeros(4, np.float32))


def test_viewer_draws_previews_under_the_detections(tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    from smartedge.viewer.node import ViewerNode
    from smartedge.viewer.rerun_view import RerunTarget, RerunView

    site = load_site(SITE)
    rrd = tmp_path / "v.rrd"
    view = RerunView(site, RerunTarget("save", str(rrd)))
    node = ViewerNode(site, view)
    assert keys.image_key("paper_lab", "*") in [s.key_expr for s in node.subscriptions()]
    img = np.full((480, 848, 3), 90, np.uint8)
    msg = encode_preview(Frame(img, 5_000_000_000, 1), CAMERA)
    node.handle(keys.image_key("paper_lab", CAMERA), msg, 0)
    unknown = encode_preview(Frame(img, 5_000_000_000, 1), "cam_unknown")
    node.handle(keys.image_key("paper_lab", "cam_unknown"), unknown, 0)  # ignored, no raise
    view.close()
    assert "image" not in view._failed
    rerun_cli = Path(sys.executable).with_name("rerun")
    if not rerun_cli.exists():
        pytest.skip("the rerun CLI is not installed beside this Python")
    printed = subprocess.run([str(rerun_cli), "rrd", "print", str(rrd)], capture_output=True,
                             text=True, timeout=60, check=True).stdout
    lines = [ln for ln in printed.splitlines() if "EncodedImage" in ln]
    assert len(lines) == 1 and f"/world/cameras/{CAMERA}/image" in lines[0]
