"""The viewer node: wire messages in, Rerun calls out (see :mod:`smartedge.viewer`).

:class:`ViewerNode` is a transport-free :class:`~core.runtime.ServiceNode` like the
services, so it runs on Zenoh (:func:`main`), in a demo thread, or under the scripted runner in
tests. It draws odometry in the world frame through ``T_world_odom``, fixed by the first fused
pose (so the drift of odometry shows), and, when it is given a ground-truth source (the
simulation), logs each estimate's error against the truth at the estimate's own stamp.
"""

from __future__ import annotations

import argparse
import logging
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final

import numpy as np

from core.geometry import se2_matrix
from core.runtime import Outgoing, ServiceNode, Subscription, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from protocol import keys
from protocol.errors import UsageError
from protocol.messages import (
    CameraImage,
    Message,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)

log = logging.getLogger(__name__)

#: robot id, stamp (ns) → true planar pose (3,) or ``None`` (simulation only)
TruthSource = Callable[[str, int], "np.ndarray | None"]
#: ground truth is drawn at most this often per robot
TRUTH_PERIOD_NS: Final = 100_000_000


class ViewerNode(ServiceNode):
    """Draws what the services publish (module docstring). ``view``: a
    :class:`~smartedge.viewer.rerun_view.RerunView` or anything with its methods; ``truth``:
    optional ground truth for the error series."""

    service = "viewer"

    def __init__(self, site: Site, view: Any, instance_id: str = "main", *,
                 truth: TruthSource | None = None, tick_period_s: float = 0.1) -> None:
        super().__init__(site.name, instance_id)
        self.site_model = site
        self.view = view
        self.truth = truth
        self.tick_period_s = tick_period_s
        self._odometry: dict[str, Odometry] = {}
        self._T_world_odom: dict[str, np.ndarray] = {}
        self._truth_drawn_ns: dict[str, int] = {}
        voxel = site.section("map").get("voxel_size_m", 0.05)
        self.map_voxel_size_m = float(voxel) if isinstance(voxel, (int, float)) else 0.05

    def subscriptions(self) -> Sequence[Subscription]:
        s = self.site
        return [
            Subscription(keys.detections_key(s, "*"), RobotDetections, capacity=4096),
            Subscription(keys.image_key(s, "*"), CameraImage, capacity=16),
            Subscription(keys.odom_key(s, "*"), Odometry, capacity=4096),
            Subscription(keys.localization_key(s, "*"), PoseEstimate, capacity=256),
            Subscription(keys.camera_pose_key(s, "*"), PoseEstimate, capacity=1024),
            Subscription(keys.pose_key(s, "*"), PoseEstimate, capacity=4096),
            Subscription(keys.correction_key(s, "*"), PoseCorrection, capacity=64),
            Subscription(keys.status_key(s, "*", "*"), ServiceStatus, capacity=256),
            Subscription(keys.map_voxels_key(s, "*"), SemanticCloud, capacity=2),
        ]

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        self.stats.event(type(message).__name__)
        if isinstance(message, RobotDetections):
            self.view.detections(message)
        elif isinstance(message, CameraImage):
            self.view.image(message)
        elif isinstance(message, Odometry):
            self._on_odometry(message)
        elif isinstance(message, PoseEstimate):
            self._on_pose(key, message, recv_ns)
        elif isinstance(message, PoseCorrection):
            self.view.correction(message.robot_id, message.stamp_ns, message.x, message.y,
                                 message.theta)
        elif isinstance(message, ServiceStatus):
            self.view.status(message)
        elif isinstance(message, SemanticCloud):
            self.view.semantic_map(message, self.map_voxel_size_m)
        return []

    def _on_odometry(self, odom: Odometry) -> None:
        self._odometry[odom.robot_id] = odom
        T = self._T_world_odom.get(odom.robot_id)
        if T is not None:
            self.view.odometry(odom, T)
        self._draw_truth(odom.robot_id, odom.stamp_ns)

    def _on_pose(self, key: str, est: PoseEstimate, recv_ns: int) -> None:
        topic = key.rsplit("/", 1)[-1]
        if topic == "localization":
            kind = "localization"
            self.view.odometry_pose(est.robot_id, est.stamp_ns, est.x, est.y, est.theta,
                                    kind=kind)
        elif topic == "camera_pose":
            kind = "camera"
            self.view.pose(est, kind)
            self.view.latency(est.stamp_ns, "stamp_to_view", max(0, recv_ns - est.stamp_ns) * 1e-9)
        else:
            kind = "fused"
            self.view.pose(est, kind)
            odom = self._odometry.get(est.robot_id)
            if est.robot_id not in self._T_world_odom and odom is not None:
                self._T_world_odom[est.robot_id] = se2_matrix(est.x, est.y, est.theta) @ (
                    np.linalg.inv(se2_matrix(odom.x, odom.y, odom.theta)))
        self._error(est.robot_id, est.stamp_ns, kind, est.x, est.y)

    def _error(self, robot_id: str, stamp_ns: int, kind: str, x: float, y: float) -> None:
        if self.truth is None:
            return
        truth = self.truth(robot_id, stamp_ns)
        if truth is not None:
            self.view.error(robot_id, stamp_ns, kind, math.hypot(x - truth[0], y - truth[1]))

    def _draw_truth(self, robot_id: str, stamp_ns: int) -> None:
        if self.truth is None:
            return
        if stamp_ns - self._truth_drawn_ns.get(robot_id, -TRUTH_PERIOD_NS) < TRUTH_PERIOD_NS:
            return
        truth = self.truth(robot_id, stamp_ns)
        if truth is not None:
            self._truth_drawn_ns[robot_id] = stamp_ns
            self.view.odometry_pose(robot_id, stamp_ns, float(truth[0]), float(truth[1]),
                                    float(truth[2]), kind="ground_truth")

    def counters(self) -> dict[str, int]:
        """The node's counters and the view's (previews drawn, ``image_errors``: previews
        that did not decode, ``image_unknown_camera``)."""
        out = dict(super().counters())
        out.update(getattr(self.view, "counters", None) or {})
        return out

    def state(self) -> tuple[str, str]:
        return "ok", f"drawing {len(self._odometry)} robot(s)"

    def close(self) -> None:
        self.view.close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge viewer",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", help="site file (with --sim-truth: default the scenario's)")
    parser.add_argument("--id", default="main", help="instance id (default: main)")
    parser.add_argument(
        "--rerun",
        default="spawn",
        help="save:PATH.rrd, spawn (default: a local viewer window), connect[:URL], "
        "serve (gRPC + web viewer)",
    )
    parser.add_argument(
        "--sim-truth",
        action="store_true",
        help="simulated site: compute ground truth from the --sim-* options and log errors",
    )
    add_session_arguments(parser)
    from simulation.live import add_sim_arguments

    add_sim_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> ViewerNode:
    from smartedge.viewer.rerun_view import RerunTarget, RerunView, StaticScene, scene_from_boxes

    truth: TruthSource | None = None
    scene: StaticScene | None = None
    site = load_site(args.site) if args.site else None
    if args.sim_truth:
        from simulation.live import LiveSimulation, spec_from_args

        live = LiveSimulation(spec_from_args(args))
        site = site or live.site
        truth = truth_from_live(live)
        sc = live.scenario
        scene = scene_from_boxes(sc.room_min_xy_m, sc.room_max_xy_m, sc.room_height_m,
                                 sc.obstacles)
    if site is None:
        raise UsageError("--site is required (or --sim-truth for the simulated site)")
    target = RerunTarget.parse(args.rerun)
    if target.kind == "none":
        raise UsageError("--rerun none: the viewer needs somewhere to draw")
    return ViewerNode(site, RerunView(site, target, scene=scene), args.id, truth=truth)


def truth_from_live(live: Any) -> TruthSource:
    """Ground truth of a :class:`simulation.live.LiveSimulation` (every robot of it)."""

    def truth(robot_id: str, stamp_ns: int) -> np.ndarray | None:
        return live.ground_truth(stamp_ns, robot_id) if robot_id in live.runs else None

    return truth


def main(argv: Sequence[str]) -> int:
    return service_main("viewer", argv, build_parser, build_node)
