from __future__ import annotations

import pytest

from protocol import ValidationError, keys
from protocol.messages import Odometry, PoseEstimate, RobotDetections, ServiceStatus


def test_builders_and_parser_agree() -> None:
    cases = [
        (keys.detections_key("lab", "cam_1"), "edge", "cam_1", "detections", RobotDetections),
        (keys.odom_key("lab", "hsr"), "robot", "hsr", "odom", Odometry),
        (keys.pose_key("lab", "hsr"), "robot", "hsr", "pose", PoseEstimate),
        (keys.status_key("lab", "backend", "host-1"), "status", "host-1", "backend", ServiceStatus),
        (keys.alive_key("lab", "edge-agent", "cam_1"), "alive", "cam_1", "edge-agent", None),
    ]
    for key, scope, source, topic, msg_type in cases:
        parsed = keys.parse_key(key)
        assert (parsed.site, parsed.scope, parsed.source_id, parsed.topic) == (
            "lab",
            scope,
            source,
            topic,
        )
        assert parsed.message_type is msg_type
    assert keys.detections_key("lab", "cam_1") == "smartedge/lab/edge/cam_1/detections"


def test_wildcards_only_where_allowed() -> None:
    assert keys.detections_key("lab", "*") == "smartedge/lab/edge/*/detections"
    with pytest.raises(ValidationError):
        keys.detections_key("*", "cam")
    with pytest.raises(ValidationError):
        keys.odom_key("lab", "a/b")


@pytest.mark.parametrize(
    "bad",
    [
        "",
        "smartedge/lab",
        "other/lab/edge/c/detections",
        "smartedge/lab/edge/c/video",
        "smartedge/lab/space/c/detections",
        "smartedge/l*b/edge/c/detections",
    ],
)
def test_parse_rejects_foreign_keys(bad: str) -> None:
    with pytest.raises(ValidationError):
        keys.parse_key(bad)
