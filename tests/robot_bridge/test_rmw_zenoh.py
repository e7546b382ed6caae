"""The rmw_zenoh adapter and its ``--adapter`` plug-in: two real Zenoh sessions on loopback where
one plays the robot's rmw_zenoh nodes. The robot side is written here from the documented
layout (struct, not the wire module's codec) and drops samples without a valid attachment, as
rmw_zenoh's subscription callback does. The wire codec itself: test_rmw_zenoh_wire.py."""

from __future__ import annotations

import argparse
import dataclasses
import math
import secrets
import struct
import time

import numpy as np
import pytest

from protocol.errors import UsageError
from protocol.messages import PoseCorrection, PoseEstimate
from robot_bridge.adapters import rmw_zenoh as rz
from robot_bridge.adapters import rmw_zenoh_wire as wire
from robot_bridge.adapters import ros2
from robot_bridge.adapters.base import MapToOdom
from robot_bridge.bridge import BridgeConfig, RobotBridge
from tests.conftest import wait_until
from tests.robot_bridge.test_rmw_zenoh_wire import HASHES
from tests.robot_bridge.test_ros2_cdr import make_odometry

pytest.importorskip("rosbags")

S = 1_000_000_000
PWCS = ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE
ODOM = ros2.ODOMETRY_TYPE


# --------------------------------------------------------------------------------------------
# the bridge's choices: domain id, QoS of its entities
# --------------------------------------------------------------------------------------------


def test_qos_the_bridges_entities_announce() -> None:
    qos_to = wire.qos_to_keyexpr
    adapt = wire.adapt_qos
    assert qos_to(adapt(rz.CORRECTION_QOS)) == "::2,:,:,:,,"
    assert qos_to(rz.TF_QOS) == "::,100:,:,:,,"
    assert qos_to(rz.POSE_OUTPUT_QOS) == "::,10:,:,:,,"
    assert qos_to(rz.SUBSCRIPTION_QOS) == "2::,10:,:,:,,"
    # how rmw_zenoh declares the Zenoh publisher: (reliable, congestion control BLOCK)
    assert wire.zenoh_publication_mode(adapt(rz.CORRECTION_QOS)) == (True, True)
    assert wire.zenoh_publication_mode(rz.POSE_OUTPUT_QOS) == (True, False)


def test_domain_id_from_flag_or_environment() -> None:
    assert rz.resolve_domain_id(None, {}) == 0
    assert rz.resolve_domain_id(None, {"ROS_DOMAIN_ID": " 42 "}) == 42
    assert rz.resolve_domain_id(None, {"ROS_DOMAIN_ID": ""}) == 0
    assert rz.resolve_domain_id(7, {"ROS_DOMAIN_ID": "42"}) == 7
    for value, env in ((None, {"ROS_DOMAIN_ID": "abc"}), (None, {"ROS_DOMAIN_ID": "-1"}),
                       (-3, {})):
        with pytest.raises(UsageError):
            rz.resolve_domain_id(value, env)


# --------------------------------------------------------------------------------------------
# the robot side, as rmw_zenoh nodes behave (written from the layout, not with the module)
# --------------------------------------------------------------------------------------------


def _hashed_key(domain_id: int, topic: str, ros_type: str) -> str:
    package, kind, name = ros_type.split("/")
    return f"{domain_id}/{topic.strip('/')}/{package}::{kind}::dds_::{name}_/{HASHES[ros_type]}"


class RobotPublisher:
    """An rmw_zenoh publisher: CDR payload plus the 33-byte attachment, sequence from 1."""

    def __init__(self, session, key: str) -> None:
        self.pub = session.declare_publisher(key)
        self.gid = secrets.token_bytes(16)
        self.seq = 0

    def put(self, payload: bytes, *, attachment: bool = True, seq_step: int = 1) -> None:
        if attachment:
            self.seq += seq_step
            att = struct.pack("<qqB16s", self.seq, time.time_ns(), 16, self.gid)
            self.pub.put(payload, attachment=att)
        else:
            self.pub.put(payload)


