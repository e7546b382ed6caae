"""The codec's two decode paths agree: the native one (msgpack's C unpacker under limits derived
from the message type) returns exactly what the careful one (raw-structure scan, nothing built
before its limit) returns, or declines; and it never builds more than the largest valid message
of the expected type holds."""

from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import DecodeError, encode
from protocol import codec as C
from protocol.limits import LimitError
from protocol.messages import (
    MAX_DETECTIONS,
    MAX_KEYPOINTS,
    MESSAGE_TYPES,
    Detection,
    Message,
    RobotDetections,
)
from tests.protocol import strategies as S

_FUZZ = settings(max_examples=300, deadline=None,
                 suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _outcome(fn, payload: bytes, expected: type[Message] | None) -> tuple[str, object]:
    try:
        msg = fn(payload, expected)
    except LimitError as exc:
        return "limit", exc.limit
    except DecodeError:
        return "error", None
    return "message", msg


def _assert_paths_agree(payload: bytes, expected: type[Message] | None) -> None:
    try:
        native = C._decode_native(payload, expected)
    except DecodeError:
        # the message's own validation refused what the native path built: final, and the
        # careful path must refuse it too
        assert _outcome(C.decode_checked, payload, expected)[0] != "message"
        return
    if native is None:
        return  # declined: the careful path decides alone
    kind, careful = _outcome(C.decode_checked, payload, expected)
    assert kind == "message" and careful == native


@_FUZZ
@given(S.any_message, st.data())
def test_the_paths_agree_on_mutated_valid_payloads(msg: Message, data) -> None:
    payload = bytearray(encode(msg))
    for _ in range(data.draw(st.integers(0, 3))):
        i = data.draw(st.integers(0, len(payload) - 1))
        payload[i] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(len(payload) // 2, len(payload)))
    expected = data.draw(st.sampled_from([None, type(msg), *MESSAGE_TYPES]))
    _assert_paths_agree(bytes(payload[:cut]), expected)


@_FUZZ
@given(S.any_message, st.dictionaries(st.text(max_size=8),
                                      st.integers(-(2**63), 2**64 - 1) | st.text(max_size=8),
                                      max_size=3))
def test_the_paths_agree_with_extra_and_replaced_keys(msg: Message, extra: dict) -> None:
    wire = msgpack.unpackb(encode(msg), raw=False)
    wire.update(extra)
    _assert_paths_agree(msgpack.packb(wire), type(msg))
    _assert_paths_agree(msgpack.packb(wire), None)


@given(S.any_message)
@settings(max_examples=200, deadline=None)
def test_valid_messages_take_the_native_path(msg: Message) -> None:
    assert C._decode_native(encode(msg), type(msg)) == msg
    assert C._decode_native(encode(msg), None) == msg


def test_the_largest_valid_detections_take_the_native_path() -> None:
    det = Detection(np.zeros(4), 0.5, np.zeros((MAX_KEYPOINTS, 2)), np.zeros(MAX_KEYPOINTS),
                    "r" * 64, np.ones(MAX_KEYPOINTS), "k" * 64)
    msg = RobotDetections("c" * 64, 1, 1, 10, 10, "m" * 128, (det,) * MAX_DETECTIONS)
    assert C._decode_native(encode(msg), RobotDetections) == msg


def test_many_small_containers_are_stopped_by_the_count_not_built() -> None:
    """Under an unknown key, 64 x 64 x 40 one-entry maps (164k dicts, 0.5 MB): within every
    per-container limit and the byte cap, but far more containers than a detections message
    holds; the native path stops after its budget and the careful path refuses the key."""
    wire = msgpack.unpackb(encode(RobotDetections("c", 1, 1, 10, 10, "m")), raw=False)
    wire["extra"] = [[[{"": 0}] * 40] * 64] * 64
    payload = msgpack.packb(wire)
    t0 = time.perf_counter()
    assert C._decode_native(payload, RobotDetections) is None
    assert time.perf_counter() - t0 < 0.05
    with pytest.raises(LimitError) as info:
        C.decode(payload, RobotDetections)
    assert info.value.limit == "unknown_key_too_large"


def test_native_limits_are_never_looser_than_the_structural_ones() -> None:
    from protocol.limits import MAX_ARRAY_ENTRIES, MAX_MAP_ENTRIES, MAX_STR_BYTES, payload_cap

    for cls in (*MESSAGE_TYPES, None):
        limits = C.native_limits(cls)
        assert limits.unpack["max_array_len"] <= MAX_ARRAY_ENTRIES
        assert limits.unpack["max_map_len"] <= MAX_MAP_ENTRIES
        assert limits.unpack["max_str_len"] <= MAX_STR_BYTES
        if cls is not None:
            assert limits.unpack["max_bin_len"] <= payload_cap(cls.SCHEMA)
    assert C.native_limits(RobotDetections).unpack["max_array_len"] == MAX_DETECTIONS


def test_an_envelope_key_inside_a_nested_record_is_unknown_there() -> None:
    msg = RobotDetections("c", 1, 1, 10, 10, "m", (Detection(np.zeros(4), 0.5, np.zeros((2, 2)),
                                                             np.zeros(2)),))
    wire = msgpack.unpackb(encode(msg), raw=False)
    wire["detections"][0]["schema"] = "x" * 5000  # over the unknown-value limit
    payload = msgpack.packb(wire)
    assert C._decode_native(payload, RobotDetections) is None
    with pytest.raises(LimitError) as info:
        C.decode(payload, RobotDetections)
    assert info.value.limit == "unknown_key_too_large"
