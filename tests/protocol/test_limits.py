"""Bounded cost: every limit is enforced before the part it bounds is built (protocol.limits)."""

from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest

from protocol import DecodeError, decode, encode
from protocol.limits import (
    LIMIT_REASONS,
    MAX_UNKNOWN_KEYS,
    MAX_UNKNOWN_VALUE_BYTES,
    PAYLOAD_CAPS,
    QUEUE_BYTE_BUDGETS,
    LimitError,
    payload_cap,
    queue_byte_budget,
)
from protocol.messages import (
    MAX_DETECTIONS,
    MAX_KEYPOINTS,
    MESSAGE_TYPES,
    Detection,
    Odometry,
    PoseEstimate,
    RobotDetections,
    ServiceStatus,
)
from tests.protocol import strategies as S


def _detection(m: int = 12, sigmas: bool = True) -> Detection:
    return Detection(np.array([0.0, 0.0, 10.0, 10.0]), 0.9, np.zeros((m, 2)), np.full(m, 0.5),
                     "hsr", np.ones(m) if sigmas else None)


def _pose() -> PoseEstimate:
    return PoseEstimate("hsr", 1, 0, 1.0, 2.0, 0.5, np.eye(3) * 0.01, "fused", ("cam1",))


def _wire(msg: object) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)  # type: ignore[arg-type]


def _limit(payload: bytes, expected: type | None = None) -> LimitError:
    with pytest.raises(LimitError) as info:
        decode(payload, expected)
    assert info.value.limit in LIMIT_REASONS
    assert isinstance(info.value, DecodeError)
    return info.value


def test_every_type_has_a_cap_and_a_queue_budget_at_least_the_cap() -> None:
    for cls in MESSAGE_TYPES:
        assert cls.SCHEMA in PAYLOAD_CAPS and cls.SCHEMA in QUEUE_BYTE_BUDGETS
        assert queue_byte_budget(cls.SCHEMA) >= payload_cap(cls.SCHEMA)


def test_the_largest_valid_messages_fit_their_caps() -> None:
    """The caps never refuse what the count limits allow (ids at their 64-character maximum)."""
    det = Detection(np.zeros(4), 0.5, np.zeros((MAX_KEYPOINTS, 2)), np.zeros(MAX_KEYPOINTS),
                    "r" * 64, np.ones(MAX_KEYPOINTS))
    dets = RobotDetections("c" * 64, 1, 1, 10, 10, "m" * 128, (det,) * MAX_DETECTIONS)
    names = {f"{i:0128d}": 1.0 for i in range(256)}
    status = ServiceStatus("s" * 64, "i" * 64, 1, 1, rates_hz=names, latency_p50_ms=names,
                           latency_p99_ms=names, counters=dict.fromkeys(names, 2**62),
                           peers_alive=tuple(f"{i:064d}" for i in range(4096)), detail="d" * 4096)
    pose = PoseEstimate("r" * 64, 1, 1, 0.0, 0.0, 0.0, np.eye(3), "fused",
                        camera_ids=tuple(f"{i:064d}" for i in range(256)),
                        flags=tuple(f"{i:064d}" for i in range(32)), frame_id="m" * 64)
    for msg in (dets, status, pose, Odometry("r" * 64, 1, 1, 0.0, 0.0, 0.0, frame_id="o" * 64)):
        payload = encode(msg)
        assert len(payload) <= payload_cap(type(msg).SCHEMA)
        assert decode(payload, type(msg)) == msg


def test_a_payload_over_its_type_cap_is_refused_before_parsing() -> None:
    wire = _wire(S.sample_odometry())
    wire["pad"] = b"\0" * (PAYLOAD_CAPS["Odometry"] + 1)
    payload = msgpack.packb(wire)
    t0 = time.perf_counter()
    err = _limit(payload, Odometry)  # with the expected type: before any parsing
    assert err.limit == "payload_too_large" and "Odometry" in err.reason
    assert _limit(payload).limit == "payload_too_large"  # announced type: right after the envelope
    assert time.perf_counter() - t0 < 0.5


