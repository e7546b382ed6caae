"""Frame sources of the edge agent and the registry the ``--source`` option is built from.

A source plug-in is registered under a name (:func:`register_source`); the edge agent's parser
offers every registered name as a ``--source`` choice, lets each plug-in add its own argument
group, and builds the chosen source with ``plugin.build(args, site)``.

The edge agent registers only what it ships (``camera``). Anything else, such as the simulated
site, is registered from the top floor (:mod:`smartedge.plugins`): this package never imports
the code that provides it.
"""

from __future__ import annotations

import argparse
import logging
from typing import Protocol

from protocol.errors import UsageError
from protocol.messages import RobotDetections
from protocol.plugins import PluginRegistry
from protocol.site import Site

log = logging.getLogger(__name__)


class FrameSource(Protocol):
    """Produces the detections of one camera that are due at ``now_ns``.

    ``label`` names the source in the status (``sim``, ``camera``...). A source that brings its
    own site (the simulated one) may also have a ``site`` attribute: the edge agent uses it when
    no ``--site`` was given.
    """

    label: str

    def poll(self, now_ns: int) -> list[RobotDetections]: ...


class SourcePlugin(Protocol):
    """A kind of frame source, as registered under a ``--source`` name.

    ``add_arguments(parser)`` adds the plug-in's own argument group (it is called once per
    parser for every registered plug-in, whichever source is chosen). ``build(args, site)``
    returns the source for the parsed ``args``; ``site`` is the site file given with
    ``--site`` (``None`` when there was none). Bad options raise ``ValueError`` or
    ``KeyError`` with a message for the user.

    A plug-in may have an ``unavailable`` attribute: a non-empty string saying why it cannot
    run in this installation; the edge agent then prints it and exits with code 2.
    """

    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def build(self, args: argparse.Namespace, site: Site | None) -> FrameSource: ...


#: the ``--source`` plug-ins (the service registers its own; the top floor adds more)
SOURCES: PluginRegistry[SourcePlugin] = PluginRegistry("--source", "frame source")


def register_source(name: str, plugin: SourcePlugin) -> None:
    """Offer ``plugin`` as ``--source name`` (see :meth:`PluginRegistry.register`)."""
    SOURCES.register(name, plugin)


def source_names() -> tuple[str, ...]:
    """The registered ``--source`` names, sorted."""
    return SOURCES.names()


def get_source(name: str) -> SourcePlugin:
    """The plug-in registered as ``name`` (``KeyError`` naming the known ones otherwise)."""
    return SOURCES.get(name)


def add_source_arguments(parser: argparse.ArgumentParser, default: str) -> None:
    """``--source`` with the registered names as choices, then every plug-in's own group."""
    SOURCES.add_arguments(parser, default)


class CameraSourcePlugin:
    """A real camera through the ONNX detector + keypoint models. The models ship
    (``edge_agent/models/``, :mod:`edge_agent.models`), the capture side (OpenCV, RealSense) is
    not built yet, so the source says so instead of running."""

    unavailable = (
        "the camera frame source (OpenCV/RealSense capture) is not built in this version; the "
        "detector and keypoint models ship in edge_agent/models/ (see smartedge evaluate "
        "keypoints)"
    )

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        pass

    def build(self, args: argparse.Namespace, site: Site | None) -> FrameSource:
        raise UsageError(self.unavailable)


register_source("camera", CameraSourcePlugin())