class RobotSubscription:
    """An rmw_zenoh subscription: samples without a valid attachment are dropped (logged as
    "Unable to obtain attachment" there); what is kept is (attachment fields, payload)."""

    def __init__(self, zenoh, session, key: str) -> None:
        self.sub = session.declare_subscriber(key, zenoh.handlers.FifoChannel(256))
        self.dropped = 0

    def take(self) -> list[tuple[int, int, bytes, bytes]]:
        out = []
        while (sample := self.sub.try_recv()) is not None:
            att = sample.attachment
            raw = att.to_bytes() if att is not None else b""
            if len(raw) < 33 or raw[16] != 16:
                self.dropped += 1
                continue
            seq, stamp = struct.unpack_from("<qq", raw)
            out.append((seq, stamp, raw[17:33], sample.payload.to_bytes()))
        return out


def _odom_cdr(ts, stamp_ns: int, x: float, vx: float = 0.0) -> bytes:
    msg = make_odometry(ts, x=x, y=1.0, yaw=0.5, vx=vx, vy=0.0, wz=0.0)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, S)
    return bytes(ts.serialize_cdr(msg, ODOM))


def _pose_stamped_cdr(ts, stamp_ns: int, x: float, y: float) -> bytes:
    t = ts.types
    sec, nanosec = divmod(stamp_ns, S)
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
        sec=sec, nanosec=nanosec), frame_id="map")
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    return bytes(ts.serialize_cdr(t[ros2.POSE_STAMPED_TYPE](header=header, pose=pose),
                                  ros2.POSE_STAMPED_TYPE))


def _collect(reader, n: int, timeout_s: float = 5.0) -> list:
    got: list = []
    wait_until(lambda: len(got.extend(reader()) or got) >= n, timeout_s=timeout_s)
    return got


