"""``smartedge backend``: the backend service.

The per-robot pipeline of :mod:`backend_service.pipeline` (sync → prior → solve → single-camera
rule → averaging while static → pose graph) on the wire: detections from every edge camera,
odometry and the robot's own localization in; camera-only estimates on ``.../camera_pose`` and
the fused pose (at odometry rate) on ``.../pose`` out. The pipeline decides everything; this
module only turns messages into pipeline calls and pipeline outputs into messages
(:class:`BackendNode`, a transport-free :class:`~core.runtime.ServiceNode`) and runs it on
Zenoh (:func:`main`). Watching it is the viewer's job (``smartedge viewer``), not the backend's.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import time
from collections.abc import Iterable, Sequence
from typing import Final

from backend_service.areas import AreaMap, backend_areas
from backend_service.fusion import FusionConfig, fusion_config_from_site
from backend_service.ownership_tokens import BackendOwnership
from backend_service.pipeline import BackendPipeline, PipelineOutput
from backend_service.pipeline_config import PipelineConfig
from core.runtime import Outgoing, ServiceNode, Subscription, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from protocol import keys
from protocol.limits import QUEUE_BYTE_BUDGETS
from protocol.messages import (
    MAX_NUMBER_MAP_ENTRIES,
    Message,
    Odometry,
    PoseEstimate,
    RobotDetections,
)

log = logging.getLogger(__name__)

#: how many recent inputs the stamp-to-arrival delay floor of the freshness check looks at
INPUT_DELAY_WINDOW: Final = 256


class BackendNode(ServiceNode):
    """The backend as a transport-free node: a :class:`BackendPipeline` on message keys.

    Freshness: a pose is published only while its age is at most the site's ``clock.max_age_ms``
    (:class:`~core.site.ClockPolicy`); an older one (the worker was stalled, or its inputs
    queued) is dropped and counted (``stale_dropped``, ``stale_dropped.pose``,
    ``stale_dropped.camera_pose``). Its age is the runner's clock (:attr:`clock`, the wall clock
    under Zenoh) minus its stamp, less the smallest stamp-to-arrival delay of the recent inputs
    (never below 0): on a live site, where sensors share the backend's time base, that floor is the
    transport's few milliseconds; on a replayed recording, whose stamps are hours old, it is the
    replay's offset, so replayed poses are not all stale.

    Several backends: each backend owns a share of the robots (:class:`~backend_service.
    ownership_tokens.BackendOwnership`: liveliness tokens ``owner/<robot>/<id>``, rendezvous hashing
    over the live backends), runs the full pipeline (solve, pose graph) only for those
    (:meth:`~backend_service.pipeline.BackendPipeline.set_active`) and publishes only their
    estimates (others are counted ``ownership.withheld``). Of the other robots it keeps what
    matching detections to robots needs: their odometry and the fused poses their owners
    publish on ``.../pose`` (subscribed here), so a detection of a robot run elsewhere is still
    matched against that robot's predicted pose, never given to a robot run here for lack of
    it. A takeover starts the robot's pipeline with the previous owner's last pose, carried
    forward by the odometry, as the first prior. Until the first liveliness sync every robot
    runs (a cold start loses nothing). Without a bus (:class:`~core.runtime.
    ScriptedRunner`) every robot runs and is published.

    Areas (backend_service/areas.py): with ``areas`` (``--area``) the backend subscribes to
    the detections of those areas' cameras only (one subscription per camera key) and owns the
    robots in those areas (``area/<area>/<id>`` tokens, backend_service/ownership.py); the
    poses on the bus (``.../pose``, ``.../localization``) tell every backend which area each
    robot is in. Without ``areas`` it receives every camera.

    Load shedding: detections that waited in the input queue longer than ``max_input_delay_s``
    are dropped by the runner before they are decoded (``shed``, ``shed.<key>``), oldest first,
    and the status reports ``degraded`` with how many since the previous status.
    """

    service = "backend"

    def __init__(
        self,
        site: Site,
        instance_id: str = "main",
        *,
        config: PipelineConfig | None = None,
        fusion: FusionConfig | None = None,
        tick_period_s: float = 0.01,
        areas: Sequence[str] = (),
    ) -> None:
        super().__init__(site.name, instance_id)
        self.area_map = AreaMap(site)
        unknown = sorted(set(areas) - set(self.area_map.areas))
        if unknown:
            raise ValueError(f"areas {unknown} are not in site {site.name!r} (areas: "
                             f"{sorted(self.area_map.areas) or '-'})")
        self.areas: tuple[str, ...] = tuple(dict.fromkeys(areas))
        self.site_model = site
        # pose-graph marginalizations run when the worker is idle (idle()), not in a frame-set
        self.pipeline = BackendPipeline(site, config, fusion_config=fusion)
        if self.areas:
            self.pipeline.serve_cameras(self.area_map.cameras_of(self.areas))
        self.tick_period_s = tick_period_s
        self._peers: dict[str, bool] = {}
        self._last_now_ns = 0
        self._max_age_ns = site.clock.max_age_ns
        self._input_delays: collections.deque[int] = collections.deque(maxlen=INPUT_DELAY_WINDOW)
        self._delay_floor_ns = 0
        self._stale_run = 0
        self._shed_seen = 0
        self._contradicted_seen = 0
        self.ownership = BackendOwnership(site.name, instance_id, sorted(site.robots),
                                          started_ns=time.time_ns(),
                                          areas=self.area_map or None, own_areas=self.areas)

    def subscriptions(self) -> Sequence[Subscription]:
        s = self.site
        delay_s = self.pipeline.config.max_input_delay_s
        cams = self.area_map.cameras_of(self.areas) if self.areas else ()
        if cams and set(cams) != set(self.site_model.cameras):
            # only the cameras of its areas: one channel per camera (a backend serving every
            # camera of the site takes the one wildcard channel below: one Zenoh callback
            # thread instead of one per camera)
            detections = [Subscription(
                keys.detections_key(s, cam), RobotDetections, capacity=max(64, 4096 // len(cams)),
                max_queued_bytes=QUEUE_BYTE_BUDGETS["RobotDetections"] // len(cams),
                max_queue_delay_s=delay_s) for cam in cams]
        else:
            detections = [Subscription(keys.detections_key(s, "*"), RobotDetections,
                                       capacity=4096, max_queue_delay_s=delay_s)]
        return [
            *detections,
            Subscription(keys.odom_key(s, "*"), Odometry, capacity=4096, drop_oldest=False),
            Subscription(keys.localization_key(s, "*"), PoseEstimate, capacity=256),
            # the owners' fused poses: the predictions of the robots run by other backends
            Subscription(keys.pose_key(s, "*"), PoseEstimate, capacity=1024),
            Subscription(keys.alive_key(s, "*", "*"), liveliness=True),
            *self.ownership.subscriptions(members=False),
        ]

    def attach(self, session: object) -> None:
        self.ownership.attach(session, self.clock)

    def alive(self, key: str, present: bool) -> None:
        try:
            parsed = keys.parse_key(key)
        except ValueError:
            return
        self.ownership.alive(key, present, self.clock())
        if parsed.scope == "alive":
            self._peers[f"{parsed.topic}.{parsed.source_id}"] = present

    def peers_alive(self) -> Sequence[str]:
        return sorted(k for k, v in self._peers.items() if v)

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        self._last_now_ns = max(self._last_now_ns, recv_ns)
        if isinstance(message, RobotDetections):
            self.stats.event("detections")
        elif isinstance(message, Odometry):
            self.stats.event("odometry")
        elif isinstance(message, PoseEstimate) and key.endswith("/pose"):
            self.pipeline.on_external_pose(message)  # a backend's fused pose (maybe our own)
            self.ownership.observe(message.robot_id, message.x, message.y, message.stamp_ns)
            return []
        elif isinstance(message, PoseEstimate) and message.source != "robot":
            # only the robot's own localization belongs on .../localization
            self.stats.count("localization_wrong_source")
            return []
        elif isinstance(message, PoseEstimate):  # the robot's own: where it is, for its area
            self.ownership.observe(message.robot_id, message.x, message.y, message.stamp_ns)
        stamp_ns = getattr(message, "stamp_ns", None)
        if isinstance(stamp_ns, int):
            self._input_delays.append(recv_ns - stamp_ns)
            self._delay_floor_ns = max(0, min(self._input_delays))
        return self._publish(self.pipeline.feed(message, recv_ns), recv_ns)

    def idle(self, now_ns: int) -> bool:
        return self.pipeline.maintain()

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        self._last_now_ns = max(self._last_now_ns, now_ns)
        self.ownership.tick(now_ns)
        run = self.ownership.pipeline_robots(now_ns)
        if run is not None:
            self.pipeline.set_active(run)
        return self._publish(self.pipeline.poll(now_ns), now_ns)

    def _publish(self, out: PipelineOutput, now_ns: int) -> list[Outgoing]:
        for solve in out.solves:
            self.stats.latency("solve", solve.solve_s)
        msgs: list[Outgoing] = []
        if not (out.camera or out.fused):
            return msgs
        publish_ns = self.clock()
        for est in out.camera:
            self.stats.event("camera_estimates")
            self.stats.latency("stamp_to_pose", max(0, now_ns - est.stamp_ns) * 1e-9)
            if self._owned(est, publish_ns) and self._fresh(est, publish_ns, "camera_pose"):
                msgs.append(Outgoing(keys.camera_pose_key(self.site, est.robot_id), est))
        for fused in out.fused:
            self.stats.event("fused")
            if self._owned(fused, publish_ns) and self._fresh(fused, publish_ns, "pose"):
                msgs.append(Outgoing(keys.pose_key(self.site, fused.robot_id), fused))
        return msgs

    def _owned(self, est: PoseEstimate, publish_ns: int) -> bool:
        """Whether this backend publishes ``est``'s robot now (its owner on a shared site)."""
        if self.ownership.may_publish(est.robot_id, publish_ns):
            return True
        self.stats.count("ownership.withheld")
        return False

    def _fresh(self, est: PoseEstimate, publish_ns: int, topic: str) -> bool:
        """Whether ``est`` is young enough to publish at ``publish_ns``; counts and logs the
        stale ones (one warning per run of stale poses)."""
        age_ns = publish_ns - est.stamp_ns - self._delay_floor_ns
        if age_ns <= self._max_age_ns:
            if self._stale_run:
                log.info("publishing poses again after dropping %d stale ones", self._stale_run)
                self._stale_run = 0
            return True
        self.stats.count("stale_dropped")
        self.stats.count(f"stale_dropped.{topic}")
        if not self._stale_run:
            log.warning("dropping stale poses: %s of %s is %.2f s old (limit %.2f s)", topic,
                        est.robot_id, age_ns * 1e-9, self._max_age_ns * 1e-9)
        self._stale_run += 1
        return False

    def state(self) -> tuple[str, str]:
        tracks = self.pipeline.tracks
        anchored = [rid for rid, t in tracks.items() if t.anchored]
        now = self._last_now_ns
        live = sorted(self.pipeline.sync.live_cameras(now)) if now else []
        detail = (f"cameras live: {','.join(live) or '-'}; "
                  f"robots localized: {','.join(anchored) or '-'}")
        problems = self.pipeline.problems(now) if now else []
        router = self.pipeline.router
        if router is not None:
            # several robots: how the unnamed detections were matched to them (counters since
            # the start; docs/pose_estimation.md, "Several robots")
            c = router.counters
            detail += (f"; detections assigned {c['detections_assigned']}, ambiguous "
                       f"{c['detections_ambiguous']}, unassigned "
                       f"{c['detections_unassigned'] + c['detections_no_prediction']}")
            if router.unpredicted:
                # neither tracked nor reporting its own localization: its detections, and
                # those of its twins known only roughly, are not used
                detail += f"; no prediction: {','.join(router.unpredicted)}"
            contradicted = c["detections_id_contradicted"]
            if contradicted > self._contradicted_seen:
                problems.append(f"{contradicted - self._contradicted_seen} detections named a "
                                f"robot whose predicted pose they contradict since the last "
                                f"status")
                self._contradicted_seen = contradicted
        if self._stale_run:
            problems.append(f"{self._stale_run} stale poses dropped (the worker stalled?)")
        shed = self.stats.snapshot_counters().get("shed", 0)
        if shed > self._shed_seen:
            limit_ms = self.pipeline.config.max_input_delay_s * 1e3
            problems.append(f"shedding load: {shed - self._shed_seen} detections waited more "
                            f"than {limit_ms:.0f} ms and were dropped since the last status")
            self._shed_seen = shed
        owners = self.ownership.detail(self.clock())
        if self.ownership.duplicate:  # publishes nothing: a person must rename one backend
            problems.append(owners)
        elif owners:
            detail += f"; {owners}; runs: {','.join(self.pipeline.active_robots) or '-'}"
        if problems:
            shown = "; ".join(problems[:6]) + (f"; +{len(problems) - 6} more"
                                               if len(problems) > 6 else "")
            return "degraded", f"{shown} | {detail}"
        return "ok", detail

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update(self.pipeline.counter_snapshot())
        out.update(self.ownership.counters())
        return fit_counters(out, MAX_NUMBER_MAP_ENTRIES)

    def close(self) -> None:
        self.ownership.close()


