"""The continuous pose output: selection and rate (PoseOutput), the map -> odom transform, the
site file sections, and the ROS topic over a real Zenoh session, decoded with rosbags."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from core.geometry import se2_compose, se2_inverse, yaw_to_quaternion
from core.site import ClockPolicy
from protocol.errors import ConfigFileError
from protocol.messages import PoseEstimate
from robot_bridge.adapters.base import MapToOdom, OdometrySample
from robot_bridge.adapters.sim import SimRobotAdapter
from robot_bridge.bridge import BridgeConfig, RobotBridge
from robot_bridge.pose_output import PoseOutput, PoseOutputConfig
from tests.conftest import wait_until

S = 1_000_000_000
T0 = 1_700_000_000 * S
COV = np.array([[4e-4, 1e-5, 2e-6], [1e-5, 9e-4, 3e-6], [2e-6, 3e-6, 2.5e-4]])


def estimate(stamp_ns: int, x: float = 1.0, y: float = 2.0, theta: float = 0.3,
             source: str = "fused", seq: int = 0, robot_id: str = "hsr") -> PoseEstimate:
    return PoseEstimate(robot_id, stamp_ns, seq, x, y, theta, COV, source, ("cam_a",),
                        frame_id="map")


def test_rate_newest_once_and_fresh_only() -> None:
    out = PoseOutput(PoseOutputConfig(rate_hz=5.0), clock=ClockPolicy(max_age_ms=500.0))
    published = []
    # estimates at 20 Hz for 2 s, the output asked at 100 Hz: 5 Hz of the newest, each once
    for i in range(200):
        now = T0 + i * S // 100
        if i % 5 == 0:
            out.on_estimate(estimate(now - 30_000_000, seq=i))
        published.extend(out.due(now).poses)
    assert len(published) == 10
    assert all(stream == "fused" for stream, _ in published)
    stamps = [e.stamp_ns for _, e in published]
    assert stamps == sorted(set(stamps))
    # camera-only estimates are not published unless asked for
    out.on_estimate(estimate(T0 + 3 * S, source="cameras"))
    assert out.due(T0 + 3 * S).poses == ()
    # nothing new: nothing again
    assert out.due(T0 + 4 * S).poses == ()
    # a stale estimate (after a stall) is skipped, counted, never sent later
    out.on_estimate(estimate(T0 + 5 * S))
    batch = out.due(T0 + 6 * S)
    assert batch.poses == () and batch.skipped == ("stale_fused",)
    assert out.due(T0 + 7 * S).poses == ()


def test_both_streams_and_off() -> None:
    out = PoseOutput(PoseOutputConfig(rate_hz=10.0, cameras=True))
    out.on_estimate(estimate(T0, source="fused"))
    out.on_estimate(estimate(T0, source="cameras", x=1.5))
    out.on_estimate(estimate(T0, source="robot", x=9.0))  # the robot's own: never echoed
    batch = out.due(T0 + S // 100)
    assert [(s, e.x) for s, e in batch.poses] == [("fused", 1.0), ("cameras", 1.5)]
    off = PoseOutput(PoseOutputConfig(rate_hz=0.0, map_to_odom=True))
    off.on_estimate(estimate(T0))
    assert off.due(T0) == off.due(T0 + S) and not off.due(T0 + S).poses
    with pytest.raises(ValueError, match="rate_hz"):
        PoseOutputConfig(rate_hz=-1.0)
    with pytest.raises(ValueError, match="max_age_ms"):
        ClockPolicy(max_age_ms=float("nan"))


def test_map_to_odom_from_interpolated_odometry() -> None:
    """The robot drives a curve in its drifting odometry frame; map -> odom is a fixed
    offset. From an estimate stamped between two odometry readings the transform comes back."""
    map_T_odom = np.array([3.0, -1.0, 0.7])
    out = PoseOutput(PoseOutputConfig(rate_hz=10.0, map_to_odom=True,
                                      transform_tolerance_s=0.1), world_frame="world")
    odom_poses = {}
    for i in range(100):  # 50 Hz for 2 s: an arc
        t = T0 + i * S // 50
        pose = np.array([0.5 * math.sin(0.4 * i / 50), 0.5 - 0.5 * math.cos(0.4 * i / 50),
                         0.4 * i / 50])
        odom_poses[t] = pose
        out.on_odometry(t, *pose, frame_id="odom_wheel")
    t_est = T0 + 37 * S // 50 + S // 100  # halfway between readings 37 and 38
    mid = 0.5 * (odom_poses[T0 + 37 * S // 50] + odom_poses[T0 + 38 * S // 50])
    truth = se2_compose(map_T_odom, mid)
    out.on_estimate(estimate(t_est, *truth))
    now = T0 + 2 * S
    batch = out.due(now)
    tf = batch.transform
    assert isinstance(tf, MapToOdom)
    assert (tf.parent_frame, tf.child_frame) == ("world", "odom_wheel")
    assert tf.stamp_ns == now + S // 10
    # an arc is not a line: linear interpolation errs by well under a millimetre here
    assert np.allclose([tf.x, tf.y, tf.theta], map_T_odom, atol=1e-3)
    # republished at the rate with fresh stamps while no new estimate comes (as AMCL does)
    again = out.due(now + S // 10).transform
    assert again is not None and again.stamp_ns == now + 2 * S // 10 and again.x == tf.x
    # an estimate far outside the odometry: the transform is kept, the miss counted once
    out.on_estimate(estimate(T0 + 10 * S, *truth))
    batch = out.due(T0 + 10 * S)
    assert batch.skipped == ("map_to_odom_no_odometry",) and batch.transform.x == tf.x
    assert out.due(T0 + 10 * S + S).skipped == ()


def test_odometry_at_refuses_gaps_and_extrapolation() -> None:
    out = PoseOutput(PoseOutputConfig(odometry_match_s=0.2))
    assert out.odometry_at(T0) is None
    out.on_odometry(T0, 0.0, 0.0, 3.1)
    out.on_odometry(T0 + S // 10, 0.1, 0.0, -3.1)  # across the +-pi seam
    mid = out.odometry_at(T0 + S // 20)
    assert mid[0] == pytest.approx(0.05) and abs(mid[2]) == pytest.approx(math.pi, abs=1e-6)
    assert out.odometry_at(T0 - 1) is None
    assert out.odometry_at(T0 + S // 10 + S // 10) is not None  # 0.1 s after the last
    assert out.odometry_at(T0 + S // 10 + S // 2) is None  # 0.5 s after: too far
    out.on_odometry(T0 + 2 * S, 0.2, 0.0, 0.0)  # a 1.9 s gap
    assert out.odometry_at(T0 + S) is None


def test_bridge_feeds_the_output_only_what_it_accepted() -> None:
    bridge = RobotBridge(BridgeConfig(
        "hsr", pose_output=PoseOutputConfig(rate_hz=10.0, cameras=True, map_to_odom=True)))

    class Robot:  # the simulated-robot port, standing still at the origin of odom
        t_s = 0.0

        def stamp_ns(self, t_s: float) -> int:
            return T0 + round(t_s * S)

        def step_to(self, t_s):
            return []

        def localization_pose(self):
            return np.zeros(3)

        def apply_correction(self, pose, stamp_ns):
            return True

    adapter = SimRobotAdapter(Robot())
    for i in range(10):
        bridge.on_robot_odometry(OdometrySample(T0 + i * S // 50, 0.0, 0.0, 0.0), T0 + i * S)
    bridge.on_pose_estimate(estimate(T0 + S // 10, x=2.0, y=1.0, theta=0.5), T0 + S // 10)
    bridge.on_pose_estimate(estimate(T0 + S // 10, source="cameras", x=2.1), T0 + S // 10)
    bridge.on_pose_estimate(estimate(T0 + S // 10, robot_id="other", x=7.0), T0 + S // 10)
    bridge.on_pose_estimate(estimate(T0 + 5 * S, x=8.0), T0 + S // 10)  # from the future
    assert bridge.publish_pose_output(adapter, T0 + S // 5) == 3
    assert adapter.published_poses["fused"].x == 2.0
    assert adapter.published_poses["cameras"].x == 2.1
    tf = adapter.published_transform
    assert (tf.x, tf.y, tf.theta) == pytest.approx((2.0, 1.0, 0.5))
    counters = bridge.counters
    assert counters["pose_output_fused"] == 1 and counters["pose_output_tf"] == 1
    assert counters["future_stamp_estimate"] == 1 and counters["other_robot_estimate"] == 1

    class NoOutput(SimRobotAdapter):
        def publish_pose(self, estimate, stream="fused"):
            raise RuntimeError("broken adapter")

    bridge.on_pose_estimate(estimate(T0 + S // 2, x=2.2), T0 + S // 2)
    assert bridge.publish_pose_output(NoOutput(Robot()), T0 + S) == 1  # the tf still went
    assert bridge.counters["pose_output_fused_failed"] == 1
    assert bridge.counters["adapter_error"] == 1


def test_site_sections_parse_and_errors_name_the_key(tmp_path, example_site_path) -> None:
    from core.site import load_site
    from robot_bridge.adapters.ros_plugin import ros_config, ros_topics

    text = example_site_path.read_text()
    good = tmp_path / "site.yaml"
    good.write_text(text + "\npose_output: {rate_hz: 20, cameras: true, map_to_odom: true}\n"
                    "ros: {profile: nav2, domain_id: 7, pose_topic: /lab/smartedge_pose,\n"
                    "      localization_topic: none}\n")
    site = load_site(good)
    config = BridgeConfig.from_site(site, next(iter(site.robots)))
    assert config.pose_output == PoseOutputConfig(rate_hz=20.0, cameras=True, map_to_odom=True)
    args = argparse.Namespace(adapter="ros2", robot_profile=None, ros_namespace=None,
                              correction_topic=None, odom_topic="wheel/odom")
    ros = ros_config(args, site)
    assert (ros.profile, ros.domain_id) == ("nav2", 7)
    topics = ros_topics(args, site)
    assert topics.correction_topic == "initialpose" and topics.odometry_topic == "wheel/odom"
    assert topics.localization_topic is None and topics.pose_topic == "/lab/smartedge_pose"
    assert topics.map_frame == site.world_frame
    for section, message in [("pose_output: {rate_hz: -2}", "pose_output"),
                             ("pose_output: {rate: 2}", "pose_output.rate"),
                             ("ros: {profile: turtlebot}", "ros"),
                             ("ros: {domain_id: 300}", "ros")]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text + "\n" + section + "\n")
        with pytest.raises(ConfigFileError, match=message) as exc:
            s = load_site(bad)
            BridgeConfig.from_site(s, next(iter(s.robots)))
            ros_config(args, s)
        assert "bad.yaml" in str(exc.value)


def test_ros_pose_topic_decodes_at_the_configured_rate(zenoh_pair) -> None:
    """Over a real Zenoh session: estimates at 15 Hz for 3 s of bridge clock, output at 5 Hz:
    15 PoseWithCovarianceStamped on ``smartedge/pose`` (rosbags decodes them) with the site's
    frame, the estimate's stamp and the REP-103 covariance; the transform on ``tf``."""
    zenoh = pytest.importorskip("zenoh")
    pytest.importorskip("rosbags")
    from robot_bridge.adapters import ros2

    bridge_side, robot_side, _ = zenoh_pair
    topics = ros2.RosConfig(profile="nav2").topics(map_frame="world")
    adapter = ros2.RosZenohAdapter(bridge_side, topics)
    bridge = RobotBridge(BridgeConfig("tb3", world_frame="world", pose_output=PoseOutputConfig(
        rate_hz=5.0, map_to_odom=True)))
    poses = robot_side.declare_subscriber("smartedge/pose", zenoh.handlers.FifoChannel(256))
    tfs = robot_side.declare_subscriber("tf", zenoh.handlers.FifoChannel(256))
    ts = ros2.typestore()
    pwcs = ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE

    def est(stamp_ns: int, seq: int) -> PoseEstimate:
        return PoseEstimate("tb3", stamp_ns, seq, 1.0 + seq * 0.01, 2.0, 0.4, COV, "fused",
                            ("cam_a",), frame_id="world")

    try:
        # warm up the route (the first puts may precede the subscription's arrival)
        bridge.on_pose_estimate(est(T0 - S, 0), T0 - S)
        warm = [T0 - S]

        def route_up() -> bool:
            warm[0] += S
            bridge.on_pose_estimate(est(warm[0], 0), warm[0])
            bridge.publish_pose_output(adapter, warm[0])
            return poses.try_recv() is not None

        assert wait_until(route_up)
        while poses.try_recv() is not None:
            pass
        while tfs.try_recv() is not None:
            pass
        start = warm[0] + S
        sent_stamps = []
        for i in range(45):  # 3 s at 15 Hz
            now = start + i * S // 15
            bridge.on_robot_odometry(OdometrySample(now - S // 30, 0.5, 0.0, 0.0), now)
            bridge.on_robot_odometry(OdometrySample(now, 0.5, 0.0, 0.0), now)
            bridge.on_pose_estimate(est(now - S // 20, i + 1), now)
            before = bridge.counters.get("pose_output_fused", 0)
            bridge.publish_pose_output(adapter, now)
            if bridge.counters.get("pose_output_fused", 0) > before:
                sent_stamps.append(now - S // 20)
        assert len(sent_stamps) == 15  # 5 Hz over 3 s
        msgs: list = []

        def all_arrived() -> bool:
            # (a warm-up message may still have been in flight when the channel was drained:
            # it is left out, and the wait goes on until the 15 sent ones are all here)
            for sample in iter(lambda: poses.try_recv(), None):
                m = ts.deserialize_cdr(sample.payload.to_bytes(), pwcs)
                if m.header.stamp.sec * S + m.header.stamp.nanosec > warm[0]:
                    msgs.append(m)
            return len(msgs) >= 15

        assert wait_until(all_arrived)
        assert [m.header.stamp.sec * S + m.header.stamp.nanosec for m in msgs] == sent_stamps
        m = msgs[-1]
        assert m.__msgtype__ == pwcs and m.header.frame_id == "world"
        cov = np.asarray(m.pose.covariance).reshape(6, 6)
        idx = [0, 1, 5]
        assert np.array_equal(cov[np.ix_(idx, idx)], COV)
        assert cov[2, 2] == cov[3, 3] == cov[4, 4] == ros2.UNOBSERVED_VARIANCE
        q = m.pose.pose.orientation
        assert (q.x, q.y, q.z, q.w) == pytest.approx(yaw_to_quaternion(0.4))
        # map -> odom: the estimate says base at (1.0 + 0.01 seq, 2, 0.4); odometry (0.5, 0, 0)
        tf_samples = []
        # (the first estimate of the run precedes its odometry: 14 transforms)
        assert bridge.counters["pose_output_tf"] == 14
        assert wait_until(lambda: len(tf_samples.extend(
            iter(lambda: tfs.try_recv(), None)) or tf_samples) >= 14)
        wait_until(lambda: False, timeout_s=0.2)  # the last ones
        tf_samples.extend(iter(lambda: tfs.try_recv(), None))
        tf_msg = ts.deserialize_cdr(tf_samples[-1].payload.to_bytes(), ros2.TF_MESSAGE_TYPE)
        (tf,) = tf_msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == ("world", "odom")
        expect = se2_compose(np.array([1.0 + 0.01 * 43, 2.0, 0.4]),
                             se2_inverse(np.array([0.5, 0.0, 0.0])))
        assert (tf.transform.translation.x, tf.transform.translation.y) == pytest.approx(
            tuple(expect[:2]))
    finally:
        adapter.close()
