"""Robot adapter plug-ins and the registry the bridge's ``--adapter`` option is built from.

A plug-in is registered under a name (:func:`register_adapter`); the bridge's parser offers
every registered name as an ``--adapter`` choice, lets each plug-in add its own argument group,
and calls ``plugin.build(args, site)`` for the chosen one, which returns an
:class:`AdapterSetup`: the adapter factory and, for a robot the bridge's process steps itself
(a simulated one), an ``advance(now_ns)`` hook.

The robot bridge registers the adapters it ships, importing their plug-ins: ``ros2`` and
``ros1`` (:mod:`robot_bridge.adapters.ros_plugin`) and ``rmw_zenoh``
(:mod:`robot_bridge.adapters.rmw_zenoh`). Those modules never import this one (the
:class:`AdapterSetup` they build lives in :mod:`robot_bridge.adapters.base`; it is re-exported
here for plug-ins), so there is no import cycle. Anything else, such as the simulated robot, is
registered from the top floor (:mod:`smartedge.simulated_site`): this package never imports the
code that provides it.
"""

from __future__ import annotations

import argparse
import logging
from typing import Protocol

from core.plugins import PluginRegistry
from core.site import Site
from robot_bridge.adapters.base import AdapterSetup
from robot_bridge.adapters.rmw_zenoh import RMW_ZENOH_ADAPTER
from robot_bridge.adapters.ros_plugin import ROS_ADAPTERS

__all__ = [
    "ADAPTERS",
    "AdapterPlugin",
    "AdapterSetup",
    "adapter_names",
    "add_adapter_arguments",
    "get_adapter",
    "register_adapter",
]

log = logging.getLogger(__name__)


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


# the adapters the bridge ships
register_adapter("ros2", ROS_ADAPTERS)
register_adapter("ros1", ROS_ADAPTERS)
register_adapter("rmw_zenoh", RMW_ZENOH_ADAPTER)
