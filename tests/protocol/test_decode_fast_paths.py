"""The cheaper checks of the decode path refuse exactly what the plain ones refused: the
finiteness test by a sum of squares (falling back to every element when a finite value
overflows it), wire arrays' sizes (exactly int, a bool is no size) and their views of the
payload (read-only, never copied)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from protocol import decode
from protocol.errors import DecodeError, ValidationError
from protocol.messages import RobotDetections
from protocol.validation import check_array


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_every_non_finite_value_is_refused(dtype: str, bad: float) -> None:
    for where in (0, 5, 11):
        arr = np.zeros((6, 2), dtype=dtype)
        arr.reshape(-1)[where] = bad
        with pytest.raises(ValidationError, match="NaN or infinity"):
            check_array("kp", arr, dtypes=(dtype,), shape=(None, 2))


@pytest.mark.parametrize("dtype, big", [("float32", 3e38), ("float64", 1e300)])
def test_finite_values_that_overflow_the_sum_of_squares_pass(dtype: str, big: float) -> None:
    arr = np.full((4, 2), big, dtype=dtype)
    arr[1, 0] = -big
    out = check_array("kp", arr, dtypes=(dtype,), shape=(None, 2))
    np.testing.assert_array_equal(out, arr)
    # ... and a NaN among them is still found
    arr[3, 1] = np.nan
    with pytest.raises(ValidationError, match="NaN or infinity"):
        check_array("kp", arr, dtypes=(dtype,), shape=(None, 2))


def test_empty_and_non_float_arrays() -> None:
    assert check_array("kp", np.zeros((0, 2)), dtypes=("float64",), shape=(None, 2)).shape == (0, 2)
    ints = np.array([1, 2, 3], dtype=np.int32)
    np.testing.assert_array_equal(check_array("ids", ints, dtypes=("int32",), shape=(3,)), ints)
    with pytest.raises(ValidationError, match=r"shape \(3,\) does not match \(4\)"):
        check_array("ids", ints, dtypes=("int32",), shape=(4,))
    with pytest.raises(ValidationError, match=r"does not match \(Nx2\)"):
        check_array("kp", np.zeros((3, 2, 1)), dtypes=("float64",), shape=(None, 2))


def _detections(keypoints: dict) -> bytes:
    det = {"bbox_xyxy": {"dtype": "<f8", "shape": [4], "data": np.arange(4.0).tobytes()},
           "score": 0.9, "keypoints_px": keypoints,
           "keypoint_scores": {"dtype": "<f8", "shape": [3], "data": np.ones(3).tobytes()}}
    return msgpack.packb({"schema": "RobotDetections", "schema_version": 1, "camera_id": "c",
                          "stamp_ns": 1, "seq": 0, "image_width": 8, "image_height": 8,
                          "model_id": "m", "detections": [det]}, use_bin_type=True)


def test_wire_arrays_are_read_only_views_of_exact_sizes() -> None:
    data = np.arange(6.0).tobytes()
    msg = decode(_detections({"dtype": "<f8", "shape": [3, 2], "data": data}), RobotDetections)
    kp = msg.detections[0].keypoints_px
    assert kp.shape == (3, 2) and not kp.flags.writeable
    np.testing.assert_array_equal(kp.reshape(-1), np.arange(6.0))
    for shape, why in (([True, 2], "shape must be"), ([3.0, 2], "shape must be"),
                       ([-3, -2], "shape must be"), ([1, 1, 1, 3, 2], "shape must be"),
                       ([3, 3], "needs 72 bytes")):
        with pytest.raises(DecodeError, match=why):
            decode(_detections({"dtype": "<f8", "shape": shape, "data": data}), RobotDetections)
    for dtype in ("<f2", "|O", 8, None):
        with pytest.raises(DecodeError, match="not allowed"):
            decode(_detections({"dtype": dtype, "shape": [3, 2], "data": data}), RobotDetections)
