"""``smartedge backend``: the backend service.

Per robot: detections from every edge camera → frame-set synchronizer → multi-view pose solve
(prior = the fused pose at the frame-set's time, else PnP: kidnapped robot) → camera-only
estimate on ``.../camera_pose``; while the robot is static, the last ``multi_frame_count``
estimates are averaged (flag ``multi_frame``). Camera estimates (single frames while moving,
averages while static) and odometry go into the pose graph, whose fused pose is published at
odometry rate on ``.../pose``. Everything is logged to Rerun (``--rerun``).

The algorithms live in pure modules; this one only wires them to messages
(:class:`BackendNode`, a transport-free :class:`~protocol.runtime.ServiceNode`) and to Zenoh
(:func:`main`).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import math
from collections.abc import Iterable, Sequence
from typing import Any, Final

import numpy as np

from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.frame_set import FrameSet, PlanarPose
from backend_service.fusion import FusionConfig, PoseGraphFusion
from backend_service.multi_frame import MultiFrameAverager
from backend_service.sync import FrameSetSynchronizer
from protocol import keys
from protocol.messages import (
    Message,
    Odometry,
    PoseEstimate,
    RobotDetections,
    ServiceStatus,
)
from protocol.runtime import Outgoing, ServiceNode, Subscription, service_main
from protocol.session import add_session_arguments
from protocol.site import Site, load_site

log = logging.getLogger(__name__)

#: A camera estimate this recent can seed the next solve when no fused pose exists yet.
PRIOR_MAX_AGE_NS: Final = 1_000_000_000
GROUND_TRUTH_BUFFER: Final = 600


def _se2(x: float, y: float, theta: float) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


@dataclasses.dataclass
class RobotTrack:
    """Everything the backend keeps per robot."""

    robot_id: str
    fusion: PoseGraphFusion
    averager: MultiFrameAverager
    last_camera: PoseEstimate | None = None
    last_odometry: Odometry | None = None
    static_since_ns: int | None = None
    T_world_odom: np.ndarray | None = None  # fixed at anchoring: shows odometry drift
    seq_camera: int = 0
    seq_fused: int = 0
    ground_truth: collections.deque = dataclasses.field(
        default_factory=lambda: collections.deque(maxlen=GROUND_TRUTH_BUFFER)
    )

    def static(self, now_ns: int, dwell_ns: int) -> bool:
        return self.static_since_ns is not None and now_ns - self.static_since_ns >= dwell_ns

    def truth_at(self, stamp_ns: int) -> np.ndarray | None:
        """Ground truth interpolated at ``stamp_ns`` (simulation only), None if not covered."""
        gt = self.ground_truth
        if len(gt) < 2 or not gt[0][0] <= stamp_ns <= gt[-1][0]:
            return None
        # estimates refer to recent stamps: walk back from the newest sample, not a full scan
        i = len(gt) - 1
        while i > 1 and gt[i - 1][0] >= stamp_ns:
            i -= 1
        (s0, p0), (s1, p1) = gt[i - 1], gt[i]
        a = 0.0 if s1 == s0 else (stamp_ns - s0) / (s1 - s0)
        theta = p0[2] + a * _wrap(p1[2] - p0[2])
        return np.array([p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), theta])


class BackendNode(ServiceNode):
    """The backend as a transport-free node (see module docstring)."""

    service = "backend"

    def __init__(
        self,
        site: Site,
        instance_id: str = "main",
        *,
        solver: SolverConfig | None = None,
        fusion: FusionConfig | None = None,
        view: Any = None,
        tick_period_s: float = 0.01,
    ) -> None:
        super().__init__(site.name, instance_id)
        self.site_model = site
        self.solver = solver or SolverConfig()
        self.fusion_config = fusion or FusionConfig()
        self.view = view
        self.tick_period_s = tick_period_s
        th = site.thresholds
        self._dwell_ns = round(th.static_dwell_s * 1e9)
        self.sync = FrameSetSynchronizer(site)
        self.tracks: dict[str, RobotTrack] = {
            rid: RobotTrack(
                rid,
                PoseGraphFusion(rid, self.fusion_config),
                MultiFrameAverager(th.multi_frame_count),
            )
            for rid in site.robots
        }
        self._peers: dict[str, bool] = {}

    # ---------------------------------------------------------------------------------------

    def subscriptions(self) -> Sequence[Subscription]:
        s = self.site
        return [
            Subscription(keys.detections_key(s, "*"), RobotDetections, capacity=4096),
            Subscription(keys.odom_key(s, "*"), Odometry, capacity=4096, drop_oldest=False),
            Subscription(keys.localization_key(s, "*"), PoseEstimate, capacity=256),
            Subscription(keys.ground_truth_key(s, "*"), PoseEstimate, capacity=256),
            Subscription(keys.status_key(s, "*", "*"), ServiceStatus, capacity=256),
            Subscription(keys.alive_key(s, "*", "*"), liveliness=True),
        ]

    def alive(self, key: str, present: bool) -> None:
        try:
            parsed = keys.parse_key(key)
        except ValueError:
            return
        self._peers[f"{parsed.topic}.{parsed.source_id}"] = present

    def peers_alive(self) -> Sequence[str]:
        return sorted(k for k, v in self._peers.items() if v)

    def _track(self, robot_id: str) -> RobotTrack | None:
        track = self.tracks.get(robot_id)
        if track is None:
            self.stats.count("unknown_robot")
        return track

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        if isinstance(message, RobotDetections):
            self.stats.event("detections")
            if self.view is not None:
                self.view.detections(message)
            return self._solve_all(self.sync.push(message, recv_ns), recv_ns)
        if isinstance(message, Odometry):
            return self._on_odometry(message, recv_ns)
        if isinstance(message, PoseEstimate):
            track = self._track(message.robot_id)
            if track is None:
                return []
            pose = (message.x, message.y, message.theta)
            if message.source == "ground_truth":
                track.ground_truth.append((message.stamp_ns, pose))
                kind = "ground_truth"
            else:
                kind = "localization"
                self._log_error(track, message.stamp_ns, "localization", message)
            if self.view is not None:
                self.view.odometry_pose(message.robot_id, message.stamp_ns, *pose, kind=kind)
            return []
        if isinstance(message, ServiceStatus) and self.view is not None:
            self.view.status(message)
        return []

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        return self._solve_all(self.sync.poll(now_ns), now_ns)

    # ---------------------------------------------------------------------------------------

    def _on_odometry(self, odom: Odometry, recv_ns: int) -> list[Outgoing]:
        track = self._track(odom.robot_id)
        if track is None:
            return []
        self.stats.event("odometry")
        th = self.site_model.thresholds
        moving = math.hypot(odom.vx, odom.vy) > th.static_max_speed_mps or (
            abs(odom.wz) > th.static_max_yaw_rate_radps
        )
        if moving:
            track.static_since_ns = None
            track.averager.reset()
        elif track.static_since_ns is None:
            track.static_since_ns = odom.stamp_ns
        track.last_odometry = odom
        fused = track.fusion.add_odometry(odom)
        if fused is None:
            return []
        if track.T_world_odom is None:
            track.T_world_odom = _se2(fused.x, fused.y, fused.theta) @ np.linalg.inv(
                _se2(odom.x, odom.y, odom.theta)
            )
        if self.view is not None:
            self.view.odometry(odom, track.T_world_odom)
        return [self._publish_fused(track, fused)]

    def _publish_fused(self, track: RobotTrack, fused: PoseEstimate) -> Outgoing:
        fused = dataclasses.replace(
            fused, seq=track.seq_fused, frame_id=self.site_model.world_frame
        )
        track.seq_fused += 1
        self.stats.event("fused")
        if self.view is not None:
            self.view.pose(fused, "fused")
        self._log_error(track, fused.stamp_ns, "fused", fused)
        return Outgoing(keys.pose_key(self.site, track.robot_id), fused)

    def _prior(self, track: RobotTrack, stamp_ns: int) -> PlanarPose | None:
        if track.fusion.anchored:
            fused = track.fusion.pose_at(stamp_ns) or track.fusion.latest()
            if fused is not None:
                return PlanarPose(fused.x, fused.y, fused.theta)
        last = track.last_camera
        if last is not None and abs(stamp_ns - last.stamp_ns) <= PRIOR_MAX_AGE_NS:
            return PlanarPose(last.x, last.y, last.theta)
        return None

    def _solve_all(self, frame_sets: list[FrameSet], now_ns: int) -> list[Outgoing]:
        out: list[Outgoing] = []
        for fs in frame_sets:
            out.extend(self._solve(fs, now_ns))
        return out

    def _solve(self, fs: FrameSet, now_ns: int) -> list[Outgoing]:
        import time

        track = self._track(fs.robot_id) if fs.robot_id else next(iter(self.tracks.values()))
        if track is None:
            return []
        t0 = time.perf_counter()
        result = estimate_pose(fs, self.site_model, self._prior(track, fs.stamp_ns), self.solver)
        self.stats.latency("solve", time.perf_counter() - t0)
        if not result.ok or result.estimate is None:
            self.stats.count("no_estimate")
            self.stats.count(f"no_estimate.{result.reason.split(':')[0][:40]}")
            return []
        self.stats.count("estimates")
        out = [self._publish_camera(track, result.estimate, now_ns)]
        if track.static(fs.stamp_ns, self._dwell_ns):
            averaged = track.averager.add(result)
            if averaged is not None and averaged.estimate is not None:
                out.append(self._publish_camera(track, averaged.estimate, now_ns))
                out.extend(self._fuse(track, averaged.estimate))
                track.averager.reset()
        else:
            track.averager.reset()
            out.extend(self._fuse(track, result.estimate))
        return out

    def _publish_camera(self, track: RobotTrack, est: PoseEstimate, now_ns: int) -> Outgoing:
        est = dataclasses.replace(est, seq=track.seq_camera, frame_id=self.site_model.world_frame)
        track.seq_camera += 1
        track.last_camera = est
        self.stats.event("camera_estimates")
        latency_s = max(0, now_ns - est.stamp_ns) * 1e-9
        self.stats.latency("stamp_to_pose", latency_s)
        if self.view is not None:
            self.view.pose(est, "camera")
            self.view.latency(est.stamp_ns, "stamp_to_pose", latency_s)
        self._log_error(track, est.stamp_ns, "camera", est)
        return Outgoing(keys.camera_pose_key(self.site, track.robot_id), est)

    def _fuse(self, track: RobotTrack, est: PoseEstimate) -> list[Outgoing]:
        fused = track.fusion.add_camera_estimate(est)
        return [] if fused is None else [self._publish_fused(track, fused)]

    def _log_error(self, track: RobotTrack, stamp_ns: int, kind: str, est: PoseEstimate) -> None:
        if self.view is None or not track.ground_truth:
            return
        truth = track.truth_at(stamp_ns)
        if truth is not None:
            self.view.error(
                track.robot_id,
                stamp_ns,
                kind,
                float(math.hypot(est.x - truth[0], est.y - truth[1])),
            )

    # ---------------------------------------------------------------------------------------

    def state(self) -> tuple[str, str]:
        anchored = [rid for rid, t in self.tracks.items() if t.fusion.anchored]
        live = sorted(self.sync.live_cameras(self._last_now())) if self._last_now() else []
        return (
            "ok",
            f"cameras live: {','.join(live) or '-'}; robots localized: {','.join(anchored) or '-'}",
        )

    def _last_now(self) -> int:
        stamps = [t.last_odometry.stamp_ns for t in self.tracks.values() if t.last_odometry]
        return max(stamps) if stamps else 0

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update({f"sync.{k}": int(v) for k, v in self.sync.counters.items()})
        for rid, t in self.tracks.items():
            out.update({f"fusion.{rid}.{k}": int(v) for k, v in t.fusion.counters.items()})
        return out

    def close(self) -> None:
        if self.view is not None:
            self.view.close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge backend",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", required=True, help="site file")
    parser.add_argument("--id", default="main", help="instance id (default: main)")
    parser.add_argument(
        "--rerun",
        default="save:smartedge.rrd",
        help="save:PATH.rrd (default save:smartedge.rrd), spawn, connect[:URL], "
        "serve (gRPC + web viewer) or none",
    )
    parser.add_argument(
        "--solver",
        choices=("default", "ipopt", "sqpmethod", "lm"),
        default="default",
        help="pose solver (default: the measured fastest)",
    )
    parser.add_argument(
        "--robust-loss",
        choices=("none", "huber", "cauchy"),
        default="huber",
        help="robust loss against keypoint outliers (default: huber)",
    )
    add_session_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> BackendNode:
    site = load_site(args.site)
    solver = SolverConfig(robust_loss=args.robust_loss)
    if args.solver != "default":
        solver = dataclasses.replace(solver, method=args.solver)
    view = None
    if args.rerun != "none":
        from backend_service.rerun_view import RerunTarget, RerunView

        view = RerunView(site, RerunTarget.parse(args.rerun))
    return BackendNode(site, args.id, solver=solver, view=view)


def main(argv: Sequence[str]) -> int:
    return service_main("backend", argv, build_parser, build_node)
