"""Robot adapter plug-ins and the registry the bridge's ``--adapter`` option is built from.

A plug-in is registered under a name (:func:`register_adapter`); the bridge's parser offers
every registered name as an ``--adapter`` choice, lets each plug-in add its own argument group,
and calls ``plugin.build(args, site)`` for the chosen one, which returns an
:class:`AdapterSetup`: the adapter factory and, for a robot the bridge's process steps itself
(a simulated one), an ``advance(now_ns)`` hook.

The robot bridge registers the adapters it ships (``ros2``, ``ros1``). Anything else, such as
the simulated robot, is registered from the top floor (:mod:`smartedge.plugins`): this package
never imports the code that provides it.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from collections.abc import Callable
from typing import Any, Protocol

from protocol.errors import UsageError
from protocol.plugins import PluginRegistry
from protocol.site import Site
from robot_bridge.adapters.base import RobotAdapter

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class AdapterSetup:
    """What an adapter plug-in builds for one bridge.

    ``factory(session)`` builds the adapter once the Zenoh session is open (the ROS adapters
    are Zenoh clients themselves). ``advance(now_ns)``: called before every pump with the wall
    clock (ns), for a robot simulated in the bridge's process; ``None`` for a real robot.
    ``site`` and ``robot_id``: what the adapter brings along (the simulated site and its
    robot), used when ``--site`` / ``--robot`` are not given.
    """

    factory: Callable[[Any], RobotAdapter]
    advance: Callable[[int], None] | None = None
    site: Site | None = None
    robot_id: str | None = None


class AdapterPlugin(Protocol):
    """A kind of robot adapter, as registered under an ``--adapter`` name.

    ``add_arguments(parser)`` adds the plug-in's own argument group (called once per parser
    for every registered plug-in, whichever adapter is chosen; a plug-in registered under
    several names is asked once). ``build(args, site)`` returns the :class:`AdapterSetup` for
    the parsed ``args``; ``site`` is the site file given with ``--site`` (``None`` when there
    was none). Bad options raise ``ValueError`` or ``KeyError`` with a message for the user.
    """

    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def build(self, args: argparse.Namespace, site: Site | None) -> AdapterSetup: ...


#: the ``--adapter`` plug-ins (the service registers its own; the top floor adds more)
ADAPTERS: PluginRegistry[AdapterPlugin] = PluginRegistry("--adapter", "robot adapter")


def register_adapter(name: str, plugin: AdapterPlugin) -> None:
    """Offer ``plugin`` as ``--adapter name`` (see :meth:`PluginRegistry.register`)."""
    ADAPTERS.register(name, plugin)


def adapter_names() -> tuple[str, ...]:
    """The registered ``--adapter`` names, sorted."""
    return ADAPTERS.names()


def get_adapter(name: str) -> AdapterPlugin:
    """The plug-in registered as ``name`` (``KeyError`` naming the known ones otherwise)."""
    return ADAPTERS.get(name)


def add_adapter_arguments(parser: argparse.ArgumentParser, default: str) -> None:
    """``--adapter`` with the registered names as choices, then every plug-in's own group."""
    ADAPTERS.add_arguments(parser, default)


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
        from robot_bridge.adapters.ros2 import RosZenohAdapter

        topics = ros_topics(args, site, ros1=args.adapter == "ros1")
        return AdapterSetup(lambda session: RosZenohAdapter(session, topics))


def ros_config(args: argparse.Namespace, site: Site | None) -> Any:
    """The site file's ``ros`` section with the command-line overrides applied (a
    :class:`robot_bridge.adapters.ros2.RosConfig`); ``UsageError`` without a site."""
    from robot_bridge.adapters.ros2 import RosConfig

    if site is None:
        raise UsageError(f"--site is required with --adapter {args.adapter}")
    config = RosConfig.from_site(site)
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


def ros_topics(args: argparse.Namespace, site: Site | None, *, ros1: bool = False) -> Any:
    """The :class:`robot_bridge.adapters.ros2.RosTopics` for ``args`` and the site: its
    ``ros`` section, the command-line overrides, and the site's ``world_frame`` as the frame
    of corrections and pose outputs."""
    config = ros_config(args, site)  # UsageError without a site
    assert site is not None
    return config.topics(ros1=ros1, map_frame=site.world_frame)


ROS_ADAPTERS = RosAdapterPlugin()
register_adapter("ros2", ROS_ADAPTERS)
register_adapter("ros1", ROS_ADAPTERS)


def _register_rmw_zenoh() -> None:
    # imported here: the module needs this one's registry (AdapterSetup, ros_config) first
    from robot_bridge.adapters.rmw_zenoh import RMW_ZENOH_ADAPTER

    register_adapter("rmw_zenoh", RMW_ZENOH_ADAPTER)


_register_rmw_zenoh()