@pytest.mark.parametrize(("domain_id", "namespace"), [(0, ""), (7, "robot1")])
def test_odometry_published_the_rmw_zenoh_way_reaches_the_adapter(
        zenoh_pair, domain_id, namespace) -> None:
    bridge_side, robot_side, _ = zenoh_pair
    adapter = rz.RmwZenohAdapter(bridge_side, ros2.RosTopics.hsr(namespace=namespace),
                                 domain_id=domain_id)
    prefix = f"/{namespace}" if namespace else ""
    odom = RobotPublisher(robot_side, _hashed_key(domain_id, f"{prefix}/switched_odom", ODOM))
    loc = RobotPublisher(robot_side, _hashed_key(domain_id, f"{prefix}/global_pose",
                                                 ros2.POSE_STAMPED_TYPE))
    other_domain = RobotPublisher(
        robot_side, _hashed_key(domain_id + 1, f"{prefix}/switched_odom", ODOM))
    old_hash = robot_side.declare_publisher(  # a Humble rmw_zenoh key: no type hash
        f"{domain_id}/{prefix.strip('/') + '/' if prefix else ''}switched_odom/"
        "nav_msgs::msg::dds_::Odometry_/TypeHashNotSupported")
    ts = ros2.typestore()
    t0 = 1_700_000_000 * S
    try:
        # garbage until the route is up: counted, dropped, not raised
        def garbage_counted() -> bool:
            odom.put(b"\x00\x01garbage")
            return adapter.read_odometry() == [] and adapter.counters.get("invalid_odometry", 0) > 0

        assert wait_until(garbage_counted)
        for i in range(5):
            other_domain.put(_odom_cdr(ts, t0, x=99.0))
            old_hash.put(_odom_cdr(ts, t0, x=98.0))
            odom.put(_odom_cdr(ts, t0 + i * S // 50, x=0.1 * i, vx=0.25))
        got = _collect(adapter.read_odometry, 5)
        assert [s.stamp_ns for s in got] == [t0 + i * S // 50 for i in range(5)]
        assert got[3].x == pytest.approx(0.3) and got[3].vx == 0.25
        assert got[3].theta == pytest.approx(0.5)
        assert adapter.counters.get("missing_attachment", 0) == 0
        assert adapter.counters.get("messages_lost", 0) == 0

        # a sample without attachment is still read (and counted); a malformed one too
        odom.put(_odom_cdr(ts, t0 + S, x=1.0), attachment=False)
        odom.pub.put(_odom_cdr(ts, t0 + 2 * S, x=2.0), attachment=b"\x01\x02")
        odom.put(_odom_cdr(ts, t0 + 3 * S, x=3.0), seq_step=4)  # three lost on the way
        got = _collect(adapter.read_odometry, 3)
        assert [s.x for s in got] == [1.0, 2.0, 3.0]
        assert adapter.counters["missing_attachment"] == 1
        assert adapter.counters["invalid_attachment"] == 1
        assert adapter.counters["messages_lost"] == 3

        assert wait_until(lambda: (loc.put(_pose_stamped_cdr(ts, t0, 4.0, -2.0)) or True)
                          and adapter.read_localization() is not None)
        pose = adapter.read_localization()
        assert (pose.x, pose.y, pose.stamp_ns) == (4.0, -2.0, t0)
        loc.put(b"garbage")
        assert wait_until(lambda: adapter.read_localization() is not None
                          and adapter.counters.get("invalid_localization", 0) == 1)
    finally:
        adapter.close()
    assert adapter.read_odometry() == []


def test_corrections_and_pose_outputs_carry_the_rmw_attachment(zenoh_pair) -> None:
    zenoh = pytest.importorskip("zenoh")
    bridge_side, robot_side, _ = zenoh_pair
    topics = dataclasses.replace(ros2.RosTopics.nav2(), map_frame="lab_map")
    adapter = rz.RmwZenohAdapter(bridge_side, topics, domain_id=3)
    subs = {
        "correction": RobotSubscription(zenoh, robot_side, _hashed_key(3, "/initialpose", PWCS)),
        "fused": RobotSubscription(zenoh, robot_side, _hashed_key(3, "/smartedge/pose", PWCS)),
        "cameras": RobotSubscription(
            zenoh, robot_side, _hashed_key(3, "/smartedge/camera_pose", PWCS)),
        "tf": RobotSubscription(zenoh, robot_side, _hashed_key(3, "/tf", ros2.TF_MESSAGE_TYPE)),
    }
    ts = ros2.typestore()
    t0 = 1_700_000_000 * S
    cov = np.diag([0.01, 0.02, 0.03])
    correction = PoseCorrection("tb3", t0, 4, 2.5, -1.5, -3.0, cov, "initialization", 0.0, 0.0)
    estimate = PoseEstimate("tb3", t0 + 7, 9, 1.0, 2.0, 0.25, cov, "cameras", ("cam_a",))
    transform = MapToOdom(t0 + 9, 0.5, -0.25, 0.1, parent_frame="lab_map")
    sends = {
        "correction": lambda: adapter.apply_correction(correction),
        "fused": lambda: adapter.publish_pose(estimate, "fused"),
        "cameras": lambda: adapter.publish_pose(estimate, "cameras"),
        "tf": lambda: adapter.publish_transform(transform),
    }
    try:
        before = time.time_ns()
        # the first puts may go out before the robot side's subscriptions are known
        for what, send in sends.items():
            assert wait_until(lambda send=send, what=what: send() and bool(subs[what].take()))
        wait_until(lambda: False, timeout_s=0.2)  # what the warm-up left in flight
        for sub in subs.values():
            sub.take()
        for send in sends.values():
            assert send() and send()
        after = time.time_ns()
        gids = set()
        for what, sub in subs.items():
            got = _collect(sub.take, 2)
            assert len(got) == 2, what
            (seq1, stamp1, gid1, payload), (seq2, _, gid2, _) = got
            assert seq2 == seq1 + 1 and seq1 >= 2  # one publisher, sequence from 1
            assert gid1 == gid2 and gid1 not in gids
            gids.add(gid1)
            assert before <= stamp1 <= after
            assert payload[:4] == b"\x00\x01\x00\x00"  # CDR, little endian encapsulation
            if what == "tf":
                msg = ts.deserialize_cdr(payload, ros2.TF_MESSAGE_TYPE)
                tf = msg.transforms[0]
                assert (tf.header.frame_id, tf.child_frame_id) == ("lab_map", "odom")
                assert tf.transform.translation.x == 0.5
            else:
                msg = ts.deserialize_cdr(payload, PWCS)
                assert msg.header.frame_id == "lab_map"
                stamp = msg.header.stamp.sec * S + msg.header.stamp.nanosec
                assert stamp == (t0 if what == "correction" else t0 + 7)
                q = msg.pose.pose.orientation
                assert 2 * math.atan2(q.z, q.w) == pytest.approx(
                    -3.0 if what == "correction" else 0.25)
            assert sub.dropped == 0
        assert adapter.counters["corrections_published"] >= 3
        assert adapter.counters["tf_published"] >= 3
    finally:
        adapter.close()
    assert not adapter.apply_correction(correction) and not adapter.publish_pose(estimate)


def test_liveliness_tokens_make_the_bridge_visible(zenoh_pair) -> None:
    zenoh = pytest.importorskip("zenoh")
    bridge_side, robot_side, _ = zenoh_pair
    events = robot_side.liveliness().declare_subscriber(
        "@ros2_lv/5/**", zenoh.handlers.FifoChannel(64), history=True)
    adapter = rz.RmwZenohAdapter(bridge_side, ros2.RosTopics.hsr(namespace="robot1"),
                                 domain_id=5, node_name="site_bridge")
    zid = str(bridge_side.info.zid())
    try:
        def visible() -> set[str]:
            return {str(r.ok.key_expr) for r in robot_side.liveliness().get("@ros2_lv/5/**")
                    if r.ok is not None}

        assert wait_until(lambda: len(visible()) == 4)
        tokens = {wire.parse_liveliness_token(k) for k in visible()}  # as the graph cache does
        assert {t.zid for t in tokens} == {zid} and {t.domain_id for t in tokens} == {5}
        assert {(t.node_name, t.namespace, t.enclave) for t in tokens} == {
            ("site_bridge", "/robot1", "/")}
        assert len({t.node_id for t in tokens}) == 1
        assert len({t.entity_id for t in tokens}) == 4
        # what `ros2 topic list -t` would list for the bridge's node
        assert {(t.kind, t.topic, t.ros_type, t.type_hash) for t in tokens} == {
            ("NN", None, None, None),
            ("MS", "/robot1/switched_odom", "nav_msgs::msg::dds_::Odometry_", HASHES[ODOM]),
            ("MS", "/robot1/global_pose", "geometry_msgs::msg::dds_::PoseStamped_",
             HASHES[ros2.POSE_STAMPED_TYPE]),
            ("MP", "/robot1/laser_2d_correct_pose",
             "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_", HASHES[PWCS]),
        }
        node = next(t for t in tokens if t.kind == wire.NODE)
        assert (f"@ros2_lv/5/{zid}/{node.node_id}/{node.node_id}/NN/%/%robot1/site_bridge"
                in visible())
        # the pose output appears with its first message
        adapter.publish_pose(PoseEstimate("r", 1, 1, 0.0, 0.0, 0.0, np.eye(3), "cameras", ()))
        assert wait_until(lambda: len(visible()) == 5)
        pose_token = next(wire.parse_liveliness_token(k) for k in visible()
                          if "smartedge" in k)
        assert pose_token.topic == "/robot1/smartedge/pose" and pose_token.kind == "MP"
        assert pose_token.qos == rz.POSE_OUTPUT_QOS
        assert sorted(adapter.token_keys()) == sorted(visible())
    finally:
        adapter.close()
    assert wait_until(lambda: not {str(r.ok.key_expr) for r in
                                   robot_side.liveliness().get("@ros2_lv/5/**") if r.ok})
    kinds: list = []

    def all_deleted() -> bool:
        while (sample := events.try_recv()) is not None:
            kinds.append(sample.kind)
        return kinds.count(zenoh.SampleKind.DELETE) == 5

    assert wait_until(all_deleted)
    assert kinds.count(zenoh.SampleKind.PUT) == 5
    events.undeclare()


def test_bridge_corrects_a_static_robot_over_rmw_zenoh(zenoh_pair) -> None:
    """Odometry the rmw_zenoh way reaches the bridge; the robot stops 30 cm off; exactly one
    correction reaches AMCL's ``/initialpose``, with a valid attachment."""
    zenoh = pytest.importorskip("zenoh")
    bridge_side, robot_side, _ = zenoh_pair
    adapter = rz.RmwZenohAdapter(bridge_side, ros2.RosTopics.nav2())
    bridge = RobotBridge(BridgeConfig(robot_id="tb3"))
    initialpose = RobotSubscription(zenoh, robot_side, _hashed_key(0, "/initialpose", PWCS))
    odom = RobotPublisher(robot_side, _hashed_key(0, "/odom", ODOM))
    amcl = RobotPublisher(robot_side, _hashed_key(0, "/amcl_pose", PWCS))
    ts = ros2.typestore()
    t0 = 1_700_000_000 * S
    try:
        assert wait_until(lambda: (odom.put(_odom_cdr(ts, t0, 0.0, 0.3)) or True)
                          and len(adapter.read_odometry()) > 0)
        sent, t = [], t0
        for i in range(150):  # 50 Hz: 1 s driving, 2 s stopped
            t += S // 50
            moving = i < 50
            odom.put(_odom_cdr(ts, t, x=min(i, 50) * 0.006, vx=0.3 if moving else 0.0))
            if i % 10 == 0:
                loc = PoseCorrection("tb3", t, 0, min(i, 50) * 0.006 + 0.3, 1.0, 0.5,
                                     np.eye(3) * 1e-3, "correction")
                amcl.put(ros2.serialize_correction(loc))
            if not moving and i % 5 == 0:
                bridge.on_pose_estimate(PoseEstimate(
                    "tb3", t, i, 0.3, 1.0, 0.5, np.eye(3) * 1e-4, "cameras", ("cam_a",)), t)
            if i % 5 == 4:
                wait_until(lambda: False, timeout_s=0.01)  # let zenoh deliver
                sent.extend(bridge.pump(adapter, t).corrections)
        assert len(sent) == 1, bridge.counters
        assert sent[0].offset_m == pytest.approx(0.3, abs=0.01)
        got = _collect(initialpose.take, 1)
        assert len(got) == 1 and got[0][0] == 1 and initialpose.dropped == 0
        msg = ts.deserialize_cdr(got[0][3], PWCS)
        assert msg.pose.pose.position.x == pytest.approx(0.3)
        assert adapter.counters.get("missing_attachment", 0) == 0
    finally:
        adapter.close()


# --------------------------------------------------------------------------------------------
# the --adapter plug-in
# --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    from robot_bridge.adapters.ros_plugin import ROS_ADAPTERS

    parser = argparse.ArgumentParser()
    parser.add_argument("--adapter", default="rmw_zenoh")
    ROS_ADAPTERS.add_arguments(parser)  # both plug-ins' groups go into one parser
    rz.RMW_ZENOH_ADAPTER.add_arguments(parser)
    return parser


def test_plugin_options_and_build(zenoh_pair, example_site, monkeypatch) -> None:
    bridge_side, _, _ = zenoh_pair
    site = dataclasses.replace(example_site, world_frame="lab_map")
    monkeypatch.setenv("ROS_DOMAIN_ID", "12")
    args = _parser().parse_args(["--robot-profile", "nav2", "--ros-namespace", "robot1",
                                 "--odom-topic", "/wheel/odom", "--ros-node-name", "edge"])
    adapter = rz.RMW_ZENOH_ADAPTER.build(args, site).factory(bridge_side)
    try:
        assert isinstance(adapter, rz.RmwZenohAdapter)
        assert (adapter.domain_id, adapter.node_name, adapter.namespace) == (12, "edge", "/robot1")
        assert adapter.topics.map_frame == "lab_map"
        keys = adapter.token_keys()
        assert any("/MS/%/%robot1/edge/%wheel%odom/" in k for k in keys)
        assert any("/MP/%/%robot1/edge/%robot1%initialpose/" in k for k in keys)
    finally:
        adapter.close()
    args = _parser().parse_args(["--ros-domain-id", "3", "--rmw-zenoh-attachment", "keyed"])
    adapter = rz.RMW_ZENOH_ADAPTER.build(args, site).factory(bridge_side)
    try:
        assert adapter.domain_id == 3 and adapter.topics.correction_topic == "laser_2d_correct_pose"
        assert adapter._encode is wire.encode_keyed_attachment
    finally:
        adapter.close()
    with pytest.raises(UsageError):
        rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args([]), None)
    with pytest.raises(UsageError):
        rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args(["--ros-domain-id", "-1"]), site)
    monkeypatch.setenv("ROS_DOMAIN_ID", "robot")
    with pytest.raises(UsageError):
        rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args([]), site)
    monkeypatch.delenv("ROS_DOMAIN_ID")
    with pytest.raises(ValueError):
        rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args(["--odom-topic", "bad topic"]), site)


