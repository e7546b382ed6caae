"""``smartedge edge-agent``: one camera's edge service.

Frames come from a source, the robot keypoint detector turns them into
:class:`protocol.RobotDetections`, which are published on
``smartedge/<site>/edge/<camera_id>/detections`` (best effort: a stale frame is worthless).

Sources:

- ``sim``: the simulated site (:mod:`simulation.live`): detections computed from the simulated
  robot's ground truth with the scenario's detector noise model. Clearly labelled
  ``source=sim`` in the status and the ``model_id``.
- ``camera``: a real camera through the ONNX keypoint detector (needs a keypoint model, which
  this version does not ship; the agent says so and exits with code 2).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Iterable, Sequence
from typing import Protocol

from protocol import keys
from protocol.messages import RobotDetections
from protocol.runtime import Outgoing, ServiceNode, service_main
from protocol.session import add_session_arguments
from protocol.site import Site, load_site

log = logging.getLogger(__name__)


class FrameSource(Protocol):
    """Produces the detections of one camera that are due at ``now_ns``."""

    label: str

    def poll(self, now_ns: int) -> list[RobotDetections]: ...


class EdgeAgentNode(ServiceNode):
    """Publishes what the source detects; counts frames with and without a robot."""

    service = "edge-agent"

    def __init__(
        self, site: Site, camera_id: str, source: FrameSource, tick_period_s: float = 0.01
    ) -> None:
        super().__init__(site.name, camera_id)
        site.camera(camera_id)  # raises a clear KeyError for an unknown camera
        self.camera_id = camera_id
        self.source = source
        self.tick_period_s = tick_period_s
        self._key = keys.detections_key(site.name, camera_id)

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        out = []
        for msg in self.source.poll(now_ns):
            self.stats.count("frames")
            self.stats.count("frames_with_robot" if msg.detections else "frames_without_robot")
            self.stats.event("detections")
            self.stats.latency("capture_to_publish", max(0, now_ns - msg.stamp_ns) * 1e-9)
            out.append(Outgoing(self._key, msg, reliable=False))
        return out

    def state(self) -> tuple[str, str]:
        return "ok", f"source={self.source.label}"


class SimulatedCameraSource:
    """Detections of one camera of the simulated site (see :mod:`simulation.live`)."""

    def __init__(self, feed) -> None:
        self._feed = feed
        self.label = "sim"

    def poll(self, now_ns: int) -> list[RobotDetections]:
        return self._feed.poll(now_ns)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge edge-agent",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", help="site file (with --source sim: default the scenario's)")
    parser.add_argument("--camera", required=True, help="camera id in the site file")
    parser.add_argument(
        "--source",
        choices=("sim", "camera"),
        default="camera",
        help="frame source (default: camera)",
    )
    add_session_arguments(parser)
    from simulation.live import add_sim_arguments  # numpy-only; fine on an edge board

    add_sim_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> EdgeAgentNode:
    """The edge agent for ``args`` (only the simulated source exists in this version)."""
    from simulation.live import CameraFeed, LiveSimulation, spec_from_args

    live = LiveSimulation(spec_from_args(args))
    site = load_site(args.site) if args.site else live.site
    node = EdgeAgentNode(site, args.camera, SimulatedCameraSource(CameraFeed(live, args.camera)))
    log.info(
        "edge agent %s: SIMULATED source (scenario %s, trajectory %s, t0 in %.1f s)",
        args.camera,
        live.scenario.name,
        live.spec.trajectory,
        (live.spec.epoch_ns - time.time_ns()) * 1e-9,
    )
    return node


def main(argv: Sequence[str]) -> int:
    if build_parser().parse_args(list(argv)).source == "camera":
        print(
            "smartedge edge-agent: the camera source needs the robot keypoint model (ONNX), "
            "which this version does not ship; use --source sim for the simulated site",
            file=sys.stderr,
        )
        return 2
    return service_main("edge-agent", argv, build_parser, build_node)
