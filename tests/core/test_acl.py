"""The generated access control block (core/acl.py): who may put what, the zenoh 1.x schema,
and the table in docs/deployment.md."""

from __future__ import annotations

import dataclasses
import json

import pytest

from core import acl
from protocol import keys
from protocol.errors import ValidationError
from tests.conftest import REPO_ROOT

SITE = "lab"
RMW_CORRECTION = (
    "0/laser_2d_correct_pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_ab")


@pytest.fixture
def block(example_site) -> dict:
    return acl.access_control(example_site)


def _putters(grants: list[acl.Grant], key: str) -> set[str]:
    """Identities whose put grant covers the concrete ``key``."""
    return {g.identity for g in grants if any(acl.key_exprs_intersect(k, key) for k in g.put)}


def test_one_identity_per_camera_robot_side_and_the_backend(example_site) -> None:
    assert acl.identities(example_site) == [
        "edge-cam_ne", "edge-cam_nw", "edge-cam_se", "edge-cam_sw", "backend", "bridge-hsr",
        "ros-hsr",
    ]  # fmt: skip
    assert acl.identities(example_site, viewers=["laptop"])[-1] == "viewer-laptop"


@pytest.mark.parametrize(
    ("key", "owner"),
    [
        (keys.detections_key(SITE, "cam_sw"), "edge-cam_sw"),
        (keys.edge_cloud_key(SITE, "cam_se"), "edge-cam_se"),
        (keys.image_key(SITE, "cam_ne"), "edge-cam_ne"),
        (keys.status_key(SITE, "edge-agent", "cam_nw"), "edge-cam_nw"),
        (keys.pose_key(SITE, "hsr"), "backend"),
        (keys.camera_pose_key(SITE, "hsr"), "backend"),
        (keys.map_voxels_key(SITE, "main"), "backend"),
        (keys.status_key(SITE, "backend", "main"), "backend"),
        (keys.status_key(SITE, "mapper", "main"), "backend"),
        (keys.status_key(SITE, "viewer", "main"), "backend"),
        (keys.odom_key(SITE, "hsr"), "bridge-hsr"),
        (keys.localization_key(SITE, "hsr"), "bridge-hsr"),
        (keys.correction_key(SITE, "hsr"), "bridge-hsr"),
        (keys.status_key(SITE, "robot-bridge", "hsr"), "bridge-hsr"),
        ("laser_2d_correct_pose", "bridge-hsr"),
        (RMW_CORRECTION, "bridge-hsr"),
        ("initialpose", "bridge-hsr"),
        ("smartedge/pose", "bridge-hsr"),
        ("smartedge/camera_pose", "bridge-hsr"),
        ("tf", "bridge-hsr"),
        ("switched_odom", "ros-hsr"),
        ("global_pose", "ros-hsr"),
        ("0/amcl_pose/geometry_msgs::msg::dds_::PoseWithCovarianceStamped_/RIHS01_cd", "ros-hsr"),
    ],
)
def test_each_key_has_exactly_one_putter(example_site, key: str, owner: str) -> None:
    assert _putters(acl.grants(example_site), key) == {owner}


@pytest.mark.parametrize(
    "key",
    [keys.ground_truth_key(SITE, "hsr"), keys.status_key(SITE, "intruder", "x"),
     "smartedge/other_site/robot/hsr/pose", "cmd_vel", "@/router/x"],
)  # fmt: skip
def test_keys_nobody_owns_are_denied_to_all(example_site, key: str) -> None:
    assert _putters(acl.grants(example_site), key) == set()


def test_edge_grant_is_its_own_keys_and_reads_the_site(example_site) -> None:
    grant = next(g for g in acl.grants(example_site) if g.identity == "edge-cam_sw")
    assert grant.put == (
        keys.detections_key(SITE, "cam_sw"), keys.edge_cloud_key(SITE, "cam_sw"),
        keys.image_key(SITE, "cam_sw"), keys.status_key(SITE, "edge-agent", "cam_sw"),
    )  # fmt: skip
    assert grant.tokens == (keys.alive_key(SITE, "edge-agent", "cam_sw"),)
    assert grant.read == (f"smartedge/{SITE}/**",)


def test_ros_side_has_nothing_on_the_site_prefix(example_site) -> None:
    ros = next(g for g in acl.grants(example_site) if g.identity == "ros-hsr")
    for key in (*ros.put, *ros.tokens, *ros.read):
        assert not acl.key_exprs_intersect(key, f"smartedge/{SITE}/**"), key
    bridge = next(g for g in acl.grants(example_site) if g.identity == "bridge-hsr")
    assert set(ros.read) >= set(acl.RosKeys.default().bridge)
    assert set(bridge.read) >= set(ros.put)