def fit_counters(counters: dict[str, int], limit: int) -> dict[str, int]:
    """``counters`` within ``limit`` entries (a status carries at most
    :data:`~protocol.messages.MAX_NUMBER_MAP_ENTRIES`; a site with a hundred cameras has a few
    counters per camera): over it, the per-camera synchronizer counters
    (``sync.camera.<cam>.<what>``) are summed over the cameras into ``sync.cameras.<what>``
    (``counters.folded``: how many were folded); still over, the last names in sorted order
    are left out (``counters.omitted``: how many)."""
    if len(counters) <= limit:
        return counters
    out: dict[str, int] = {}
    folded = 0
    for name, value in counters.items():
        parts = name.split(".")
        if len(parts) >= 4 and parts[0] == "sync" and parts[1] == "camera":
            key = f"sync.cameras.{parts[-1]}"
            out[key] = out.get(key, 0) + int(value)
            folded += 1
        else:
            out[name] = value
    out["counters.folded"] = folded
    if len(out) > limit:
        names = sorted(n for n in out if n != "counters.folded")[:limit - 2]
        kept = {n: out[n] for n in names}
        kept["counters.folded"] = folded
        kept["counters.omitted"] = len(out) - 1 - len(names)
        out = kept
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
    parser.add_argument(
        "--area", action="append", default=[], metavar="NAME",
        help="serve only this area of the site file's areas: section (its cameras' detections, "
        "the robots in it); repeat for several. Default: the areas that list this --id under "
        "backends, else every camera",
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
    requested = getattr(args, "area", None) or []  # a hand-built Namespace may lack it
    areas = backend_areas(site, [a for v in requested for a in v.split(",") if a], args.id)
    if areas:
        log.info("backend %s serves the areas %s", args.id, ", ".join(areas))
    return BackendNode(site, args.id, config=dataclasses.replace(config, solver=solver),
                       fusion=fusion_config_from_site(site), areas=areas)


def main(argv: Sequence[str]) -> int:
    return service_main("backend", argv, build_parser, build_node)
