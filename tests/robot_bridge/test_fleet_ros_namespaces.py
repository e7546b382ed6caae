"""A fleet's ROS sides: each robot entry's own ``ros:`` keys, and two robots on the same ROS
topics refused by `smartedge site check`, the certificates' ACL and the bridge."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from core import acl
from core.site import load_site
from protocol.errors import ConfigFileError, UsageError, ValidationError
from robot_bridge.adapters.ros2 import RosConfig
from robot_bridge.adapters.ros_plugin import ros_config, ros_topics
from simulation.scenario import SITES_DIR
from smartedge.commands.site import main as site_main

PAPER_SITE = (SITES_DIR / "paper_lab.yaml").read_text()
ONE_ROBOT = "  - {id: hsr, model: hsr}"


def _site(tmp_path: Path, robots: str, extra: str = "", name: str = "fleet.yaml") -> Path:
    assert ONE_ROBOT in PAPER_SITE
    path = tmp_path / name
    path.write_text(PAPER_SITE.replace(ONE_ROBOT, robots) + extra)
    return path


def _args(robot: str, adapter: str = "ros2") -> argparse.Namespace:
    return argparse.Namespace(adapter=adapter, robot=robot, robot_profile=None,
                              ros_namespace=None, correction_topic=None, odom_topic=None)


def test_each_robot_gets_its_own_namespace_over_the_site_wide_section(tmp_path: Path) -> None:
    path = _site(tmp_path, "  - {id: hsr1, model: hsr, ros: {namespace: /hsr1}}\n"
                           "  - {id: hsr2, model: hsr, ros: {namespace: /hsr2, domain_id: 3}}",
                 "\nros: {profile: nav2, domain_id: 7}\n")
    site = load_site(path)
    one, two = RosConfig.from_site(site, "hsr1"), RosConfig.from_site(site, "hsr2")
    assert (one.profile, one.namespace, one.domain_id) == ("nav2", "/hsr1", 7)
    assert (two.profile, two.namespace, two.domain_id) == ("nav2", "/hsr2", 3)
    assert RosConfig.from_site(site).namespace == ""  # the site-wide section alone
    topics = ros_topics(_args("hsr2"), site)
    assert topics.namespace == "/hsr2" and topics.correction_topic == "initialpose"
    # the ACL gives each bridge its own robot's topics only
    grants = {g.identity: g for g in acl.grants(site, acl.site_ros_keys(site))}
    put1 = grants[acl.bridge_identity("hsr1")].put
    assert any(k.startswith("hsr1/") for k in put1)
    assert not any("hsr2" in k for k in put1)
    assert site_main(["check", str(path)]) == 0


def test_two_robots_on_the_same_topics_are_refused(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    path = _site(tmp_path, "  - {id: hsr1, model: hsr}\n  - {id: hsr2, model: hsr}")
    assert site_main(["check", str(path)]) == 1
    err = capsys.readouterr().err
    assert "'hsr1' and 'hsr2' share ROS topics" in err and "fleet.yaml" in err
    assert "namespace" in err
    site = load_site(path)
    with pytest.raises(ValidationError, match="share ROS topics"):
        acl.grants(site, acl.site_ros_keys(site))
    with pytest.raises(UsageError, match="share ROS topics"):
        ros_config(_args("hsr1"), site)
    # one namespace apart is enough; the same namespace twice is not
    same = _site(tmp_path, "  - {id: hsr1, model: hsr, ros: {namespace: lab}}\n"
                           "  - {id: hsr2, model: hsr, ros: {namespace: /lab}}", name="same.yaml")
    assert site_main(["check", str(same)]) == 1
    apart = _site(tmp_path, "  - {id: hsr1, model: hsr}\n"
                            "  - {id: hsr2, model: hsr, ros: {namespace: /hsr2}}",
                  name="apart.yaml")
    assert site_main(["check", str(apart)]) == 0


def test_a_bad_robot_ros_key_names_the_entry(tmp_path: Path) -> None:
    path = _site(tmp_path, "  - {id: hsr1, model: hsr}\n"
                           "  - {id: hsr2, model: hsr, ros: {namespce: /hsr2}}")
    with pytest.raises(ConfigFileError, match=r"robots\[1\]\.ros\.namespce") as exc:
        RosConfig.from_site(load_site(path), "hsr2")
    assert "fleet.yaml" in str(exc.value)
    not_a_mapping = _site(tmp_path, "  - {id: hsr1, model: hsr, ros: /hsr1}", name="nm.yaml")
    with pytest.raises(ConfigFileError, match=r"robots\[0\]\.ros"):
        load_site(not_a_mapping)