def test_adapter_rejects_ros1_and_bad_names(zenoh_pair) -> None:
    bridge_side, _, _ = zenoh_pair
    for kwargs in ({"topics": ros2.RosTopics.hsr(ros1=True)},
                   {"topics": ros2.RosTopics(odometry_topic="odom*")},
                   {"attachment_format": "xml"}, {"domain_id": -1},
                   {"node_name": "two words"}):
        with pytest.raises(ValueError):
            rz.RmwZenohAdapter(bridge_side, **kwargs)


def test_plugin_reads_the_site_files_ros_section(zenoh_pair, tmp_path, example_site_path,
                                                 monkeypatch) -> None:
    """Topics, namespace and domain id come from the site file's ``ros`` section;
    ``$ROS_DOMAIN_ID`` and the command line override it."""
    from core.site import load_site

    bridge_side, _, _ = zenoh_pair
    path = tmp_path / "site.yaml"
    path.write_text(example_site_path.read_text() + "\nros: {profile: nav2, domain_id: 7, "
                    "odometry_topic: /wheel/odom, pose_topic: /lab/pose}\n")
    site = load_site(path)
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    adapter = rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args([]), site).factory(bridge_side)
    try:
        assert adapter.domain_id == 7
        assert adapter.topics.correction_topic == "initialpose"
        assert adapter.topics.odometry_topic == "/wheel/odom"
        assert adapter.topics.pose_topic == "/lab/pose"
        assert adapter.topics.map_frame == site.world_frame
    finally:
        adapter.close()
    monkeypatch.setenv("ROS_DOMAIN_ID", "9")
    adapter = rz.RMW_ZENOH_ADAPTER.build(_parser().parse_args([]), site).factory(bridge_side)
    try:
        assert adapter.domain_id == 9
    finally:
        adapter.close()
    args = _parser().parse_args(["--ros-domain-id", "4", "--robot-profile", "hsr"])
    adapter = rz.RMW_ZENOH_ADAPTER.build(args, site).factory(bridge_side)
    try:
        assert adapter.domain_id == 4
        assert adapter.topics.correction_topic == "laser_2d_correct_pose"
    finally:
        adapter.close()
