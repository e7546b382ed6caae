"""The rmw_zenoh wire codec: keys, liveliness tokens, attachment, QoS field and type hashes
against fixtures taken from rmw_zenoh's design document (fixtures/rmw_zenoh_design.json) and
zenoh's own serializer. The adapter that uses them is tested in test_rmw_zenoh.py."""

from __future__ import annotations

import json
import secrets
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot_bridge.adapters import rmw_zenoh_wire as wire
from robot_bridge.adapters import ros2

pytest.importorskip("rosbags")

FIXTURES = json.loads(
    (Path(__file__).parent / "fixtures" / "rmw_zenoh_design.json").read_text())
HASHES = FIXTURES["type_hashes"]
S = 1_000_000_000
PWCS = ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE
ODOM = ros2.ODOMETRY_TYPE


# --------------------------------------------------------------------------------------------
# pure functions against the design document
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("case", FIXTURES["topic_keys"], ids=lambda c: c["key"][:24])
def test_topic_keys_of_the_design_document(case) -> None:
    key = wire.topic_key(case["domain_id"], case["topic"], case["ros_type"], case.get("type_hash"))
    assert key == case["key"]


@pytest.mark.parametrize("case", FIXTURES["liveliness_tokens"], ids=lambda c: c["kind"])
def test_liveliness_tokens_of_the_design_document(case) -> None:
    qos = wire.QosProfile(depth=case["depth"]) if "depth" in case else None
    key = wire.liveliness_token_key(
        case["domain_id"], case["zid"], case["node_id"], case["entity_id"], case["kind"],
        node_name=case["node_name"], topic=case.get("topic"), ros_type=case.get("ros_type"),
        type_hash_=case.get("type_hash"), qos=qos)
    assert key == case["key"]
    token = wire.parse_liveliness_token(key)  # what rmw_zenoh's graph cache reads back
    assert (token.domain_id, token.zid, token.kind, token.node_name) == (
        case["domain_id"], case["zid"], case["kind"], case["node_name"])
    assert token.namespace == "/" and token.enclave == "/"
    if case["kind"] != wire.NODE:
        assert token.topic == case["topic"] and token.qos == wire.QosProfile(depth=case["depth"])
        assert token.ros_type == wire.dds_type_name(case["ros_type"])


@pytest.mark.parametrize("ros_type", sorted(HASHES))
def test_type_hash_and_key_of_each_message_the_bridge_uses(ros_type) -> None:
    assert wire.type_hash(ros_type) == HASHES[ros_type]
    package, _, name = ros_type.split("/")
    assert wire.dds_type_name(ros_type) == f"{package}::msg::dds_::{name}_"
    assert wire.topic_key(3, "/robot1/x", ros_type) == (
        f"3/robot1/x/{package}::msg::dds_::{name}_/{HASHES[ros_type]}")


def test_keys_of_the_hsr_and_nav2_topic_sets() -> None:
    cases = {
        ("switched_odom", ODOM): "0/switched_odom/nav_msgs::msg::dds_::Odometry_/",
        ("laser_2d_correct_pose", PWCS):
            "0/laser_2d_correct_pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/",
        ("global_pose", ros2.POSE_STAMPED_TYPE):
            "0/global_pose/geometry_msgs::msg::dds_::PoseStamped_/",
        ("odom", ODOM): "0/odom/nav_msgs::msg::dds_::Odometry_/",
        ("initialpose", PWCS):
            "0/initialpose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/",
        ("tf", ros2.TF_MESSAGE_TYPE): "0/tf/tf2_msgs::msg::dds_::TFMessage_/",
        ("smartedge/pose", PWCS):
            "0/smartedge/pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/",
    }
    for (topic, ros_type), prefix in cases.items():
        fqn = wire.fully_qualified_name(topic)
        assert wire.topic_key(0, fqn, ros_type) == prefix + HASHES[ros_type]


def test_names_resolve_like_ros() -> None:
    fqn = wire.fully_qualified_name
    assert fqn("switched_odom") == "/switched_odom"
    assert fqn("odom", "robot1") == "/robot1/odom" == fqn("odom", "/robot1/")
    assert fqn("/odom", "robot1") == "/odom"  # absolute names ignore the namespace
    assert fqn("smartedge/pose", "/a/b") == "/a/b/smartedge/pose"
    assert wire.node_namespace("") == wire.node_namespace("/") == "/"
    assert wire.mangle_name("/robot1/odom") == "%robot1%odom"
    assert wire.demangle_name("%robot1%odom") == "/robot1/odom"
    for bad in ("", "/", "a//b", "odom*", "~/odom", "1odom", "od om", "odom/"):
        with pytest.raises(ValueError):
            fqn(bad)
    for bad in ("geometry_msgs/PoseStamped", "a/msg/b/c", "", "a/msg/B*"):
        with pytest.raises(ValueError):
            wire.dds_type_name(bad)
    with pytest.raises(ValueError):
        wire.type_hash("nope_msgs/msg/Nothing")
    with pytest.raises(ValueError):
        wire.topic_key(-1, "/odom", ODOM)


def test_attachment_layout_of_the_design_document() -> None:
    a = FIXTURES["attachment"]
    gid = bytes.fromhex(a["source_gid_hex"])
    data = wire.encode_attachment(a["sequence_number"], a["source_timestamp_ns"], gid)
    assert data.hex() == a["hex"] and len(data) == wire.ATTACHMENT_SIZE == 33
    assert struct.unpack_from("<q", data, 0)[0] == a["sequence_number"]
    assert struct.unpack_from("<q", data, 8)[0] == a["source_timestamp_ns"]
    assert data[16] == 16 and data[17:] == gid
    assert wire.decode_attachment(data) == wire.Attachment(
        a["sequence_number"], a["source_timestamp_ns"], gid)


