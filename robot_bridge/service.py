"""``smartedge robot-bridge``: between one robot's navigation stack and the smartedge network.

Robot side (an adapter): odometry and the robot's own localization in, pose corrections out.
Network side: publishes :class:`protocol.Odometry` on ``.../robot/<id>/odom``, the robot's own
localization as a ``PoseEstimate`` (source ``robot``) on ``.../localization``, every correction
pushed on ``.../correction``; listens to the backend's fused (``.../pose``) and camera-only
(``.../camera_pose``) estimates and to the backend's liveliness.

The robot never waits on the bridge: the worker loop reads the adapter and returns; when the
backend or the link is gone the status says so and nothing else changes for the robot.

Adapters: ``sim`` (the simulated robot of :mod:`simulation.live`, which also publishes ground
truth on ``.../ground_truth``), ``ros2`` (ROS 2 through zenoh-bridge-ros2dds), ``ros1``
(zenoh-plugin-ros1); see docs/robot_bridge.md.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from protocol import keys
from protocol.messages import Message, PoseEstimate
from protocol.runtime import Outgoing, ServiceNode, Subscription, service_main
from protocol.session import add_session_arguments
from protocol.site import Site, load_site
from robot_bridge.adapters.base import RobotAdapter
from robot_bridge.bridge import BridgeConfig, RobotBridge

log = logging.getLogger(__name__)

LOCALIZATION_PERIOD_NS = 100_000_000  # publish the robot's own pose at 10 Hz


class RobotBridgeNode(ServiceNode):
    """The bridge core (:class:`RobotBridge`) on a robot adapter, as a service node.

    ``adapter_factory(session)`` builds the adapter once the Zenoh session is open (the ROS
    adapters are Zenoh clients themselves); ``advance(now_ns)`` optionally steps a simulated
    robot before each pump; ``ground_truth(now_ns)`` optionally returns the true pose."""

    service = "robot-bridge"

    def __init__(
        self,
        site: Site,
        robot_id: str,
        adapter_factory: Any,
        *,
        correction_source: str = "fused",
        advance: Any = None,
        ground_truth: Any = None,
        tick_period_s: float = 0.05,
    ) -> None:
        super().__init__(site.name, robot_id)
        site.robot_model(robot_id)  # clear KeyError for an unknown robot
        self.robot_id = robot_id
        self.bridge = RobotBridge(
            BridgeConfig(robot_id, site.thresholds, world_frame=site.world_frame)
        )
        self._adapter_factory = adapter_factory
        self.adapter: RobotAdapter | None = None
        self._correction_source = correction_source
        self._advance = advance
        self._ground_truth = ground_truth
        self.tick_period_s = tick_period_s
        self._next_localization_ns = 0
        self._seq = {"localization": 0, "ground_truth": 0}
        self._frame = site.world_frame

    def attach(self, session: Any) -> None:
        self.adapter = self._adapter_factory(session)

    def subscriptions(self) -> Sequence[Subscription]:
        topic = "pose" if self._correction_source == "fused" else "camera_pose"
        return [
            Subscription(
                keys.robot_key(self.site, self.robot_id, topic), PoseEstimate, capacity=64
            ),
            Subscription(keys.alive_key(self.site, "backend", "*"), liveliness=True),
        ]

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        assert isinstance(message, PoseEstimate)
        self.stats.event("estimates")
        self.bridge.on_backend_heartbeat(recv_ns)
        return self._outgoing(self.bridge.on_pose_estimate(message, recv_ns), push=True)

    def alive(self, key: str, present: bool) -> None:
        import time

        if present:
            self.bridge.on_backend_heartbeat(time.time_ns())
        else:
            self.bridge.on_backend_gone(time.time_ns())

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        if self.adapter is None:
            return []
        if self._advance is not None:
            self._advance(now_ns)
        out = self._outgoing(self.bridge.pump(self.adapter, now_ns), push=False)
        if now_ns >= self._next_localization_ns:
            self._next_localization_ns = now_ns + LOCALIZATION_PERIOD_NS
            out.extend(self._poses(now_ns))
        return out

    def _outgoing(self, box: Any, *, push: bool) -> list[Outgoing]:
        out = []
        for odom in box.odometry:
            self.stats.event("odometry")
            out.append(Outgoing(keys.odom_key(self.site, self.robot_id), odom))
        for correction in box.corrections:
            if push and self.adapter is not None:
                # a correction decided on an incoming estimate: push it to the robot now
                try:
                    accepted = bool(self.adapter.apply_correction(correction))
                except Exception:
                    log.exception("adapter failed to apply a correction")
                    accepted = False
                self.bridge.on_correction_result(correction, accepted)
            self.stats.count(f"corrections_{correction.kind}")
            log.info(
                "%s pushed to %s: (%.3f, %.3f, %.1f deg), offset %.3f m",
                correction.kind,
                self.robot_id,
                correction.x,
                correction.y,
                np.degrees(correction.theta),
                correction.offset_m,
            )
            out.append(Outgoing(keys.correction_key(self.site, self.robot_id), correction))
        return out

    def _poses(self, now_ns: int) -> list[Outgoing]:
        out = []
        loc = self.adapter.read_localization() if self.adapter is not None else None
        if loc is not None and not getattr(loc, "lost", False):
            cov = loc.covariance if loc.covariance is not None else np.diag([1e-2, 1e-2, 1e-3])
            est = PoseEstimate(
                self.robot_id,
                int(loc.stamp_ns),
                self._seq["localization"],
                float(loc.x),
                float(loc.y),
                float(loc.theta),
                np.asarray(cov),
                "robot",
                frame_id=self._frame,
            )
            self._seq["localization"] += 1
            out.append(Outgoing(keys.localization_key(self.site, self.robot_id), est))
        if self._ground_truth is not None:
            x, y, theta = self._ground_truth(now_ns)
            est = PoseEstimate(
                self.robot_id,
                now_ns,
                self._seq["ground_truth"],
                float(x),
                float(y),
                float(theta),
                np.zeros((3, 3)),
                "ground_truth",
                frame_id=self._frame,
            )
            self._seq["ground_truth"] += 1
            out.append(Outgoing(keys.ground_truth_key(self.site, self.robot_id), est))
        return out

    def state(self) -> tuple[str, str]:
        status = self.bridge.status()
        state = status.state if status.state in ("starting", "ok", "degraded") else "ok"
        return state, status.detail

    def peers_alive(self) -> Sequence[str]:
        return ("backend",) if self.bridge.backend_alive() else ()

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update({f"bridge.{k}": int(v) for k, v in self.bridge.counters.items()})
        if self.adapter is not None:
            out.update({f"adapter.{k}": int(v) for k, v in dict(self.adapter.counters).items()})
        return out

    def close(self) -> None:
        if self.adapter is not None:
            try:
                self.adapter.close()
            except Exception:
                log.exception("closing the robot adapter failed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge robot-bridge",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", help="site file (with --adapter sim: default the scenario's)")
    parser.add_argument("--robot", help="robot id in the site file (default: the only robot)")
    parser.add_argument("--adapter", choices=("ros2", "ros1", "sim"), default="ros2")
    parser.add_argument(
        "--robot-profile",
        choices=("hsr", "nav2"),
        default="hsr",
        help="ROS topic set: HSR (laser_2d_correct_pose) or Nav2 (initialpose)",
    )
    parser.add_argument("--ros-namespace", default="", help="zenoh-bridge namespace")
    parser.add_argument("--correction-topic", help="override the correction topic")
    parser.add_argument("--odom-topic", help="override the odometry topic")
    parser.add_argument(
        "--correction-source",
        choices=("fused", "cameras"),
        default="fused",
        help="which backend estimate corrections are made from",
    )
    parser.add_argument(
        "--no-feedback",
        action="store_true",
        help="publish odometry but never push corrections to the robot",
    )
    parser.add_argument(
        "--kidnapped",
        action="store_true",
        help="sim adapter: the robot starts without localization",
    )
    add_session_arguments(parser)
    from simulation.live import add_sim_arguments

    add_sim_arguments(parser)
    return parser


def _ros_factory(args: argparse.Namespace):
    import dataclasses

    from robot_bridge.adapters.ros2 import RosTopics, RosZenohAdapter

    ros1 = args.adapter == "ros1"
    if args.robot_profile == "hsr":
        topics = RosTopics.hsr(ros1=ros1, namespace=args.ros_namespace)
    else:
        topics = dataclasses.replace(RosTopics.nav2(namespace=args.ros_namespace), ros1=ros1)
    if args.correction_topic:
        topics = dataclasses.replace(topics, correction_topic=args.correction_topic)
    if args.odom_topic:
        topics = dataclasses.replace(topics, odometry_topic=args.odom_topic)
    return lambda session: RosZenohAdapter(session, topics)


class _NoFeedback(RobotAdapter):
    """Wraps an adapter and refuses every correction (the "w/o correction feedback" runs)."""

    def __init__(self, inner: RobotAdapter) -> None:
        super().__init__()
        self.inner = inner
        self.name = f"{inner.name}(no feedback)"

    def read_odometry(self):
        return self.inner.read_odometry()

    def read_localization(self):
        return self.inner.read_localization()

    def apply_correction(self, correction) -> bool:
        return False

    def close(self) -> None:
        self.inner.close()


def build_node(args: argparse.Namespace) -> RobotBridgeNode:
    advance = ground_truth = None
    if args.adapter == "sim":
        from robot_bridge.adapters.sim import SimRobotAdapter
        from simulation.live import LiveSimulation, spec_from_args

        live = LiveSimulation(spec_from_args(args))
        site = load_site(args.site) if args.site else live.site
        sim_adapter = SimRobotAdapter(live.run.robot, localized=not args.kidnapped)

        def factory(session: Any) -> RobotAdapter:
            return sim_adapter

        def advance(now_ns: int) -> None:
            sim_adapter.advance_to(live.t_s(now_ns))

        def ground_truth(now_ns: int) -> np.ndarray:
            return live.ground_truth(now_ns)

        robot_id = args.robot or live.robot_id
    else:
        if not args.site:
            raise ValueError("--site is required with a ROS adapter")
        site = load_site(args.site)
        factory = _ros_factory(args)
        robot_id = args.robot or next(iter(site.robots))
    if args.no_feedback:
        inner_factory = factory

        def factory(session: Any) -> RobotAdapter:
            return _NoFeedback(inner_factory(session))

    return RobotBridgeNode(
        site,
        robot_id,
        factory,
        correction_source=args.correction_source,
        advance=advance,
        ground_truth=ground_truth,
    )


def main(argv: Sequence[str]) -> int:
    return service_main("robot-bridge", argv, build_parser, build_node)
