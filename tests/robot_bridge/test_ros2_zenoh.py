"""The ROS adapter over two real Zenoh sessions on loopback: one plays the robot's
zenoh-bridge-ros2dds (rosbags-made CDR on the mapped keys), the other runs adapter + bridge."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import PoseCorrection, PoseEstimate
from robot_bridge.adapters import ros2
from robot_bridge.bridge import BridgeConfig, RobotBridge
from tests.conftest import wait_until
from tests.robot_bridge.test_ros2_cdr import make_odometry

zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags")

S = 1_000_000_000
PWCS = ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE


def _odom_cdr(ts, stamp_ns: int, x: float, vx: float, yaw: float = 0.5) -> bytes:
    msg = make_odometry(ts, x=x, y=1.0, yaw=yaw, vx=vx, vy=0.0, wz=0.0)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, S)
    return bytes(ts.serialize_cdr(msg, "nav_msgs/msg/Odometry"))


def _localization_cdr(stamp_ns: int, x: float, y: float, theta: float) -> bytes:
    # what AMCL publishes on amcl_pose: the same message type as a correction
    loc = PoseCorrection("hsr", stamp_ns, 0, x, y, theta, np.eye(3) * 1e-3, "correction")
    return ros2.serialize_correction(loc)


@pytest.mark.parametrize("namespace", ["", "robot1"])
def test_adapter_reads_odometry_and_publishes_corrections(zenoh_pair, namespace) -> None:
    bridge_side, robot_side, _ = zenoh_pair
    topics = ros2.RosTopics.hsr(namespace=namespace)
    adapter = ros2.RosZenohAdapter(bridge_side, topics)
    prefix = f"{namespace}/" if namespace else ""
    corrections = robot_side.declare_subscriber(
        f"{prefix}laser_2d_correct_pose", zenoh.handlers.FifoChannel(16))
    odom_pub = robot_side.declare_publisher(f"{prefix}switched_odom")
    ts = ros2.typestore()
    t0 = 1_700_000_000 * S
    try:
        # garbage on the odometry key (until the route is up): counted, dropped, not raised
        def garbage_counted() -> bool:
            odom_pub.put(b"\x00\x01garbage")
            return adapter.read_odometry() == [] and adapter.counters.get("invalid_odometry", 0) > 0

        assert wait_until(garbage_counted)
        got = []
        for i in range(5):
            odom_pub.put(_odom_cdr(ts, t0 + i * S // 50, x=0.1 * i, vx=0.25))
        assert wait_until(lambda: len(got.extend(adapter.read_odometry()) or got) >= 5)
        assert [s.stamp_ns for s in got] == [t0 + i * S // 50 for i in range(5)]
        assert got[3].x == pytest.approx(0.3) and got[3].y == 1.0
        assert got[3].theta == pytest.approx(0.5) and got[3].vx == 0.25

        c = PoseCorrection("hsr", t0 + 123_456_789, 4, 2.5, -1.5, -3.0,
                           np.diag([0.01, 0.01, 0.02]), "initialization", 0.0, 0.0)
        # the first puts may go out before the robot side's subscription is known
        assert wait_until(lambda: adapter.apply_correction(c)
                          and corrections.try_recv(), timeout_s=5.0)
        while corrections.try_recv() is not None:
            pass
        assert adapter.apply_correction(c)
        sample = corrections.recv()
        msg = ts.deserialize_cdr(sample.payload.to_bytes(), PWCS)
        assert msg.__msgtype__ == PWCS
        assert msg.header.frame_id == "map"
        assert msg.header.stamp.sec * S + msg.header.stamp.nanosec == t0 + 123_456_789
        assert (msg.pose.pose.position.x, msg.pose.pose.position.y) == (2.5, -1.5)
        q = msg.pose.pose.orientation
        assert 2 * math.atan2(q.z, q.w) == pytest.approx(-3.0)
        assert msg.pose.covariance[0] == 0.01 and msg.pose.covariance[35] == 0.02
    finally:
        adapter.close()
    assert adapter.read_odometry() == [] and not adapter.apply_correction(c)


def test_bridge_over_zenoh_corrects_a_static_ros_robot(zenoh_pair) -> None:
    """Robot drives then stops; its AMCL pose is 30 cm off; a camera estimate arrives during
    the stop: exactly one PoseWithCovarianceStamped reaches `initialpose`, while stopped."""
    bridge_side, robot_side, _ = zenoh_pair
    adapter = ros2.RosZenohAdapter(bridge_side, ros2.RosTopics.nav2())
    bridge = RobotBridge(BridgeConfig(robot_id="tb3"))
    initialpose = robot_side.declare_subscriber("initialpose", zenoh.handlers.FifoChannel(16))
    odom_pub = robot_side.declare_publisher("odom")
    amcl_pub = robot_side.declare_publisher("amcl_pose")
    ts = ros2.typestore()
    t0 = 1_700_000_000 * S
    try:
        # wait until the route carries data
        assert wait_until(lambda: (odom_pub.put(_odom_cdr(ts, t0, 0.0, 0.3)) or True)
                          and len(adapter.read_odometry()) > 0)
        published_odometry = 0
        sent_at = []
        t = t0
        for i in range(200):  # 4 s at 50 Hz: 1 s driving, 3 s stopped
            t += S // 50
            moving = i < 50
            odom_pub.put(_odom_cdr(ts, t, x=min(i, 50) * 0.006, vx=0.3 if moving else 0.0))
            if i % 10 == 0:
                amcl_pub.put(_localization_cdr(t, min(i, 50) * 0.006 + 0.3, 1.0, 0.5))
            if not moving and i % 5 == 0:
                est_cov = np.diag([1e-4, 1e-4, 1e-4])
                bridge.on_pose_estimate(PoseEstimate(
                    "tb3", t, i, 0.3, 1.0, 0.5, est_cov, "cameras", ("cam_a",)), t)
            if i % 5 == 4:
                wait_until(lambda: False, timeout_s=0.01)  # let zenoh deliver
                out = bridge.pump(adapter, t)
                published_odometry += len(out.odometry)
                sent_at.extend((i, c) for c in out.corrections)
        wait_until(lambda: False, timeout_s=0.1)
        out = bridge.pump(adapter, t)
        published_odometry += len(out.odometry)
        assert published_odometry >= 190  # best-effort transport, but on loopback ~all arrive
        assert len(sent_at) == 1, bridge.counters
        i_sent, c = sent_at[0]
        assert i_sent >= 100 and c.kind == "correction"  # stopped at 50, dwell 1 s
        assert c.offset_m == pytest.approx(0.3, abs=0.01)
        assert wait_until(lambda: bridge.counters.get("corrections_accepted") == 1)
        sample = initialpose.recv()
        msg = ts.deserialize_cdr(sample.payload.to_bytes(), PWCS)
        assert msg.pose.pose.position.x == pytest.approx(0.3)
        assert msg.header.stamp.sec * S + msg.header.stamp.nanosec == c.stamp_ns
        assert initialpose.try_recv() is None
    finally:
        adapter.close()


def test_corrections_carry_the_sites_world_frame(zenoh_pair, example_site) -> None:
    """The ROS adapter the bridge builds stamps corrections with the site file's
    ``world_frame``, not a fixed "map"."""
    import argparse
    import dataclasses

    from robot_bridge.adapters.ros_plugin import ROS_ADAPTERS

    bridge_side, _, _ = zenoh_pair
    site = dataclasses.replace(example_site, world_frame="lab_map")
    args = argparse.Namespace(adapter="ros2", robot_profile="nav2", ros_namespace="",
                              correction_topic=None, odom_topic=None)
    adapter = ROS_ADAPTERS.build(args, site).factory(bridge_side)
    try:
        assert adapter.topics.map_frame == "lab_map"
    finally:
        adapter.close()