def test_attachment_is_what_the_zenoh_ext_serializer_writes() -> None:
    """rmw_zenoh serializes (int64, int64, std::array<uint8_t, 16>) with zenoh-ext; zenoh's own
    Python serializer of (Int64, Int64, bytes) is the independent reference for both layouts."""
    ext = pytest.importorskip("zenoh.ext")
    gid = secrets.token_bytes(16)
    for seq, stamp in ((1, 0), (2**63 - 1, -(2**63)), (42, 1_700_000_000 * S)):
        compact = ext.z_serialize((ext.Int64(seq), ext.Int64(stamp), gid)).to_bytes()
        assert wire.encode_attachment(seq, stamp, gid) == compact
        keyed = ext.z_serialize(("sequence_number", ext.Int64(seq), "source_timestamp",
                                 ext.Int64(stamp), "source_gid", gid)).to_bytes()
        assert wire.encode_keyed_attachment(seq, stamp, gid) == keyed and len(keyed) == 77
        assert wire.decode_attachment(keyed) == wire.decode_attachment(compact)


@settings(max_examples=200, deadline=None)
@given(seq=st.integers(-(2**63), 2**63 - 1), stamp=st.integers(-(2**63), 2**63 - 1),
       gid=st.binary(min_size=16, max_size=16), keyed=st.booleans())
def test_attachment_round_trip(seq, stamp, gid, keyed) -> None:
    encode = wire.encode_keyed_attachment if keyed else wire.encode_attachment
    assert wire.decode_attachment(encode(seq, stamp, gid)) == wire.Attachment(seq, stamp, gid)


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=100))
def test_decoding_garbage_raises_only_attachment_error(data) -> None:
    try:
        info = wire.decode_attachment(data)
    except wire.AttachmentError:
        return
    assert len(info.source_gid) == 16 and len(data) >= 33


def test_attachment_rejections() -> None:
    good = wire.encode_attachment(1, 2, bytes(16))
    for bad in (b"", good[:32], good[:16] + b"\x0f" + bytes(16), "text", None):
        with pytest.raises(wire.AttachmentError):
            wire.decode_attachment(bad)
    assert wire.decode_attachment(good + b"extra").sequence_number == 1  # as zenoh-cpp reads it
    for args in ((2**63, 0, bytes(16)), (0, 0, bytes(15)), (True, 0, bytes(16))):
        with pytest.raises(ValueError):
            wire.encode_attachment(*args)


def test_qos_encoding() -> None:
    qos_to = wire.qos_to_keyexpr
    adapt = wire.adapt_qos
    assert qos_to(wire.QosProfile(depth=10)) == "::,10:,:,:,,"  # rclcpp QoS(10)
    system_default = wire.QosProfile(
        wire.Reliability.SYSTEM_DEFAULT, wire.Durability.SYSTEM_DEFAULT,
        wire.History.SYSTEM_DEFAULT, 0, (0, 0), (0, 0), wire.Liveliness.SYSTEM_DEFAULT, (0, 0))
    assert adapt(system_default) == wire.RMW_ZENOH_DEFAULT_QOS
    assert qos_to(adapt(system_default)) == "::,:,:,:,,"
    sensor = wire.QosProfile(wire.Reliability.BEST_EFFORT, wire.Durability.TRANSIENT_LOCAL,
                             wire.History.KEEP_ALL, 5, (1, 500), (0, 0), wire.Liveliness.AUTOMATIC)
    assert qos_to(adapt(sensor)) == "2:1:2,5:1,500:,:,,"
    assert wire.qos_from_keyexpr("2:1:2,5:1,500:,:,,") == adapt(sensor)
    for bad in ("", "::,10:,:,:", "::,10:,:,:,", "9::,:,:,:,,", "::,x:,:,:,,", ":::,:,:,:,,"):
        with pytest.raises(ValueError):
            wire.qos_from_keyexpr(bad)
    # how rmw_zenoh declares the Zenoh publisher: (reliable, congestion control BLOCK)
    assert wire.zenoh_publication_mode(adapt(sensor)) == (False, False)
    reliable_keep_all = wire.QosProfile(wire.Reliability.RELIABLE, history=wire.History.KEEP_ALL)
    assert wire.zenoh_publication_mode(reliable_keep_all) == (True, True)
    assert wire.zenoh_publication_mode(wire.QosProfile(depth=10)) == (True, False)


def test_token_builder_rejections() -> None:
    ok = dict(node_name="n", topic="/odom", ros_type=ODOM)
    wire.liveliness_token_key(0, "ab12", 1, 2, wire.PUBLISHER, **ok)
    for args, kwargs in (
        ((0, "ab12", 1, 2, "XX"), ok),
        ((0, "AB-12", 1, 2, wire.PUBLISHER), ok),
        ((0, "ab12", 1, 2, wire.NODE), {"node_name": "n"}),  # a node's ids are equal
        ((0, "ab12", 1, 2, wire.PUBLISHER), {"node_name": "n"}),  # no topic
        ((0, "ab12", 1, 2, wire.PUBLISHER), {**ok, "node_name": "bad name"}),
        ((0, "ab12", -1, 2, wire.PUBLISHER), ok),
    ):
        with pytest.raises(ValueError):
            wire.liveliness_token_key(*args, **kwargs)
    for bad in ("@ros2_lv/0/ab/0/0/NN/%/%", "@other/0/ab/0/0/NN/%/%/n",
                "@ros2_lv/0/ab/0/0/XX/%/%/n", "@ros2_lv/0/ab/0/1/MP/%/%/n/%odom",
                "@ros2_lv/0/ab/0/0/NN/%//n"):
        with pytest.raises(ValueError):
            wire.parse_liveliness_token(bad)
