"""``smartedge backend``: the backend service.

The per-robot pipeline of :mod:`backend_service.pipeline` (sync → prior → solve → single-camera
rule → averaging while static → pose graph) on the wire: detections from every edge camera,
odometry and the robot's own localization in; camera-only estimates on ``.../camera_pose`` and
the fused pose (at odometry rate) on ``.../pose`` out. The pipeline decides everything; this
module only turns messages into pipeline calls and pipeline outputs into messages
(:class:`BackendNode`, a transport-free :class:`~protocol.runtime.ServiceNode`) and runs it on
Zenoh (:func:`main`). Watching it is the viewer's job (``smartedge viewer``), not the backend's.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from collections.abc import Iterable, Sequence

from backend_service.fusion import FusionConfig, fusion_config_from_site
from backend_service.pipeline import BackendPipeline, PipelineConfig, PipelineOutput
from protocol import keys
from protocol.messages import Message, Odometry, PoseEstimate, RobotDetections
from protocol.runtime import Outgoing, ServiceNode, Subscription, service_main
from protocol.session import add_session_arguments
from protocol.site import Site, load_site

log = logging.getLogger(__name__)



class BackendNode(ServiceNode):
    """The backend as a transport-free node: a :class:`BackendPipeline` on message keys."""

    service = "backend"

    def __init__(
        self,
        site: Site,
        instance_id: str = "main",
        *,
        config: PipelineConfig | None = None,
        fusion: FusionConfig | None = None,
        tick_period_s: float = 0.01,
    ) -> None:
        super().__init__(site.name, instance_id)
        self.site_model = site
        self.pipeline = BackendPipeline(site, config, fusion_config=fusion)
        self.tick_period_s = tick_period_s
        self._peers: dict[str, bool] = {}
        self._last_now_ns = 0

    def subscriptions(self) -> Sequence[Subscription]:
        s = self.site
        return [
            Subscription(keys.detections_key(s, "*"), RobotDetections, capacity=4096),
            Subscription(keys.odom_key(s, "*"), Odometry, capacity=4096, drop_oldest=False),
            Subscription(keys.localization_key(s, "*"), PoseEstimate, capacity=256),
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

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        self._last_now_ns = max(self._last_now_ns, recv_ns)
        if isinstance(message, RobotDetections):
            self.stats.event("detections")
        elif isinstance(message, Odometry):
            self.stats.event("odometry")
        elif isinstance(message, PoseEstimate) and message.source != "robot":
            # only the robot's own localization belongs on .../localization
            self.stats.count("localization_wrong_source")
            return []
        return self._publish(self.pipeline.feed(message, recv_ns), recv_ns)

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        self._last_now_ns = max(self._last_now_ns, now_ns)
        return self._publish(self.pipeline.poll(now_ns), now_ns)

    def _publish(self, out: PipelineOutput, now_ns: int) -> list[Outgoing]:
        for solve in out.solves:
            self.stats.latency("solve", solve.solve_s)
        msgs: list[Outgoing] = []
        for est in out.camera:
            self.stats.event("camera_estimates")
            self.stats.latency("stamp_to_pose", max(0, now_ns - est.stamp_ns) * 1e-9)
            msgs.append(Outgoing(keys.camera_pose_key(self.site, est.robot_id), est))
        for fused in out.fused:
            self.stats.event("fused")
            msgs.append(Outgoing(keys.pose_key(self.site, fused.robot_id), fused))
        return msgs

    def state(self) -> tuple[str, str]:
        tracks = self.pipeline.tracks
        anchored = [rid for rid, t in tracks.items() if t.anchored]
        now = self._last_now_ns
        live = sorted(self.pipeline.sync.live_cameras(now)) if now else []
        return (
            "ok",
            f"cameras live: {','.join(live) or '-'}; robots localized: {','.join(anchored) or '-'}",
        )

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update(self.pipeline.counter_snapshot())
        return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="smartedge backend",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", required=True, help="site file")
    parser.add_argument("--id", default="main", help="instance id (default: main)")
    parser.add_argument(
        "--solver",
        choices=("ipopt", "sqpmethod", "lm", "gauss_newton"),
        help="pose solver (default: the site file's pose.method, else the measured fastest)",
    )
    parser.add_argument(
        "--robust-loss",
        choices=("none", "huber", "cauchy"),
        help="robust loss against keypoint outliers (default: the site file's "
        "pose.robust_loss, else the solver's default, cauchy)",
    )
    add_session_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> BackendNode:
    site = load_site(args.site)
    config = PipelineConfig.from_site(site)
    solver = config.solver
    if args.robust_loss is not None:
        solver = dataclasses.replace(solver, robust_loss=args.robust_loss)
    if args.solver is not None:
        solver = dataclasses.replace(solver, method=args.solver)
    return BackendNode(site, args.id, config=dataclasses.replace(config, solver=solver),
                       fusion=fusion_config_from_site(site))


def main(argv: Sequence[str]) -> int:
    return service_main("backend", argv, build_parser, build_node)
