"""Hostile payloads: only DecodeError escapes decode, and memory stays bounded."""

from __future__ import annotations

import contextlib
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import MAX_PAYLOAD_BYTES, DecodeError, decode, encode
from tests.protocol import strategies as S

_FUZZ = settings(
    max_examples=500,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def _decode_only_decode_error(payload: bytes) -> None:
    try:
        decode(payload)
    except DecodeError as exc:
        assert exc.reason
    # any other exception type fails the test by propagating


@_FUZZ
@given(st.binary(max_size=512))
def test_random_bytes(payload: bytes) -> None:
    _decode_only_decode_error(payload)


@_FUZZ
@given(S.any_message, st.data())
def test_mutated_valid_payloads(msg, data) -> None:
    payload = bytearray(encode(msg))
    for _ in range(data.draw(st.integers(1, 8))):
        op = data.draw(st.sampled_from(["flip", "truncate", "insert", "delete"]))
        if not payload:
            break
        i = data.draw(st.integers(0, len(payload) - 1))
        if op == "flip":
            payload[i] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "truncate":
            del payload[i:]
        elif op == "insert":
            payload[i:i] = data.draw(st.binary(min_size=1, max_size=8))
        else:
            del payload[i]
    _decode_only_decode_error(bytes(payload))


json_like = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=10)
    | st.binary(max_size=16),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=20,
)


@settings(max_examples=500, deadline=None)
@given(
    st.sampled_from(
        [
            "RobotDetections",
            "SemanticCloud",
            "Odometry",
            "PoseEstimate",
            "PoseCorrection",
            "ServiceStatus",
        ]
    ),
    st.dictionaries(
        st.sampled_from(
            [
                "camera_id",
                "stamp_ns",
                "seq",
                "image_width",
                "image_height",
                "model_id",
                "detections",
                "sensor_id",
                "frame_id",
                "points_xyz",
                "class_ids",
                "confidences",
                "robot_id",
                "x",
                "y",
                "theta",
                "covariance",
                "source",
                "flags",
                "service",
                "instance_id",
                "counters",
                "rates_hz",
                "T_frame_sensor",
            ]
        ),
        json_like,
        max_size=12,
    ),
)
def test_structurally_valid_maps_with_wrong_types(schema, fields) -> None:
    payload = msgpack.packb({"schema": schema, "schema_version": 1, **fields}, use_bin_type=True)
    _decode_only_decode_error(payload)


def _array(dtype: str, shape: list, data: bytes) -> dict:
    return {"dtype": dtype, "shape": shape, "data": data}


@pytest.mark.parametrize(
    "points",
    [
        _array("<f4", [10**12, 3], b""),  # shape claims terabytes
        _array("<f4", [2, 3], b"\x00" * 7),  # byte count mismatch
        _array("|O", [1, 3], b"\x00" * 24),  # object dtype never allowed
        _array("<f4", [-1, 3], b""),  # negative size
        _array("<f4", [1, 1, 1, 1, 1, 3], b"\x00" * 12),  # too many dims
        _array("<f4", [2, 3], np.full(6, np.nan, "<f4").tobytes()),  # NaN
        {"dtype": "<f4", "shape": [1, 3]},  # missing data
    ],
)
def test_hostile_arrays_are_rejected(points) -> None:
    payload = msgpack.packb(
        {
            "schema": "SemanticCloud",
            "schema_version": 1,
            "sensor_id": "s",
            "stamp_ns": 0,
            "seq": 0,
            "frame_id": "map",
            "points_xyz": points,
            "class_ids": _array("|u1", [0], b""),
            "confidences": _array("<f4", [0], b""),
        },
        use_bin_type=True,
    )
    with pytest.raises(DecodeError):
        decode(payload)


def test_oversized_payload_rejected_before_parsing() -> None:
    with pytest.raises(DecodeError, match="exceeds"):
        decode(b"\x00" * (MAX_PAYLOAD_BYTES + 1))


def test_huge_container_headers_do_not_allocate() -> None:
    # array32 / map32 / bin32 headers announcing 4 billion entries, with no body
    for header in (b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff"):
        with pytest.raises(DecodeError):
            decode(header)


def test_deep_nesting_is_a_decode_error() -> None:
    payload = b"\x91" * 100_000 + b"\xc0"
    with pytest.raises(DecodeError):
        decode(payload)


def test_memory_stays_bounded_under_fuzzing() -> None:
    rng = np.random.default_rng(1)
    valid = encode(S.sample_cloud(50))
    tracemalloc.start()
    try:
        for i in range(3000):
            buf = bytearray(valid)
            for _ in range(4):
                buf[int(rng.integers(len(buf)))] = int(rng.integers(256))
            if i % 3 == 0:
                buf = bytearray(rng.bytes(int(rng.integers(1, 256))))
            with contextlib.suppress(DecodeError):
                decode(bytes(buf))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 32 * 1024 * 1024, f"peak {peak / 1e6:.1f} MB while decoding small payloads"
