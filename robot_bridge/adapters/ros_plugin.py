"""The ``--adapter ros2`` / ``ros1`` plug-in and the ROS options every ROS plug-in reads.

:class:`RosAdapterPlugin` adds the ROS argument group (``--robot-profile``, ``--ros-namespace``,
``--correction-topic``, ``--odom-topic``) and builds a
:class:`robot_bridge.adapters.ros2.RosZenohAdapter` (zenoh-bridge-ros2dds or zenoh-plugin-ros1
on the robot). :func:`ros_config` (the site file's ``ros`` section with those options applied)
is shared with the ``rmw_zenoh`` plug-in (:mod:`robot_bridge.adapters.rmw_zenoh`).
:mod:`robot_bridge.adapters.registry` registers both; this module never imports the registry.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging

from core import acl
from core.site import Site
from protocol.errors import UsageError
from robot_bridge.adapters.base import AdapterSetup
from robot_bridge.adapters.ros2 import RosConfig, RosTopics, RosZenohAdapter

log = logging.getLogger(__name__)


class RosAdapterPlugin:
    """ROS 2 (zenoh-bridge-ros2dds) and ROS 1 (zenoh-plugin-ros1) robots through
    :class:`robot_bridge.adapters.ros2.RosZenohAdapter`; one plug-in for both names, the
    ``--adapter`` value says which."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group(
            "ROS adapters (ros2, ros1, rmw_zenoh; default: the site file's ros section)")
        group.add_argument(
            "--robot-profile",
            choices=("hsr", "nav2"),
            help="ROS topic set: HSR (laser_2d_correct_pose) or Nav2 (initialpose); "
                 "default ros.profile, else hsr",
        )
        group.add_argument("--ros-namespace", help="zenoh-bridge namespace (ros.namespace)")
        group.add_argument("--correction-topic", help="override the correction topic")
        group.add_argument("--odom-topic", help="override the odometry topic")

    def build(self, args: argparse.Namespace, site: Site | None) -> AdapterSetup:
        topics = ros_topics(args, site, ros1=args.adapter == "ros1")
        log.debug("--adapter %s: odometry %s, corrections %s", args.adapter,
                  topics.odometry_topic, topics.correction_topic)
        return AdapterSetup(lambda session: RosZenohAdapter(session, topics))


def ros_config(args: argparse.Namespace, site: Site | None) -> RosConfig:
    """The site file's ``ros`` section for the bridge's robot (``--robot``: its entry's own
    ``ros:`` keys on top) with the command-line overrides applied; ``UsageError`` without a
    site or for a bad override."""
    if site is None:
        raise UsageError(f"--site is required with --adapter {args.adapter}")
    config = RosConfig.from_site(site, getattr(args, "robot", None))
    if len(site.robots) > 1:  # two bridges on one robot's topics would correct each other's
        ros1 = getattr(args, "adapter", "") == "ros1"
        conflicts = acl.ros_conflicts(acl.site_ros_keys(site, ros1=ros1))
        if conflicts:
            raise UsageError(f"{site.source_path}: " + "; ".join(conflicts))
    overrides = {
        "profile": getattr(args, "robot_profile", None),
        "namespace": getattr(args, "ros_namespace", None),
        "correction_topic": getattr(args, "correction_topic", None),
        "odometry_topic": getattr(args, "odom_topic", None),
    }
    try:
        return dataclasses.replace(
            config, **{k: v for k, v in overrides.items() if v is not None})
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def ros_topics(args: argparse.Namespace, site: Site | None, *, ros1: bool = False) -> RosTopics:
    """The topics for ``args`` and the site: its ``ros`` section, the command-line overrides,
    and the site's ``world_frame`` as the frame of corrections and pose outputs."""
    config = ros_config(args, site)  # UsageError without a site
    assert site is not None
    return config.topics(ros1=ros1, map_frame=site.world_frame)


#: the plug-in registered as ``ros2`` and ``ros1``
ROS_ADAPTERS = RosAdapterPlugin()
