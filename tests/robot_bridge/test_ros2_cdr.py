"""ROS message conversion of the ROS 2 adapter, checked against real rosbags serialization."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.geometry import angle_diff
from protocol.messages import PoseCorrection
from robot_bridge.adapters import ros2
from robot_bridge.adapters.base import OdometrySample

pytest.importorskip("rosbags")

S = 1_000_000_000
STAMP_NS = 1_700_000_123 * S + 456_789_012
PWCS = "geometry_msgs/msg/PoseWithCovarianceStamped"


def correction(x=1.25, y=-2.5, theta=2.9, seq=7, kind="correction") -> PoseCorrection:
    cov = np.array([[0.010, 0.002, 0.001], [0.002, 0.020, 0.003], [0.001, 0.003, 0.030]])
    return PoseCorrection("hsr", STAMP_NS, seq, x, y, theta, cov, kind, 0.12, 0.05)


def make_odometry(ts, *, ros1=False, x=3.5, y=-1.25, yaw=-2.8, vx=0.3, vy=-0.05, wz=0.2,
                  frame="odom", cov_diag=(0.01, 0.02, 0.0, 0.0, 0.0, 0.04), quat_scale=1.0):
    """A nav_msgs/msg/Odometry built with rosbags types, as a robot would publish it."""
    t = ts.types
    stamp = t["builtin_interfaces/msg/Time"](sec=STAMP_NS // S, nanosec=STAMP_NS % S)
    header = (t["std_msgs/msg/Header"](seq=11, stamp=stamp, frame_id=frame) if ros1
              else t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame))
    q = t["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=math.sin(yaw / 2) * quat_scale, w=math.cos(yaw / 2) * quat_scale)
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                                       orientation=q)
    cov = np.diag(np.asarray(cov_diag, dtype=np.float64)).reshape(36)
    cov[1] = cov[6] = 0.005  # x-y correlation
    vec = t["geometry_msgs/msg/Vector3"]
    twist = t["geometry_msgs/msg/Twist"](linear=vec(x=vx, y=vy, z=0.0),
                                         angular=vec(x=0.0, y=0.0, z=wz))
    return t["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id="base_footprint",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist,
                                                          covariance=np.zeros(36)),
    )


def test_topic_keys() -> None:
    assert ros2.ros2dds_key("/laser_2d_correct_pose") == "laser_2d_correct_pose"
    assert ros2.ros2dds_key("initialpose", "/robot1") == "robot1/initialpose"
    assert ros2.ros2dds_key("/hsrb/odom", "robot1/") == "robot1/hsrb/odom"
    assert ros2.ros2dds_key("/odom", "/") == "odom"
    for bad in ("", "/", "a//b", "odom*"):
        with pytest.raises(ValueError):
            ros2.ros2dds_key(bad)
    # zenoh-plugin-ros1: <hex(datatype)>/<md5>/<topic>; md5 is ROS 1's well-known one
    key = ros2.ros1_key("/laser_2d_correct_pose", PWCS)
    hex_type, md5, topic = key.split("/")
    assert bytes.fromhex(hex_type).decode() == "geometry_msgs/PoseWithCovarianceStamped"
    assert md5 == "953b798c0f514ff060a53a3498ce6246"
    assert topic == "laser_2d_correct_pose"
    assert ros2.ros1_key_pattern("/hsrb/odom") == "*/*/hsrb/odom"
    hsr = ros2.RosTopics.hsr()
    assert (hsr.odometry_key(), hsr.correction_key(), hsr.localization_key()) == (
        "switched_odom", "laser_2d_correct_pose", "global_pose")
    assert ros2.RosTopics.nav2(namespace="tb3").correction_key() == "tb3/initialpose"
    assert ros2.RosTopics.hsr(ros1=True).odometry_key() == "*/*/hsrb/odom"


def test_correction_cdr_is_a_pose_with_covariance_stamped() -> None:
    c = correction()
    payload = ros2.serialize_correction(c)
    assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation header
    msg = ros2.typestore().deserialize_cdr(payload, PWCS)
    assert msg.__msgtype__ == PWCS
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_123, 456_789_012)
    assert msg.header.frame_id == "map"
    p = msg.pose.pose
    assert (p.position.x, p.position.y, p.position.z) == (1.25, -2.5, 0.0)
    q = p.orientation
    assert q.x == 0.0 and q.y == 0.0
    assert math.hypot(q.z, q.w) == pytest.approx(1.0)
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(2.9)
    cov6 = msg.pose.covariance.reshape(6, 6)
    idx = [0, 1, 5]
    np.testing.assert_allclose(cov6[np.ix_(idx, idx)], c.covariance)
    others = np.delete(np.delete(cov6, idx, 0), idx, 1)
    assert np.all(others == 0.0) and np.all(cov6[2:5, :] == 0.0)
    np.testing.assert_allclose(cov6, cov6.T)


def test_correction_ros1_serialization() -> None:
    c = correction(seq=42, kind="initialization")
    payload = ros2.serialize_correction(c, ros1=True, frame_id="map")
    ts1 = ros2.typestore(ros1=True)
    msg = ts1.deserialize_ros1(payload, PWCS)
    assert msg.header.seq == 42 and msg.header.frame_id == "map"
    assert msg.header.stamp.sec * S + msg.header.stamp.nanosec == STAMP_NS
    assert msg.pose.pose.position.x == 1.25
    assert msg.pose.covariance[35] == pytest.approx(0.03)
    # ROS 1 bytes are not CDR: the two encodings must not be confused
    assert payload != ros2.serialize_correction(c)


@pytest.mark.parametrize("ros1", [False, True])
def test_stamps_past_2038_are_a_conversion_error(ros1: bool) -> None:
    late = PoseCorrection("hsr", 2**31 * S, 0, 0.0, 0.0, 0.0, np.eye(3), "correction")
    with pytest.raises(ros2.RosConversionError):
        ros2.serialize_correction(late, ros1=ros1)


@pytest.mark.parametrize("ros1", [False, True])
def test_odometry_from_rosbags_is_read_correctly(ros1: bool) -> None:
    ts = ros2.typestore(ros1)
    msg = make_odometry(ts, ros1=ros1, frame="/odom")
    payload = (ts.serialize_ros1(msg, "nav_msgs/msg/Odometry") if ros1
               else ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
    sample = ros2.deserialize_odometry(bytes(payload), ros1=ros1)
    assert isinstance(sample, OdometrySample)
    assert sample.stamp_ns == STAMP_NS
    assert (sample.x, sample.y) == (3.5, -1.25)
    assert sample.theta == pytest.approx(-2.8)
    assert (sample.vx, sample.vy, sample.wz) == (0.3, -0.05, 0.2)
    np.testing.assert_allclose(
        sample.covariance, [[0.01, 0.005, 0.0], [0.005, 0.02, 0.0], [0.0, 0.0, 0.04]])
    assert sample.frame_id == "odom"


def test_odometry_edge_cases() -> None:
    ts = ros2.typestore()

    def cdr(**kw):
        return bytes(ts.serialize_cdr(make_odometry(ts, **kw), "nav_msgs/msg/Odometry"))

    # an unnormalised quaternion still gives the right yaw
    assert ros2.deserialize_odometry(cdr(yaw=1.0, quat_scale=3.0)).theta == pytest.approx(1.0)
    # ROS's "unknown covariance" (-1 first) becomes zeros instead of an invalid covariance
    unknown = ros2.deserialize_odometry(cdr(cov_diag=(-1, 0, 0, 0, 0, 0)))
    assert np.all(unknown.covariance == 0.0)
    assert ros2.deserialize_odometry(cdr(frame="hsrb/odom")).frame_id == "hsrb_odom"
    for kw in ({"quat_scale": 0.0}, {"x": math.nan}, {"wz": math.inf}):
        with pytest.raises(ros2.RosConversionError):
            ros2.deserialize_odometry(cdr(**kw))
    for garbage in (b"", b"\x00\x01\x00\x00", cdr()[:40], "odom", None, 12):
        with pytest.raises(ros2.RosConversionError):
            ros2.deserialize_odometry(garbage)
    # a correction's bytes are not odometry
    with pytest.raises(ros2.RosConversionError):
        ros2.deserialize_odometry(ros2.serialize_correction(correction()))


def test_localization_messages() -> None:
    ts = ros2.typestore()
    c = correction(theta=-0.7)
    loc = ros2.deserialize_localization(ros2.serialize_correction(c), PWCS)
    assert (loc.x, loc.y, loc.frame_id, loc.stamp_ns) == (1.25, -2.5, "map", STAMP_NS)
    assert loc.theta == pytest.approx(-0.7)
    np.testing.assert_allclose(loc.covariance, c.covariance)
    t = ts.types
    ps = t["geometry_msgs/msg/PoseStamped"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=5, nanosec=6), frame_id="/map"),
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=-4.0, y=2.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(1.5), w=math.cos(1.5))))
    payload = bytes(ts.serialize_cdr(ps, ros2.POSE_STAMPED_TYPE))
    loc = ros2.deserialize_localization(payload, ros2.POSE_STAMPED_TYPE)
    assert (loc.x, loc.y, loc.frame_id, loc.stamp_ns, loc.covariance) == (
        -4.0, 2.0, "map", 5 * S + 6, None)
    assert loc.theta == pytest.approx(3.0)
    with pytest.raises(ros2.RosConversionError):
        ros2.deserialize_localization(payload, "nav_msgs/msg/Odometry")


@settings(max_examples=80, deadline=None)
@given(
    x=st.floats(-1e4, 1e4), y=st.floats(-1e4, 1e4), theta=st.floats(-math.pi, math.pi),
    sx=st.floats(0.0, 10.0), sy=st.floats(0.0, 10.0), rho=st.floats(-0.99, 0.99),
    stamp_ns=st.integers(0, 2**31 * S - 1), ros1=st.booleans(), seq=st.integers(0, 2**40),
)
def test_property_correction_round_trip(x, y, theta, sx, sy, rho, stamp_ns, ros1, seq) -> None:
    cov = np.array([[sx * sx, rho * sx * sy, 0.0], [rho * sx * sy, sy * sy, 0.0],
                    [0.0, 0.0, 0.01]])
    c = PoseCorrection("hsr", stamp_ns, seq, x, y, theta, cov, "correction")
    loc = ros2.deserialize_localization(ros2.serialize_correction(c, ros1=ros1), PWCS, ros1=ros1)
    assert (loc.x, loc.y, loc.stamp_ns) == (x, y, stamp_ns)
    assert abs(angle_diff(loc.theta, theta)) < 1e-9
    np.testing.assert_allclose(loc.covariance, cov, rtol=1e-12, atol=1e-15)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=400))
def test_property_any_bytes_give_a_sample_or_a_conversion_error(payload: bytes) -> None:
    for ros1 in (False, True):
        try:
            sample = ros2.deserialize_odometry(payload, ros1=ros1)
        except ros2.RosConversionError:
            continue
        assert math.isfinite(sample.x) and math.isfinite(sample.theta)
