"""The TF buffer: chains of frames, static and moving transforms, interpolation, missing and
stale transforms, refused input, and /tf messages decoded from real rosbags CDR."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.geometry import (
    invert_transform,
    rotation_from_rotvec,
    rotation_from_rpy,
    rotation_to_quaternion,
    rotation_z,
    rotvec_from_rotation,
)
from core.tf_buffer import (
    TfBuffer,
    TfBufferConfig,
    TfError,
    TfExtrapolationError,
    TfMissingError,
    TfStaleError,
    interpolate_rigid,
)
from robot_bridge.adapters import ros2

S = 1_000_000_000
T0 = 1_700_000_000 * S


def se3(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


#: the head: base_link -> head_pan_link (moving: pan about z, at a fixed offset) ->
#: head_tilt_link (moving: tilt about y) -> camera (static: the optical frame, z forward)
T_PAN_OFFSET = np.array([0.02, 0.0, 1.05])
T_TILT_OFFSET = np.array([0.0, 0.0, 0.12])
T_TILT_CAMERA = se3(rotation_from_rpy(-math.pi / 2, 0.0, -math.pi / 2), [0.08, 0.03, 0.05])


def T_base_pan(pan_rad: float) -> np.ndarray:
    return se3(rotation_z(pan_rad), T_PAN_OFFSET)


def T_pan_tilt(tilt_rad: float) -> np.ndarray:
    return se3(rotation_from_rpy(0.0, tilt_rad, 0.0), T_TILT_OFFSET)


def head_buffer(config: TfBufferConfig | None = None) -> TfBuffer:
    """Pan 0 -> 0.6 rad and tilt 0.1 -> -0.3 rad between T0 and T0 + 1 s, in 0.1 s steps."""
    buf = TfBuffer(config)
    assert buf.add("head_tilt_link", "camera", 0, T_TILT_CAMERA, static=True)
    for k in range(11):
        stamp = T0 + k * S // 10
        assert buf.add("base_link", "head_pan_link", stamp, T_base_pan(0.06 * k))
        assert buf.add("head_pan_link", "head_tilt_link", stamp, T_pan_tilt(0.1 - 0.04 * k))
    return buf


def assert_same_transform(A: np.ndarray, B: np.ndarray, *, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(A, B, atol=atol, rtol=0.0)


# --------------------------------------------------------------------------------------------
# chains, static and moving transforms
# --------------------------------------------------------------------------------------------


def test_chain_of_three_frames_at_a_message_stamp_both_directions():
    buf = head_buffer()
    stamp = T0 + 3 * S // 10
    expected = T_base_pan(0.18) @ T_pan_tilt(0.1 - 0.12) @ T_TILT_CAMERA
    T_base_camera = buf.lookup("base_link", "camera", stamp)
    assert_same_transform(T_base_camera, expected)
    # the reverse walks down the tree: the inverse
    assert_same_transform(buf.lookup("camera", "base_link", stamp), invert_transform(expected))
    # a point 2 m in front of the camera (optical z) lands in base_link where the truth says
    p_base = T_base_camera @ np.array([0.0, 0.0, 2.0, 1.0])
    assert_same_transform(p_base, expected @ np.array([0.0, 0.0, 2.0, 1.0]))
    assert buf.counters["lookups_ok"] == 2 and buf.counters["held"] == 0


def test_lookup_between_branches_goes_through_the_common_ancestor():
    buf = head_buffer()
    T_base_laser = se3(rotation_z(math.pi), [0.2, 0.0, 0.3])
    assert buf.add("base_link", "base_range_sensor_link", 0, T_base_laser, static=True)
    stamp = T0 + 5 * S // 10
    T_base_camera = T_base_pan(0.30) @ T_pan_tilt(-0.10) @ T_TILT_CAMERA
    assert_same_transform(buf.lookup("base_range_sensor_link", "camera", stamp),
                          invert_transform(T_base_laser) @ T_base_camera)
    # from the camera to its own ancestor, and a frame to itself
    assert_same_transform(buf.lookup("head_pan_link", "camera", stamp),
                          T_pan_tilt(-0.10) @ T_TILT_CAMERA)
    assert_same_transform(buf.lookup("camera", "camera", stamp), np.eye(4))


def test_static_transform_holds_at_any_time():
    buf = TfBuffer()
    T = se3(rotation_from_rpy(0.1, -0.2, 0.3), [0.1, 0.2, 0.3])
    assert buf.add("head_tilt_link", "camera", T0, T, static=True)
    for stamp in (0, T0 - 3600 * S, T0, T0 + 3600 * S, None):
        assert_same_transform(buf.lookup("head_tilt_link", "camera", stamp), T)
    assert buf.is_static("camera") is True and buf.parent_of("camera") == "head_tilt_link"
    # /tf_static republished (a restarted robot) replaces the value
    T2 = se3(np.eye(3), [0.0, 0.0, 0.5])
    assert buf.add("head_tilt_link", "camera", T0 + S, T2, static=True)
    assert_same_transform(buf.lookup("head_tilt_link", "camera", T0), T2)
    assert buf.counters["static_transforms"] == 2


def test_interpolation_at_a_stamp_between_two_messages():
    buf = TfBuffer()
    R0 = rotation_from_rpy(0.2, -0.1, 0.4)
    R1 = rotation_from_rpy(-0.3, 0.25, 1.3)
    t0, t1 = np.array([0.0, 0.0, 1.0]), np.array([0.4, -0.2, 1.1])
    assert buf.add("base_link", "head", T0, se3(R0, t0))
    assert buf.add("base_link", "head", T0 + 100_000_000, se3(R1, t1))
    for fraction in (0.25, 0.5, 0.9):
        stamp = T0 + round(fraction * 100_000_000)
        # the truth: along the geodesic R0 exp(f log(R0^T R1)), translation linear
        R_true = R0 @ rotation_from_rotvec(fraction * rotvec_from_rotation(R0.T @ R1))
        assert_same_transform(buf.lookup("base_link", "head", stamp),
                              se3(R_true, t0 + fraction * (t1 - t0)), atol=1e-9)
    # at a held stamp: that message exactly
    assert_same_transform(buf.lookup("base_link", "head", T0 + 100_000_000), se3(R1, t1))


def test_interpolation_of_the_moving_head_chain():
    buf = head_buffer()
    stamp = T0 + 250_000_000  # between the messages at 0.2 s and 0.3 s
    expected = T_base_pan(0.15) @ T_pan_tilt(0.0) @ T_TILT_CAMERA  # single-axis: exact
    assert_same_transform(buf.lookup("base_link", "camera", stamp), expected)


def test_slerp_takes_the_shorter_arc():
    from core.tf_buffer import Rigid

    qa = np.array(rotation_to_quaternion(rotation_z(math.radians(170))))
    qb = np.array(rotation_to_quaternion(rotation_z(math.radians(-170))))
    assert float(np.dot(qa, qb)) < 0.0  # 20 deg apart, but on opposite quaternion hemispheres
    mid = interpolate_rigid(Rigid(np.zeros(3), qa), Rigid(np.zeros(3), qb), 0.5).matrix()
    # halfway across +-180 deg, not through 0
    assert_same_transform(mid[:3, :3], rotation_z(math.pi), atol=1e-12)


def test_latest_common_time_when_no_stamp_is_given():
    buf = head_buffer()
    # the tilt joint stops 0.2 s before the pan joint: "latest" is the tilt's newest stamp
    buf2 = TfBuffer()
    for k in range(11):
        stamp = T0 + k * S // 10
        buf2.add("base_link", "head_pan_link", stamp, T_base_pan(0.06 * k))
        if k <= 8:
            buf2.add("head_pan_link", "head_tilt_link", stamp, T_pan_tilt(0.1 - 0.04 * k))
    expected = T_base_pan(0.48) @ T_pan_tilt(0.1 - 0.32)
    assert_same_transform(buf2.lookup("base_link", "head_tilt_link"), expected)
    assert_same_transform(buf.lookup("base_link", "camera"),
                          T_base_pan(0.6) @ T_pan_tilt(-0.3) @ T_TILT_CAMERA)


# --------------------------------------------------------------------------------------------
# missing, stale, out of the history
# --------------------------------------------------------------------------------------------


def test_missing_frame_is_named_and_counted():
    buf = head_buffer()
    with pytest.raises(TfMissingError) as err:
        buf.lookup("base_link", "hand_camera", T0)
    assert err.value.missing_frame == "hand_camera"
    assert "'hand_camera' is unknown" in str(err.value) and "base_link" in str(err.value)
    assert buf.counters["missing"] == 1 and buf.counters["lookups_ok"] == 0
    assert "hand_camera" in buf.last_error and "hand_camera" in buf.detail()


def test_disconnected_trees_name_both_roots():
    buf = head_buffer()
    assert buf.add("odom", "base_footprint", T0, np.eye(4))
    with pytest.raises(TfMissingError) as err:
        buf.lookup("odom", "camera", T0)
    assert err.value.missing_frame is None
    assert err.value.roots == ("odom", "base_link")
    assert "not connected" in str(err.value)
    assert buf.counters["missing"] == 1
    # the missing edge arrives: the same lookup now works
    assert buf.add("base_footprint", "base_link", 0, np.eye(4), static=True)
    assert buf.can_transform("odom", "camera", T0)


def test_stale_transform_says_how_old_against_the_limit():
    buf = head_buffer(TfBufferConfig(max_age_s=0.1))
    newest = T0 + S
    # 50 ms past the newest: within the limit, the newest is held
    assert_same_transform(buf.lookup("base_link", "camera", newest + 50_000_000),
                          T_base_pan(0.6) @ T_pan_tilt(-0.3) @ T_TILT_CAMERA)
    assert buf.counters["held"] == 2  # pan and tilt edges
    # the pan joint goes on publishing, the tilt joint stops: the tilt edge is named
    for k in range(1, 6):
        assert buf.add("base_link", "head_pan_link", newest + k * S // 10, T_base_pan(0.6))
    with pytest.raises(TfStaleError) as err:
        buf.lookup("base_link", "camera", newest + 500_000_000)
    exc = err.value
    assert (exc.parent, exc.child) == ("head_pan_link", "head_tilt_link")
    assert exc.age_ns == 500_000_000 and exc.limit_ns == 100_000_000
    assert "0.500 s older" in str(exc) and "limit 0.1 s" in str(exc)
    assert buf.counters["stale"] == 1 and buf.counters["extrapolation"] == 0
    assert isinstance(exc, TfError) and "stale" in buf.detail()


def test_stamp_before_the_history_is_an_extrapolation_error():
    buf = head_buffer()
    with pytest.raises(TfExtrapolationError) as err:
        buf.lookup("base_link", "camera", T0 - 1)
    assert (err.value.oldest_ns, err.value.newest_ns) == (T0, T0 + S)
    assert "before the oldest held" in str(err.value)
    assert buf.counters["extrapolation"] == 1


def test_history_is_bounded_in_seconds():
    buf = TfBuffer(TfBufferConfig(history_s=2.0, max_items_per_edge=1000))
    for k in range(101):  # 10 s at 10 Hz
        assert buf.add("base_link", "head", T0 + k * S // 10, T_base_pan(0.01 * k))
    # the last 2 s (plus the one transform at the horizon) are kept
    assert_same_transform(buf.lookup("base_link", "head", T0 + 8 * S), T_base_pan(0.8))
    with pytest.raises(TfExtrapolationError):
        buf.lookup("base_link", "head", T0 + 7 * S)
    # a transform older than the window is refused, not inserted
    assert not buf.add("base_link", "head", T0 + 5 * S, T_base_pan(0.0))
    assert buf.counters["too_old"] == 1
    capped = TfBuffer(TfBufferConfig(history_s=100.0, max_items_per_edge=5))
    for k in range(20):
        capped.add("base_link", "head", T0 + k * S, T_base_pan(0.0))
    with pytest.raises(TfExtrapolationError) as err:
        capped.lookup("base_link", "head", T0 + 14 * S)
    assert err.value.oldest_ns == T0 + 15 * S


def test_out_of_order_messages_are_placed_by_stamp():
    buf = TfBuffer()
    assert buf.add("base_link", "head", T0 + 2 * S, T_base_pan(0.2))
    assert buf.add("base_link", "head", T0, T_base_pan(0.0))
    assert_same_transform(buf.lookup("base_link", "head", T0 + S), T_base_pan(0.1))
    assert not buf.add("base_link", "head", T0, T_base_pan(0.5))  # first of a stamp wins
    assert buf.counters["duplicate"] == 1
    assert_same_transform(buf.lookup("base_link", "head", T0), T_base_pan(0.0))


# --------------------------------------------------------------------------------------------
# refused input
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("q, what", [
    ((0.0, 0.0, float("nan"), 1.0), "unit quaternion"),
    ((0.0, 0.0, 0.0, 0.0), "unit quaternion"),
    ((0.0, 0.0, 0.0, 2.0), "unit quaternion"),
    ((0.0, 0.0, float("inf"), 1.0), "unit quaternion"),
])
def test_invalid_quaternions_are_refused_and_counted(q, what):
    buf = head_buffer()
    before = buf.lookup("base_link", "head_pan_link", T0 + S)
    assert not buf.add_quaternion("base_link", "head_pan_link", T0 + S + 1, (0, 0, 0), q)
    assert buf.counters["invalid"] == 1 and what in buf.last_error
    assert "base_link -> head_pan_link" in buf.last_error
    # nothing of it reached the history: the newest is still the last good one
    assert_same_transform(buf.lookup("base_link", "head_pan_link", T0 + S), before)


def test_other_bad_transforms_are_refused_and_counted():
    buf = head_buffer()
    bad_translation = np.eye(4)
    bad_translation[0, 3] = float("nan")
    not_rotation = np.eye(4)
    not_rotation[:3, :3] *= 1.5
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    cases = [
        ("base_link", "head_pan_link", bad_translation),
        ("base_link", "head_pan_link", not_rotation),
        ("base_link", "head_pan_link", mirror),
        ("base_link", "base_link", np.eye(4)),
        ("", "x", np.eye(4)),
        ("base_link", "head_pan_link", np.eye(3)),
    ]
    for parent, child, T in cases:
        assert not buf.add(parent, child, T0 + 2 * S, T)
    assert buf.counters["invalid"] == len(cases)
    assert not buf.add("base_link", "head_pan_link", -5, np.eye(4))
    assert buf.counters["invalid"] == len(cases) + 1


def test_frame_with_two_parents_is_refused_and_counted():
    buf = head_buffer()
    assert not buf.add("odom", "head_pan_link", T0 + S // 2, np.eye(4))
    assert buf.counters["two_parents"] == 1
    assert "already has parent 'base_link'" in buf.last_error
    assert buf.parent_of("head_pan_link") == "base_link"
    # a loop is refused too: base_link below camera
    assert not buf.add("camera", "base_link", T0, np.eye(4))
    assert buf.counters["loops"] == 1
    # static and dynamic on one edge
    assert not buf.add("head_tilt_link", "camera", T0, np.eye(4), static=False)
    assert buf.counters["kind_conflict"] == 1
    assert_same_transform(buf.lookup("base_link", "camera", T0),
                          T_base_pan(0.0) @ T_pan_tilt(0.1) @ T_TILT_CAMERA)


def test_config_is_checked():
    with pytest.raises(ValueError, match="history_s"):
        TfBufferConfig(history_s=0.0)
    with pytest.raises(ValueError, match="max_age_s"):
        TfBufferConfig(max_age_s=float("nan"))
    with pytest.raises(ValueError, match="max_items_per_edge"):
        TfBufferConfig(max_items_per_edge=1)
    with pytest.raises(ValueError, match="max_frames"):
        TfBufferConfig(max_frames=0)


def test_a_flood_of_invented_frames_is_bounded():
    buf = TfBuffer(TfBufferConfig(max_frames=50))
    held = sum(buf.add("base_link", f"junk_{k}", T0, np.eye(4), static=True) for k in range(80))
    assert held == 50 and buf.counters["too_many_frames"] == 30
    # known frames still take new transforms
    assert buf.add("base_link", "junk_3", T0, T_base_pan(0.2), static=True)
    assert_same_transform(buf.lookup("base_link", "junk_3"), T_base_pan(0.2))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-3.1, 3.1), st.floats(-1.5, 1.5), st.floats(-3.1, 3.1),
                          st.floats(-2, 2), st.floats(-2, 2), st.floats(-2, 2)),
                min_size=2, max_size=5),
       st.integers(0, 4), st.integers(0, 4))
def test_lookup_equals_the_product_of_the_chain(edges, i, j):
    """A chain f0 <- f1 <- ... : T_fi_fj is the product of the edges between them."""
    buf = TfBuffer()
    Ts = [se3(rotation_from_rpy(r, p, y), (x, yy, z)) for r, p, y, x, yy, z in edges]
    for k, T in enumerate(Ts):
        assert buf.add(f"f{k}", f"f{k + 1}", T0, T, static=k % 2 == 0)
    i, j = i % (len(Ts) + 1), j % (len(Ts) + 1)
    T_root = [np.eye(4)]
    for T in Ts:
        T_root.append(T_root[-1] @ T)
    expected = invert_transform(T_root[i]) @ T_root[j]
    assert_same_transform(buf.lookup(f"f{i}", f"f{j}", T0), expected, atol=1e-9)


# --------------------------------------------------------------------------------------------
# /tf and /tf_static as ROS sends them: real CDR (and ROS 1) bytes made with rosbags
# --------------------------------------------------------------------------------------------


def tf_message(ts, transforms, *, ros1: bool = False):
    """A ``tf2_msgs/msg/TFMessage`` from ``(parent, child, stamp_ns, T)`` tuples."""
    t = ts.types
    items = []
    for parent, child, stamp_ns, T in transforms:
        stamp = t["builtin_interfaces/msg/Time"](sec=stamp_ns // S, nanosec=stamp_ns % S)
        header = (t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=parent) if ros1
                  else t["std_msgs/msg/Header"](stamp=stamp, frame_id=parent))
        if isinstance(T, np.ndarray):
            q = rotation_to_quaternion(T[:3, :3])
            tr = T[:3, 3]
        else:  # (translation, quaternion) as given, possibly bad
            tr, q = T
        items.append(t["geometry_msgs/msg/TransformStamped"](
            header=header, child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=tr[0], y=tr[1], z=tr[2]),
                rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))))
    return t["tf2_msgs/msg/TFMessage"](transforms=items)


@pytest.mark.parametrize("ros1", [False, True])
def test_tf_and_tf_static_from_serialized_messages(ros1):
    pytest.importorskip("rosbags")
    ts = ros2.typestore(ros1)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    static_bytes = bytes(serialize(tf_message(ts, [
        ("/head_tilt_link", "camera", 0, T_TILT_CAMERA)], ros1=ros1), ros2.TF_MESSAGE_TYPE))
    buf = TfBuffer()
    assert buf.add_tf_message(ros2.deserialize_tf_message(static_bytes, ros1=ros1),
                              static=True) == 1
    for k in range(3):
        stamp = T0 + k * S // 10
        payload = bytes(serialize(tf_message(ts, [
            ("base_link", "head_pan_link", stamp, T_base_pan(0.06 * k)),
            ("head_pan_link", "head_tilt_link", stamp, T_pan_tilt(0.1 - 0.04 * k)),
        ], ros1=ros1), ros2.TF_MESSAGE_TYPE))
        assert payload[:4] != b"" and len(payload) > 100
        assert buf.add_tf_message(ros2.deserialize_tf_message(payload, ros1=ros1),
                                  static=False) == 2
    # the leading "/" of a frame id is dropped, as tf2 does
    assert buf.parent_of("camera") == "head_tilt_link"
    expected = T_base_pan(0.09) @ T_pan_tilt(0.04) @ T_TILT_CAMERA
    assert_same_transform(buf.lookup("base_link", "camera", T0 + 150_000_000), expected,
                          atol=1e-12)


def test_bad_tf_payloads_and_transforms_are_counted():
    pytest.importorskip("rosbags")
    ts = ros2.typestore(False)
    payload = bytes(ts.serialize_cdr(tf_message(ts, [
        ("base_link", "head_pan_link", T0, T_base_pan(0.1)),
        ("base_link", "head_tilt_link", T0, ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0))),
        ("base_link", "arm", T0, ((float("nan"), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))),
    ]), ros2.TF_MESSAGE_TYPE))
    buf = TfBuffer()
    assert buf.add_tf_message(ros2.deserialize_tf_message(payload), static=False) == 1
    assert buf.counters["invalid"] == 2 and buf.counters["transforms"] == 1
    with pytest.raises(ros2.RosConversionError, match="TFMessage"):
        ros2.deserialize_tf_message(payload[: len(payload) // 2])
    with pytest.raises(ros2.RosConversionError):
        ros2.deserialize_tf_message("not bytes")