def test_nested_records_over_the_count_limit_are_never_built(monkeypatch) -> None:
    """The 1.5 MB probe of issue 17: thousands of nested detections under the byte cap cost only
    the header read, not thousands of Detection constructions."""
    wire = _wire(RobotDetections("cam1", 1, 0, 848, 480, "m", (_detection(2, sigmas=False),)))
    wire["detections"] = wire["detections"] * 2000
    payload = msgpack.packb(wire)
    assert len(payload) <= PAYLOAD_CAPS["RobotDetections"]
    built = []
    original = Detection.__post_init__

    def counting(self: Detection) -> None:
        built.append(1)
        original(self)

    monkeypatch.setattr(Detection, "__post_init__", counting)
    t0 = time.perf_counter()
    err = _limit(payload, RobotDetections)
    assert time.perf_counter() - t0 < 0.05
    assert err.limit == "too_many_entries" and "detections" in err.reason and not built
    wire["detections"] = wire["detections"][:MAX_DETECTIONS]
    assert len(decode(msgpack.packb(wire), RobotDetections).detections) == MAX_DETECTIONS


@pytest.mark.parametrize(
    ("field", "value"),
    [("flags", ["f"] * 33), ("camera_ids", ["c"] * 257)],
)
def test_list_fields_over_their_count_are_refused_from_the_header(field: str, value: list) -> None:
    wire = _wire(_pose())
    wire[field] = value
    err = _limit(msgpack.packb(wire), PoseEstimate)
    assert err.limit == "too_many_entries" and field in err.reason


def test_number_maps_over_their_count_are_refused_from_the_header() -> None:
    wire = _wire(ServiceStatus("backend", "main", 1, 0))
    wire["counters"] = {f"c{i}": i for i in range(257)}
    err = _limit(msgpack.packb(wire), ServiceStatus)
    assert err.limit == "too_many_entries" and "counters" in err.reason


def test_small_unknown_keys_are_tolerated_at_every_level() -> None:
    msg = RobotDetections("cam1", 1, 0, 848, 480, "m", (_detection(),))
    wire = _wire(msg)
    wire["added_later"] = {"dtype": "<f8", "shape": [256], "data": b"\0" * 2048}
    wire["note"] = "x" * 100
    wire["detections"][0]["per_keypoint_extra"] = list(range(12))
    assert decode(msgpack.packb(wire), RobotDetections) == msg


@pytest.mark.parametrize("where", ["top", "nested"])
def test_an_unknown_key_over_the_size_limit_is_refused(where: str) -> None:
    wire = _wire(RobotDetections("cam1", 1, 0, 848, 480, "m", (_detection(),)))
    target = wire if where == "top" else wire["detections"][0]
    target["padding"] = b"\0" * (MAX_UNKNOWN_VALUE_BYTES + 1)
    err = _limit(msgpack.packb(wire), RobotDetections)
    assert err.limit == "unknown_key_too_large" and "'padding'" in err.reason
    if where == "nested":
        assert "detections[0]" in err.reason


def test_too_many_unknown_keys_are_refused() -> None:
    wire = _wire(S.sample_odometry())
    wire.update({f"k{i}": i for i in range(MAX_UNKNOWN_KEYS)})
    assert isinstance(decode(msgpack.packb(wire), Odometry), Odometry)
    wire["one_more"] = 0
    assert _limit(msgpack.packb(wire), Odometry).limit == "too_many_unknown_keys"


def test_a_huge_key_is_refused_before_it_is_built() -> None:
    wire = _wire(S.sample_odometry())
    wire["k" * 300] = 0
    assert _limit(msgpack.packb(wire), Odometry).limit == "unknown_key_too_large"


def test_known_fields_in_any_order_and_trailing_bytes() -> None:
    msg = S.sample_odometry()
    wire = _wire(msg)
    reordered = dict(reversed(list(wire.items())))  # schema last
    assert decode(msgpack.packb(reordered)) == msg
    with pytest.raises(DecodeError, match="trailing"):
        decode(encode(msg) + b"\xc0")
