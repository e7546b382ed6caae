"""``smartedge robot-camera``: the simulated robot's head RGB-D camera as semantic clouds.

On the paper's HSR the head camera's frames are segmented on the robot's own board (a Jetson
TX2) and sent as semantic point clouds; this service plays that part for the simulated robot.
It renders the robot model's ``head_camera`` (site file) from the robot's *true* pose at the
capture time (:class:`simulation.live.HeadCameraFeed`, sensor and depth noise included), runs
the edge's :class:`edge_agent.networks.SemanticSegmenter` and cloud builder on it
(:class:`edge_agent.semantic_cloud.SemanticCloudMaker`, the same code as a static camera) and
publishes a :class:`protocol.SemanticCloud` in ``base_link`` (``T_frame_sensor`` =
``T_base_cam``) on ``smartedge/<site>/robot/<robot_id>/cloud``, reliably, ``--cloud-rate``
times a second. The backend places it with its *estimated* pose at the cloud's stamp, whose
error its ICP must remove.

Simulation only (it lives on the top floor because it joins the simulation and the edge code);
a real robot's clouds come from the robot itself.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Iterable, Sequence
from typing import Any, Final

from core.runtime import Outgoing, ServiceNode, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from edge_agent.semantic_cloud import ROBOT_BASE_FRAME, SemanticCloudMaker
from protocol import keys
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

DEFAULT_HEAD_CLOUD_RATE_HZ: Final = 1.0


class RobotCameraNode(ServiceNode):
    """Renders the head camera when a frame is due and publishes its semantic cloud.

    ``feed``: a :class:`simulation.live.HeadCameraFeed` (``due(now_ns)``, ``render(stamp_ns)``
    → (RGB, depth, class ids)); ``clouds``: the maker (``None``: nothing is rendered or sent;
    ``unavailable`` says why, in the status)."""

    service = "robot-camera"
    tick_period_s = 0.05

    def __init__(self, site: Site, robot_id: str, feed: Any, clouds: SemanticCloudMaker | None,
                 unavailable: str = "") -> None:
        super().__init__(site.name, robot_id)
        self.robot_id = robot_id
        self.feed = feed
        self.clouds = clouds
        self.unavailable = unavailable
        self._key = keys.robot_cloud_key(site.name, robot_id)

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        if self.clouds is None:  # nothing to make: do not render either
            return []
        capture_ns = self.feed.due(now_ns)
        if capture_ns is None:
            return []
        t0 = time.perf_counter()
        image, depth_m, _ = self.feed.render(capture_ns)
        self.stats.latency("render", time.perf_counter() - t0)
        self.stats.count("frames")
        cloud = self.clouds.make_for_service(image, depth_m, capture_ns, self.stats)
        if cloud is None:
            return []
        self.stats.latency("capture_to_publish", max(0, time.time_ns() - capture_ns) * 1e-9)
        return [Outgoing(self._key, cloud, reliable=True)]

    def state(self) -> tuple[str, str]:
        detail = (f"source=sim-head-camera frames={self.feed.seq} skipped={self.feed.skipped}")
        if self.clouds is None:
            return "degraded", f"{detail}; no clouds: {self.unavailable}"
        if self.feed.seq > 10 and self.feed.skipped > self.feed.seq:
            return "degraded", f"{detail}; rendering + segmentation cannot keep up"
        return "ok", detail

    def close(self) -> None:
        release = getattr(self.feed, "release", None)
        if release is not None:
            release()
        super().close()


def build_parser() -> argparse.ArgumentParser:
    from simulation.live import add_sim_arguments

    parser = argparse.ArgumentParser(
        prog="smartedge robot-camera",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--source", choices=("sim", "ros"), default="sim",
                        help="sim: the simulated head camera (default); ros: the real robot's "
                        "RGB-D topics and TF (see smartedge robot-camera --source ros --help)")
    parser.add_argument("--site", help="site file (default: the simulation's own); the head "
                        "camera's calibration comes from its robot model")
    parser.add_argument("--robot", help="robot id (default: the simulation's robot)")
    parser.add_argument("--cloud-rate", type=float, default=DEFAULT_HEAD_CLOUD_RATE_HZ,
                        metavar="HZ", help="head camera frames (clouds) per second (default "
                        f"{DEFAULT_HEAD_CLOUD_RATE_HZ:g})")
    parser.add_argument("--segmentation-model", metavar="ONNX",
                        help="segmentation network (default: the shipped one)")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads (default 2)")
    add_session_arguments(parser)
    add_sim_arguments(parser)
    return parser


def build_node(args: argparse.Namespace, segmenter: Any = None) -> RobotCameraNode:
    """The robot camera of ``args``; ``segmenter``: use this instead of loading
    ``--segmentation-model`` (tests)."""
    from simulation.live import HeadCameraFeed, LiveSimulation, spec_from_args

    if not args.cloud_rate > 0:
        raise UsageError(f"--cloud-rate {args.cloud_rate}: must be > 0 (leave the service "
                         "out for no robot clouds)")
    live = LiveSimulation(spec_from_args(args))
    site = load_site(args.site) if args.site else live.site
    robot_id = args.robot or live.robot_id
    if robot_id != live.robot_id:
        raise UsageError(f"--robot {robot_id}: the simulation's robot is {live.robot_id!r}")
    head = site.robot_model(robot_id).head_camera
    if head is None:
        raise UsageError(f"robot {robot_id!r} has no head_camera in {site.source_path} "
                         "(robot_models.<model>.head_camera)")
    feed = HeadCameraFeed(live, rate_hz=args.cloud_rate)
    unavailable = ""
    if segmenter is None:
        try:
            from edge_agent.networks import SemanticSegmenter

            segmenter = SemanticSegmenter(args.segmentation_model, threads=args.threads)
        except (ImportError, SmartedgeError, OSError, RuntimeError) as exc:
            unavailable = f"the segmentation model cannot be loaded: {exc}"
            log.error("%s: no robot clouds: %s", robot_id, unavailable)
    clouds = None
    if segmenter is not None:
        clouds = SemanticCloudMaker(segmenter, head.camera_model(f"{robot_id}_head"),
                                    sensor_id=robot_id, frame_id=ROBOT_BASE_FRAME,
                                    T_frame_sensor=head.T_base_cam, rate_hz=args.cloud_rate)
        log.info("%s: SIMULATED head camera %dx%d at %g Hz, clouds in %s through %s", robot_id,
                 head.width, head.height, args.cloud_rate, ROBOT_BASE_FRAME,
                 getattr(segmenter, "model_id", type(segmenter).__name__))
    return RobotCameraNode(site, robot_id, feed, clouds, unavailable)


def main(argv: Sequence[str]) -> int:
    """The simulated head camera as a service (``smartedge robot-camera --source sim``)."""
    return service_main("robot-camera", argv, build_parser, build_node)
