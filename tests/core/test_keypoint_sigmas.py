"""The optional per-keypoint pixel sigmas of :class:`protocol.messages.Detection`: validated on
construction (shape (M,), finite, > 0, <= MAX_KEYPOINT_SIGMA_PX), kept exactly by the codec,
absent on the wire from older senders (decoded as ``None``), and a hostile payload with a bad
sigma array is a :class:`DecodeError` naming the field."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

import protocol
from protocol import DecodeError, decode, encode
from protocol.messages import MAX_KEYPOINT_SIGMA_PX, Detection, RobotDetections

M = 5


def _detection(sigmas: object = None, m: int = M) -> Detection:
    kps = np.column_stack([np.linspace(10.0, 50.0, m), np.linspace(20.0, 60.0, m)])
    return Detection(np.array([5.0, 15.0, 55.0, 65.0]), 0.8, kps, np.full(m, 0.9),
                     "hsr", sigmas)


def _message(det: Detection) -> RobotDetections:
    return RobotDetections("cam1", 1_000, 3, 848, 480, "hsr/models", (det,))


# --------------------------------------------------------------------------------------------
# construction
# --------------------------------------------------------------------------------------------


def test_sigmas_default_to_none() -> None:
    assert _detection().keypoint_sigmas_px is None


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_valid_sigmas_are_kept_as_float64(dtype: type) -> None:
    sig = np.array([0.5, 1.0, 2.5, 40.0, MAX_KEYPOINT_SIGMA_PX], dtype=dtype)
    det = _detection(sig)
    assert det.keypoint_sigmas_px is not None
    assert det.keypoint_sigmas_px.dtype == np.float64
    assert det.keypoint_sigmas_px.shape == (M,)
    np.testing.assert_allclose(det.keypoint_sigmas_px, sig.astype(np.float64))


def test_sigmas_as_a_list_are_accepted() -> None:
    det = _detection([1.0, 2.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(det.keypoint_sigmas_px, [1.0, 2.0, 3.0, 4.0, 5.0])


def test_sigmas_do_not_alias_the_callers_array() -> None:
    sig = np.ones(M)
    det = _detection(sig)
    sig[0] = 99.0
    assert det.keypoint_sigmas_px[0] == 1.0


def test_empty_detection_with_empty_sigmas() -> None:
    det = _detection(np.zeros(0), m=0)
    assert det.keypoint_sigmas_px is not None and det.keypoint_sigmas_px.shape == (0,)


def test_equality_looks_at_the_sigmas() -> None:
    a = _detection(np.full(M, 2.0))
    assert a == _detection(np.full(M, 2.0))
    assert a != _detection(np.full(M, 3.0))
    assert a != _detection(None)


@pytest.mark.parametrize(
    ("sigmas", "what"),
    [
        (np.ones(M - 1), "too short"),
        (np.ones(M + 1), "too long"),
        (np.ones((M, 1)), "2-D"),
        (np.ones((1, M)), "row vector"),
        (np.float64(1.0), "scalar"),
        (np.array([1.0, 2.0, math.nan, 1.0, 1.0]), "NaN"),
        (np.array([1.0, 2.0, math.inf, 1.0, 1.0]), "infinity"),
        (np.array([1.0, 2.0, 0.0, 1.0, 1.0]), "zero"),
        (np.array([1.0, -0.5, 1.0, 1.0, 1.0]), "negative"),
        (np.array([1.0, 1.0, 1.0, 1.0, MAX_KEYPOINT_SIGMA_PX * 1.01]), "too large"),
        (np.ones(M, dtype=np.int64), "integer dtype"),
        ("1.0 1.0 1.0 1.0 1.0", "a string"),
    ],
)
def test_bad_sigmas_raise_validation_error_naming_the_field(sigmas: object, what: str) -> None:
    with pytest.raises(protocol.ValidationError, match="keypoint_sigmas_px") as info:
        _detection(sigmas)
    assert info.value.field == "keypoint_sigmas_px", what


def test_sigmas_must_match_the_keypoint_count_not_a_fixed_size() -> None:
    _detection(np.ones(3), m=3)  # fine for 3 keypoints
    with pytest.raises(protocol.ValidationError, match="keypoint_sigmas_px"):
        _detection(np.ones(3), m=4)


# --------------------------------------------------------------------------------------------
# codec
# --------------------------------------------------------------------------------------------


def test_codec_round_trip_keeps_the_sigmas() -> None:
    sig = np.array([0.3, 1.25, 7.0, 123.456, 1e-3])
    msg = _message(_detection(sig))
    back = decode(encode(msg), RobotDetections)
    assert back == msg
    got = back.detections[0].keypoint_sigmas_px
    assert got is not None and got.dtype == np.float64
    np.testing.assert_array_equal(got, sig)


def test_codec_round_trip_without_sigmas_stays_none() -> None:
    msg = _message(_detection(None))
    back = decode(encode(msg), RobotDetections)
    assert back == msg and back.detections[0].keypoint_sigmas_px is None


def test_sigmas_travel_as_an_array_map() -> None:
    sig = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    wire = msgpack.unpackb(encode(_message(_detection(sig))), raw=False)
    field = wire["detections"][0]["keypoint_sigmas_px"]
    assert field["dtype"] == "<f8" and field["shape"] == [M]
    assert field["data"] == sig.astype("<f8").tobytes()


def test_payload_of_an_older_sender_without_the_field_decodes_with_none() -> None:
    """An older edge agent does not send the key at all: the detection decodes, sigmas None."""
    msg = _message(_detection(None))
    wire = msgpack.unpackb(encode(msg), raw=False)
    assert "keypoint_sigmas_px" in wire["detections"][0]
    del wire["detections"][0]["keypoint_sigmas_px"]
    back = decode(msgpack.packb(wire, use_bin_type=True), RobotDetections)
    assert back.detections[0].keypoint_sigmas_px is None
    assert back == msg


def test_payload_without_the_field_among_detections_with_it() -> None:
    """Two detections, only the second sends sigmas: each decodes on its own terms."""
    sig = np.full(M, 1.5)
    msg = RobotDetections("cam1", 1, 0, 848, 480, "m", (_detection(None), _detection(sig)))
    wire = msgpack.unpackb(encode(msg), raw=False)
    del wire["detections"][0]["keypoint_sigmas_px"]
    back = decode(msgpack.packb(wire, use_bin_type=True), RobotDetections)
    assert back.detections[0].keypoint_sigmas_px is None
    np.testing.assert_array_equal(back.detections[1].keypoint_sigmas_px, sig)


def _hostile(sigmas_wire: object) -> bytes:
    wire = msgpack.unpackb(encode(_message(_detection(np.ones(M)))), raw=False)
    wire["detections"][0]["keypoint_sigmas_px"] = sigmas_wire
    return msgpack.packb(wire, use_bin_type=True)


@pytest.mark.parametrize(
    "array",
    [np.ones(M - 2), np.ones(M + 3), np.ones((M, 2)), np.ones(0)],
    ids=["short", "long", "2-D", "empty"],
)
def test_hostile_payload_with_wrong_sigma_shape_is_a_decode_error(array: np.ndarray) -> None:
    payload = _hostile({"dtype": "<f8", "shape": list(array.shape),
                        "data": array.astype("<f8").tobytes()})
    with pytest.raises(DecodeError, match=r"detections\[0\]\.keypoint_sigmas_px") as info:
        decode(payload)
    assert "shape" in str(info.value)


@pytest.mark.parametrize(
    ("values", "reason"),
    [
        ([1.0, 1.0, -1.0, 1.0, 1.0], "> 0"),
        ([1.0, 0.0, 1.0, 1.0, 1.0], "> 0"),
        ([1.0, 1.0, 1.0, 1.0, 2 * MAX_KEYPOINT_SIGMA_PX], "> 0"),
        ([1.0, math.nan, 1.0, 1.0, 1.0], "NaN"),
    ],
)
def test_hostile_payload_with_bad_sigma_values_is_a_decode_error(values: list[float],
                                                                  reason: str) -> None:
    arr = np.array(values, "<f8")
    payload = _hostile({"dtype": "<f8", "shape": [M], "data": arr.tobytes()})
    with pytest.raises(DecodeError, match=r"detections\[0\]\.keypoint_sigmas_px") as info:
        decode(payload)
    assert reason in str(info.value)


@pytest.mark.parametrize(
    "sigmas_wire",
    [
        "not an array",
        [1.0, 1.0, 1.0, 1.0, 1.0],
        {"dtype": "<f8", "shape": [M]},  # no data
        {"dtype": "<f8", "shape": [M], "data": b"\x00" * 7},  # byte count does not match
        {"dtype": "|O", "shape": [M], "data": b"\x00" * (8 * M)},  # object dtype
    ],
    ids=["string", "plain-list", "no-data", "short-data", "object-dtype"],
)
def test_hostile_payload_with_a_malformed_sigma_array_is_a_decode_error(
        sigmas_wire: object) -> None:
    with pytest.raises(DecodeError, match="keypoint_sigmas_px"):
        decode(_hostile(sigmas_wire))


def test_explicit_nil_sigmas_decode_as_none() -> None:
    back = decode(_hostile(None), RobotDetections)
    assert back.detections[0].keypoint_sigmas_px is None
