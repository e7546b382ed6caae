"""``smartedge robot-bridge``: between one robot's navigation stack and the smartedge network.

Robot side (an adapter): odometry and the robot's own localization in, pose corrections out.
Network side: publishes :class:`protocol.Odometry` on ``.../robot/<id>/odom``, the robot's own
localization as a ``PoseEstimate`` (source ``robot``) on ``.../localization``, every correction
pushed on ``.../correction``; listens to the backend's fused (``.../pose``) or camera-only
(``.../camera_pose``) estimates, and to the backend's status messages and liveliness token (its
only signs of life: estimates are not heartbeats). Who may put on those keys is the router's
access control (docs/robot_bridge.md, "What the bridge trusts"); the bridge checks what it can
locally (source vs key, clock tolerance, covariance floor, jump, window and floor-area limits).

The robot never waits on the bridge: the worker loop reads the adapter and returns; when the
backend or the link is gone the status says so and nothing else changes for the robot.

Adapters are plug-ins (:mod:`robot_bridge.adapters.registry`); ``--adapter`` offers the
registered ones: ``ros2`` (ROS 2 through zenoh-bridge-ros2dds), ``ros1``
(zenoh-plugin-ros1), and ``sim`` (the simulated robot, registered by ``smartedge robot-bridge``,
see :mod:`smartedge.simulated_site`); see docs/robot_bridge.md.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from core.runtime import Outgoing, ServiceNode, Subscription, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from protocol import keys
from protocol.errors import UsageError
from protocol.messages import Message, PoseEstimate, SemanticCloud, ServiceStatus
from robot_bridge.adapters.base import RobotAdapter
from robot_bridge.adapters.registry import add_adapter_arguments, get_adapter
from robot_bridge.bridge import BridgeConfig, Outbox, RobotBridge
from robot_bridge.map_output import MapOutput, MapOutputConfig

log = logging.getLogger(__name__)

LOCALIZATION_PERIOD_NS = 100_000_000  # publish the robot's own pose at 10 Hz


class RobotBridgeNode(ServiceNode):
    """The bridge core (:class:`RobotBridge`) on a robot adapter, as a service node.

    ``adapter_factory(session)`` builds the adapter once the Zenoh session is open (the ROS
    adapters are Zenoh clients themselves); ``advance(now_ns)`` optionally steps a simulated
    robot before each pump. Every correction reaches the robot through
    :meth:`RobotBridge.apply`, whether it was decided on an incoming estimate or in a pump."""

    service = "robot-bridge"

    def __init__(
        self,
        site: Site,
        robot_id: str,
        adapter_factory: Callable[[Any], RobotAdapter],
        *,
        correction_source: str = "fused",
        advance: Callable[[int], None] | None = None,
        tick_period_s: float = 0.05,
    ) -> None:
        super().__init__(site.name, robot_id)
        site.robot_model(robot_id)  # clear KeyError for an unknown robot
        self.robot_id = robot_id
        self.bridge = RobotBridge(
            BridgeConfig.from_site(site, robot_id)
        )
        self._adapter_factory = adapter_factory
        self.adapter: RobotAdapter | None = None
        self._correction_source = correction_source
        self._advance = advance
        self.tick_period_s = tick_period_s
        self._next_localization_ns = 0
        self._localization_seq = 0
        self._frame = site.world_frame
        self.map_output = MapOutput(MapOutputConfig.from_site(site), site.world_frame)

    def attach(self, session: Any) -> None:
        self.adapter = self._adapter_factory(session)

    def subscriptions(self) -> Sequence[Subscription]:
        topic = "pose" if self._correction_source == "fused" else "camera_pose"
        return [
            Subscription(
                keys.robot_key(self.site, self.robot_id, topic), PoseEstimate, capacity=64
            ),
            # the backend's heartbeat: its status (every second) and its liveliness token
            Subscription(keys.status_key(self.site, "backend", "*"), ServiceStatus, capacity=64),
            Subscription(keys.alive_key(self.site, "backend", "*"), liveliness=True),
            *self._map_subscriptions(),
        ]

    def _map_subscriptions(self) -> list[Subscription]:
        """The mapper's voxels, when the map output is on and the adapter publishes maps
        (``attach`` came first): latest only (a queue of two)."""
        config = self.map_output.config
        if not config.enabled or not self._adapter_publishes_maps():
            return []
        return [Subscription(keys.map_voxels_key(self.site, config.map_id), SemanticCloud,
                             capacity=2)]

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        if isinstance(message, ServiceStatus):
            self.stats.event("backend_status")
            if message.state == "stopping":  # its last words: gone now, not in 3 s
                self.bridge.on_backend_gone(recv_ns)
            else:
                self.bridge.on_backend_heartbeat(recv_ns)
            return []
        if isinstance(message, SemanticCloud):
            self.stats.event("maps")
            self.map_output.on_map(message)
            return []
        assert isinstance(message, PoseEstimate)
        self.stats.event("estimates")
        # the key's last chunk: the source must match it (pose -> fused, camera_pose -> cameras)
        box = self.bridge.on_pose_estimate(message, recv_ns, topic=key.rsplit("/", 1)[-1])
        if self.adapter is not None:
            # a correction decided on an incoming estimate goes to the robot now
            box = self.bridge.apply(self.adapter, box)
        return self._outgoing(box)

    def alive(self, key: str, present: bool) -> None:
        if present:
            self.bridge.on_backend_heartbeat(time.time_ns())
        else:
            self.bridge.on_backend_gone(time.time_ns())

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        if self.adapter is None:
            return []
        if self._advance is not None:
            self._advance(now_ns)
        out = self._outgoing(self.bridge.pump(self.adapter, now_ns))
        self.bridge.publish_pose_output(self.adapter, now_ns)
        self._publish_map(now_ns)
        if now_ns >= self._next_localization_ns:
            self._next_localization_ns = now_ns + LOCALIZATION_PERIOD_NS
            out.extend(self._localization())
        return out

    def _adapter_publishes_maps(self) -> bool:
        """Whether the adapter has a map output (the ROS adapters; not ``sim``)."""
        return (self.adapter is not None
                and type(self.adapter).publish_map is not RobotAdapter.publish_map)

    def _publish_map(self, now_ns: int) -> None:
        """The newest map to the robot's ROS topics, when one is due (:class:`MapOutput`)."""
        snapshot = self.map_output.due(now_ns)
        if snapshot is None or self.adapter is None:
            return
        try:
            ok = self.adapter.publish_map(snapshot)
        except Exception:  # an adapter's bug must not stop the bridge
            log.exception("publishing the map failed")
            ok = False
        self.stats.count("map_output_published" if ok else "map_output_failed")

    def _outgoing(self, box: Outbox) -> list[Outgoing]:
        """Publish what the bridge produced (corrections were already applied to the robot)."""
        out = []
        for odom in box.odometry:
            self.stats.event("odometry")
            out.append(Outgoing(keys.odom_key(self.site, self.robot_id), odom))
        for correction in box.corrections:
            self.stats.count(f"corrections_{correction.kind}")
            out.append(Outgoing(keys.correction_key(self.site, self.robot_id), correction))
        return out

    def _localization(self) -> list[Outgoing]:
        """The robot's own pose, as a ``PoseEstimate`` of source ``robot``."""
        loc = self.adapter.read_localization() if self.adapter is not None else None
        if loc is None or getattr(loc, "lost", False):
            return []
        cov = loc.covariance if loc.covariance is not None else np.diag([1e-2, 1e-2, 1e-3])
        est = PoseEstimate(
            self.robot_id,
            int(loc.stamp_ns),
            self._localization_seq,
            float(loc.x),
            float(loc.y),
            float(loc.theta),
            np.asarray(cov),
            "robot",
            frame_id=self._frame,
        )
        self._localization_seq += 1
        return [Outgoing(keys.localization_key(self.site, self.robot_id), est)]

    def state(self) -> tuple[str, str]:
        status = self.bridge.status()
        state = status.state if status.state in ("starting", "ok", "degraded") else "ok"
        return state, status.detail

    def peers_alive(self) -> Sequence[str]:
        return ("backend",) if self.bridge.backend_alive() else ()

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update({f"bridge.{k}": int(v) for k, v in self.bridge.counters.items()})
        out.update({f"map_output.{k}": int(v) for k, v in self.map_output.counters.items()})
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
    parser.add_argument(
        "--site", help="site file (optional with an adapter that brings its own site, e.g. sim)"
    )
    parser.add_argument("--robot", help="robot id in the site file (default: the only robot)")
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
    add_session_arguments(parser)
    add_adapter_arguments(parser, default="ros2")
    return parser


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
    """The bridge for ``args``: the chosen adapter plug-in builds the robot side."""
    site = load_site(args.site) if args.site else None
    setup = get_adapter(args.adapter).build(args, site)
    site = site or setup.site
    if site is None:
        raise UsageError(f"--site is required with --adapter {args.adapter}")
    robot_id = args.robot or setup.robot_id or next(iter(site.robots))
    factory = setup.factory
    if args.no_feedback:
        inner_factory = factory

        def factory(session: Any) -> RobotAdapter:
            return _NoFeedback(inner_factory(session))

    return RobotBridgeNode(
        site,
        robot_id,
        factory,
        correction_source=args.correction_source,
        advance=setup.advance,
    )


def main(argv: Sequence[str]) -> int:
    return service_main("robot-bridge", argv, build_parser, build_node)
