"""Every message type survives encode → decode unchanged, including empty and large arrays."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

import protocol
from protocol import DecodeError, decode, encode
from protocol.messages import MESSAGE_TYPES, Detection, RobotDetections, SemanticCloud
from tests.protocol import strategies as S

_SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.parametrize(
    "strategy",
    [
        S.robot_detections(),
        S.camera_images(),
        S.semantic_clouds(),
        S.odometries(),
        S.pose_estimates(),
        S.pose_corrections(),
        S.service_statuses(),
    ],
    ids=[cls.SCHEMA for cls in MESSAGE_TYPES],
)
def test_roundtrip_every_message_type(strategy) -> None:
    @_SETTINGS
    @given(strategy)
    def check(msg) -> None:
        payload = encode(msg)
        back = decode(payload)
        assert type(back) is type(msg)
        assert back == msg
        assert decode(payload, expected=type(msg)) == msg

    check()


def test_empty_detections_and_empty_cloud_roundtrip() -> None:
    empty = RobotDetections("cam0", 1, 0, 848, 480, "m", ())
    assert decode(encode(empty)) == empty
    det = Detection(np.zeros(4), 0.5, np.zeros((0, 2)), np.zeros(0))
    msg = RobotDetections("cam0", 1, 0, 848, 480, "m", (det,))
    back = decode(encode(msg))
    assert back.detections[0].keypoints_px.shape == (0, 2)
    cloud = SemanticCloud(
        "cam0",
        1,
        0,
        "map",
        np.zeros((0, 3), np.float32),
        np.zeros(0, np.uint8),
        np.zeros(0, np.float32),
    )
    assert decode(encode(cloud)) == cloud


def test_large_cloud_roundtrip_is_exact() -> None:
    rng = np.random.default_rng(0)
    n = 300_000
    cloud = SemanticCloud(
        "robot_1",
        123,
        7,
        "map",
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.integers(0, 65535, size=n).astype(np.uint16),
        rng.random(n).astype(np.float32),
        T_frame_sensor=np.eye(4),
    )
    back = decode(encode(cloud))
    assert back == cloud
    assert back.points_xyz.dtype == np.float32 and back.class_ids.dtype == np.uint16


def test_arrays_travel_as_little_endian_bytes_with_schema() -> None:
    det = Detection(
        np.array([1.0, 2, 3, 4]),
        0.9,
        np.array([[1.5, 2.5]], np.float32),
        np.array([0.25], np.float32),
    )
    wire = msgpack.unpackb(encode(RobotDetections("c", 5, 1, 10, 10, "m", (det,))), raw=False)
    assert wire["schema"] == "RobotDetections" and wire["schema_version"] == 1
    kp = wire["detections"][0]["keypoints_px"]
    assert kp["dtype"] == "<f4" and kp["shape"] == [1, 2]
    assert kp["data"] == np.array([1.5, 2.5], "<f4").tobytes()


def test_big_endian_input_array_is_encoded_little_endian() -> None:
    pts = np.arange(6, dtype=">f4").reshape(2, 3)
    cloud = SemanticCloud(
        "s", 0, 0, "map", pts.astype(np.float32), np.zeros(2, np.uint8), np.zeros(2, np.float32)
    )
    assert np.array_equal(decode(encode(cloud)).points_xyz, pts)


def test_unknown_version_and_schema_are_clear_errors() -> None:
    wire = msgpack.unpackb(encode(S.sample_odometry()), raw=False)
    wire["schema_version"] = 99
    with pytest.raises(DecodeError, match="unsupported schema_version 99"):
        decode(msgpack.packb(wire))
    wire["schema"] = "Teleport"
    with pytest.raises(DecodeError, match="unknown schema 'Teleport'"):
        decode(msgpack.packb(wire))


def test_expected_type_mismatch_is_rejected() -> None:
    payload = encode(S.sample_odometry())
    with pytest.raises(DecodeError, match="expected PoseEstimate, got Odometry"):
        decode(payload, expected=protocol.PoseEstimate)


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("x", math.nan, "NaN"),
        ("theta", math.inf, "infinity"),
        ("robot_id", "a/b", "invalid id"),
        ("stamp_ns", -1, "outside"),
        ("covariance", np.ones((2, 2)), "shape"),
    ],
)
def test_invalid_field_values_are_rejected_with_field_name(field, value, reason) -> None:
    odo = S.sample_odometry()
    wire = msgpack.unpackb(encode(odo), raw=False)
    wire[field] = (
        {"dtype": "<f8", "shape": list(value.shape), "data": value.astype("<f8").tobytes()}
        if isinstance(value, np.ndarray)
        else value
    )
    with pytest.raises(DecodeError, match=field) as info:
        decode(msgpack.packb(wire))
    assert reason in str(info.value)


def test_nested_error_names_the_path() -> None:
    det = Detection(np.zeros(4), 0.5, np.zeros((3, 2)), np.zeros(3))
    wire = msgpack.unpackb(encode(RobotDetections("c", 1, 0, 8, 8, "m", (det,))), raw=False)
    wire["detections"][0]["keypoint_scores"]["data"] = np.full(3, 7.0).tobytes()
    with pytest.raises(DecodeError, match=r"detections\[0\]\.keypoint_scores"):
        decode(msgpack.packb(wire))


def test_construction_validates_like_decode() -> None:
    with pytest.raises(protocol.ValidationError, match="keypoint_scores"):
        Detection(np.zeros(4), 0.5, np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(protocol.ValidationError, match="points_xyz"):
        SemanticCloud(
            "s", 0, 0, "map", np.zeros((2, 3)), np.zeros(2, np.uint8), np.zeros(2, np.float32)
        )