def test_block_follows_the_zenoh_schema(block: dict) -> None:
    assert block["enabled"] is True and block["default_permission"] == "deny"
    rule_ids = [r["id"] for r in block["rules"]]
    assert len(rule_ids) == len(set(rule_ids))
    for rule in block["rules"]:
        assert set(rule) == {"id", "messages", "flows", "permission", "key_exprs"}
        assert set(rule["messages"]) <= set(acl.MESSAGES) and rule["messages"]
        assert set(rule["flows"]) <= set(acl.FLOWS) and rule["flows"]
        assert rule["permission"] == "allow" and rule["key_exprs"]
    subjects = {s["id"]: s for s in block["subjects"]}
    for sid, subject in subjects.items():
        assert subject["cert_common_names"] == [sid]
    for policy in block["policies"]:
        assert set(policy["rules"]) <= set(rule_ids)
        assert set(policy["subjects"]) <= set(subjects)
    # publishing is ingress only: nobody is granted put by an egress rule of someone else
    for rule in block["rules"]:
        if "put" in rule["messages"] and "ingress" in rule["flows"]:
            assert rule["id"].endswith("/put")


def test_zenoh_accepts_the_block_and_opens_a_router_with_it(block: dict) -> None:
    zenoh = pytest.importorskip("zenoh")
    text = "{mode: 'router', listen: {endpoints: []}, scouting: {multicast: {enabled: false}}, " \
           f"access_control: {acl.render_json5(block)}}}"
    conf = zenoh.Config.from_json5(text)
    assert json.loads(conf.get_json("access_control/default_permission")) == "deny"
    with zenoh.open(conf):
        pass  # the policies are resolved (rule and subject ids) when the router opens


def test_zenoh_rejects_an_unknown_message_name(block: dict) -> None:
    """The schema check above is real: zenoh 1.x refuses message kinds it does not know."""
    zenoh = pytest.importorskip("zenoh")
    bad = dict(block, rules=[dict(block["rules"][0], messages=["publish"])])
    with pytest.raises(Exception, match="publish"):
        zenoh.Config.from_json5(json.dumps({"access_control": bad}))


def test_render_json5_reads_back_as_the_block(block: dict) -> None:
    text = acl.render_json5(block)
    assert json.loads(text) == block
    assert '"messages": ["put", "delete"]' in text  # short lists on one line


def test_ros_topic_keys_namespace_domain_and_ros1() -> None:
    assert acl.ros_topic_keys(["/odom"]) == ("odom", "*/odom/**")
    assert acl.ros_topic_keys(["odom"], "/hsrb/", domain_id=3, ros1=True) == (
        "hsrb/odom", "3/hsrb/odom/**", "*/*/hsrb/odom")
    for bad in ("", "/", "a//b", "@x", "a/*"):
        with pytest.raises(ValidationError):
            acl.ros_topic_keys([bad])


def test_ros_keys_from_the_site_section() -> None:
    ros = acl.RosKeys.from_section({"namespace": "robot1", "domain_id": 7,
                                    "odometry_topic": "wheel_odom", "localization_topic": "none",
                                    "pose_topic": "fused_pose"})  # fmt: skip
    assert "robot1/wheel_odom" in ros.robot and "7/robot1/wheel_odom/**" in ros.robot
    assert "robot1/fused_pose" in ros.bridge and "robot1/laser_2d_correct_pose" in ros.bridge
    assert not any(k.endswith("none") for k in ros.robot)
    with pytest.raises(ValidationError, match="domain_id"):
        acl.RosKeys.from_section({"domain_id": "x"})


def test_ros_keys_overlapping_the_site_are_refused(example_site) -> None:
    """A site named like a ROS topic: ``*/odom/**`` would cover ``smartedge/odom/**``."""
    site = dataclasses.replace(example_site, name="odom")
    with pytest.raises(ValidationError, match="overlaps"):
        acl.grants(site)
    acl.grants(site, acl.RosKeys.from_section({"domain_id": 0}))  # a domain makes them distinct


def test_per_robot_ros_keys(example_site) -> None:
    ros = acl.RosKeys(bridge=("hsr_ns/laser_2d_correct_pose",), robot=("hsr_ns/odom",))
    grant = next(g for g in acl.grants(example_site, {"hsr": ros}) if g.identity == "bridge-hsr")
    assert "hsr_ns/laser_2d_correct_pose" in grant.put and "laser_2d_correct_pose" not in grant.put


@pytest.mark.parametrize(
    ("a", "b", "meet"),
    [
        ("*/odom/**", "smartedge/odom/**", True),
        ("0/odom/**", "smartedge/lab/**", False),
        ("smartedge/pose", "smartedge/lab/**", False),
        ("smartedge/pose", "smartedge/pose/**", True),
        ("@ros2_lv/**", "**", False),
        ("@/*/@ros2_lv/**", "@/z/@ros2_lv/0/x", True),
        ("a/**/b", "a/b", True),
        ("a/*/b", "a/b", False),
        ("**/c", "a/b/c", True),
        ("a/b", "a/b/c", False),
    ],
)
def test_key_exprs_intersect(a: str, b: str, meet: bool) -> None:
    assert acl.key_exprs_intersect(a, b) is meet
    assert acl.key_exprs_intersect(b, a) is meet


def test_deployment_doc_holds_the_generated_table(example_site) -> None:
    doc = (REPO_ROOT / "docs" / "deployment.md").read_text()
    table = acl.put_table_markdown(example_site, acl.RosKeys.from_section(
        example_site.section("ros")))
    assert table in doc, (
        "docs/deployment.md: regenerate the table of 'Identities and access control' with "
        "acl.put_table_markdown(site, acl.RosKeys.from_section(site.section('ros'))) on "
        "deploy/site.example.yaml")
