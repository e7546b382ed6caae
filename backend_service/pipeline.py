"""The per-robot backend pipeline: messages in, estimates out. Transport-free, one object.

Everything that turns detections and odometry into poses happens here, in one place, driven the
same way by the backend service (:mod:`backend_service.service`), the paper's experiments
(``smartedge evaluate paper``), ``smartedge bench backend`` and replays:

0. **detections to robots** (a site with several robots): each camera message's unnamed
   detections are named after the robot each is (:class:`~backend_service.association.
   DetectionRouter`: every robot's :meth:`RobotTrack.prediction` at the image's stamp, its
   keypoints reprojected, a gated optimal assignment; ambiguous and unmatched detections are
   counted and left out); a site with one robot skips this, its unnamed detections are its own;
1. **sync**: :class:`~backend_service.sync.FrameSetSynchronizer` groups per-camera detections
   into frame-sets;
2. **prior**: one rule (:meth:`RobotTrack.prior`) picks the pose a solve starts from
   (``PipelineConfig.prior``): the fused pose, or the robot's own localization, falling back
   to a recent camera estimate; none means PnP initialization (kidnapped robot);
3. **solve**: :func:`~backend_service.estimate.estimate_pose` (CasADi; the single-camera
   heuristic inside it);
4. **averaging while static**: the one static detector of :mod:`core.geometry`, fed with the
   robot's odometry, decides when the robot stands still; then ``multi_frame.count``
   consecutive agreeing estimates are averaged (:class:`~backend_service.multi_frame.
   MultiFrameAverager`) and the average is flagged ``multi_frame``;
5. **pose graph**: camera estimates (single frames while moving when ``fuse_while_moving``,
   averages while static) and odometry go into :class:`~backend_service.fusion.
   PoseGraphFusion`; each odometry sample yields the fused pose at its stamp;
6. **camera health**: every solved frame-set with enough cameras also feeds
   :class:`~backend_service.camera_health.CameraHealthMonitor` (each camera's residual bias
   against the pose the other cameras agree on); a camera judged moved is named in
   :meth:`BackendPipeline.problems` and, with ``camera_health.action: exclude``, its detections
   are left out of every solve (counted ``camera_health.excluded_views``) until it is
   recalibrated (its calibrated pose in ``site`` changes: assign a new :class:`Site` to
   :attr:`BackendPipeline.site`), :meth:`BackendPipeline.reset_camera_health` or a restart.

Several backends sharing a site's robots: :meth:`BackendPipeline.set_active` names the robots
whose steps 1-6 run here; of the others only their odometry and the fused poses their owners
publish (:meth:`BackendPipeline.on_external_pose`) are kept, as their predictions in step 0
(carried forward by the odometry) and as the first prior when this backend takes one over.

Inputs are the wire messages in arrival order (:meth:`BackendPipeline.feed`) plus the clock
(:meth:`BackendPipeline.poll`); outputs are :class:`PipelineOutput` records: the camera
estimates and fused poses exactly as they are published (``seq`` and ``frame_id`` set), and one
:class:`SolveRecord` per frame-set for whoever wants to look inside (viewer, experiments, tests).
Time comes from message stamps and the ``now_ns`` the caller passes; nothing here reads the
wall clock for a decision (the solve latency is measured for the status only).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from collections.abc import Callable, Collection, Mapping
from typing import TYPE_CHECKING

import numpy as np

from backend_service.association import RobotPrediction
from backend_service.camera_health import CameraHealthMonitor, NoiseModel
from backend_service.detection_router import DetectionRouter
from backend_service.estimate import PoseResult, estimate_pose, solver_views
from backend_service.frame_set import FrameSet
from backend_service.pipeline_config import Fusion, PipelineConfig
from backend_service.robot_track import RobotTrack
from backend_service.sync import PROBLEM_HOLD_NS, FrameSetSynchronizer
from core.pose import PlanarPose
from core.site import Site
from protocol.messages import Message, Odometry, PoseEstimate, RobotDetections

if TYPE_CHECKING:  # gtsam is imported only where the pose graph is built
    from backend_service.fusion import FusionConfig

log = logging.getLogger(__name__)


#: robot id → a fresh pose graph for that robot (``None``: no fusion, camera estimates only)
FusionFactory = Callable[[str], Fusion]


@dataclasses.dataclass(frozen=True, eq=False)
class SolveRecord:
    """One frame-set's trip through the pipeline.

    ``prior``: the pose the solve started from (``None``: PnP) and ``prior_source`` which one
    (``fused``, ``localization``, ``camera``, ``external``: the pose another backend published,
    carried forward by the odometry, after a takeover; or ``none``); ``result``: the solver's
    outcome;
    ``static``: the robot stood still at the frame-set's stamp; ``averaged``: the multi-frame
    average this solve completed (or ``None``); ``solve_s``: wall time of the solve;
    ``prior_covariance``: the prior's covariance the solve was given (or ``None``).
    """

    robot_id: str
    frame_set: FrameSet
    prior: PlanarPose | None
    prior_source: str
    result: PoseResult
    static: bool
    averaged: PoseEstimate | None
    solve_s: float
    prior_covariance: np.ndarray | None = None


@dataclasses.dataclass
class PipelineOutput:
    """What one input produced, in order: ``camera`` estimates (single frames and averages,
    for ``.../camera_pose``), ``fused`` poses (for ``.../pose``), ``solves`` (one per
    frame-set). Outputs of several calls add up with ``+=``."""

    camera: list[PoseEstimate] = dataclasses.field(default_factory=list)
    fused: list[PoseEstimate] = dataclasses.field(default_factory=list)
    solves: list[SolveRecord] = dataclasses.field(default_factory=list)

    def __iadd__(self, other: PipelineOutput) -> PipelineOutput:
        self.camera.extend(other.camera)
        self.fused.extend(other.fused)
        self.solves.extend(other.solves)
        return self

    def __bool__(self) -> bool:
        return bool(self.camera or self.fused or self.solves)


class BackendPipeline:
    """Sync → prior → solve → averaging while static → pose graph, for every robot of a site.

    ``fusion_factory``: builds one pose graph per robot (default: GTSAM's
    :class:`~backend_service.fusion.PoseGraphFusion` with ``fusion_config``); pass ``None``
    explicitly through ``with_fusion=False`` for camera estimates only. ``deferred_upkeep``
    (default): the pose graphs' marginalizations wait for :meth:`maintain` (the service's idle
    time; :meth:`step` runs it), inline only once overdue; ``False``: inline, in the message
    that filled the window. Not thread-safe: one worker loop drives it.
    """

    def __init__(self, site: Site, config: PipelineConfig | None = None, *,
                 fusion_config: FusionConfig | None = None,
                 fusion_factory: FusionFactory | None = None,
                 with_fusion: bool = True,
                 deferred_upkeep: bool = True) -> None:
        self.site = site
        self.config = config or PipelineConfig.from_site(site)
        if with_fusion and fusion_factory is None:
            from backend_service.fusion import FusionConfig, PoseGraphFusion

            fcfg = fusion_config or FusionConfig()

            def fusion_factory(robot_id: str) -> Fusion:
                return PoseGraphFusion(robot_id, fcfg, site.clock,
                                       deferred_marginalization=deferred_upkeep)
        self._fusion_factory = fusion_factory if with_fusion else None

        #: several robots: unnamed detections go to robots by where each is expected to be
        self.router: DetectionRouter | None = (
            DetectionRouter(site, self.config.association) if len(site.robots) > 1 else None)
        # several robots: a robot's frame-set waits only for the cameras that can see it
        self.sync = FrameSetSynchronizer(
            site, relevant_cameras=self._cameras_seeing if self.router is not None else None)
        self.tracks: dict[str, RobotTrack] = {
            rid: RobotTrack(rid, self.config,
                            fusion_factory(rid) if with_fusion and fusion_factory else None,
                            site.world_frame, site.clock,
                            round(site.thresholds.sync_window_ms * 1e6))
            for rid in site.robots
        }
        self.counters: collections.Counter[str] = collections.Counter()
        solver = self.config.solver
        self.camera_health = CameraHealthMonitor(
            self.config.camera_health,
            NoiseModel(solver.covariance_floor_px, solver.error_model.detection_shift_sigma_px,
                       solver.error_model.detection_scale_sigma))
        self._future_at: dict[str, int] = {}  # counter -> arrival time of the last drop
        self._fusion_resets_seen: dict[str, int] = {}
        self._standby = False  # some robot is run by another backend (set_active)
        #: the robots' predictions for the latest image stamp routed (stamp, by robot)
        self._predictions: tuple[int, dict[str, RobotPrediction | None]] | None = None
        self._fusion_reset_at: dict[str, int] = {}

    # -- inputs ------------------------------------------------------------------------------

    def feed(self, message: Message, arrival_ns: int) -> PipelineOutput:
        """One wire message as it arrived (``arrival_ns`` on the backend's clock). Detections,
        odometry and the robot's own localization (``PoseEstimate`` with source ``robot``) are
        used; anything else is ignored (counted ``ignored``). Odometry and localization stamped
        further ahead of ``arrival_ns`` than the site's clock policy allows
        (``clock.max_future_ms``) are dropped (``odometry_future``,
        ``localization_future``): one such stamp would otherwise freeze the fusion."""
        if isinstance(message, RobotDetections):
            return self.on_detections(message, arrival_ns)
        if isinstance(message, Odometry):
            if self._future(message.stamp_ns, arrival_ns, "odometry_future"):
                return PipelineOutput()
            return self.on_odometry(message)
        if isinstance(message, PoseEstimate) and message.source == "robot":
            if not self._future(message.stamp_ns, arrival_ns, "localization_future"):
                self.on_localization(message)
            return PipelineOutput()
        self.counters["ignored"] += 1
        return PipelineOutput()

    def set_active(self, robot_ids: Collection[str] | None) -> None:
        """Run the full pipeline (solve, averaging, pose graph) only for ``robot_ids``
        (``None``: every robot, the default): several backends share a site's robots, each
        runs the robots it owns. The others keep only what matching detections to robots
        needs: their odometry and the poses their owners publish (:meth:`on_external_pose`),
        for their predictions; their detections are not synchronized (counted
        ``standby.detections``; the windows open when a robot stops being run here are
        dropped, counted ``standby.frame_sets``).
        A robot that stops being run here loses its pose graph (a later takeover starts a
        fresh one, its first solve from the previous owner's last pose carried forward by the
        odometry: prior source ``external``)."""
        if all((robot_ids is None or rid in robot_ids) == t.active
               for rid, t in self.tracks.items()):
            return  # no change (the service asks on every tick)
        # the synchronizer keeps windows only for the robots run here; the open windows of
        # those leaving are skipped like any other frame-set of a robot run elsewhere
        left = self.sync.synchronize_only(
            None if robot_ids is None else [r for r in self.tracks if r in robot_ids])
        self.counters["standby.frame_sets"] += len(left)
        for rid, track in self.tracks.items():
            want = robot_ids is None or rid in robot_ids
            if want == track.active:
                continue
            track.active = want
            track.averager.reset()
            track.forget_predictions()
            self._predictions = None
            if want:
                self.counters["standby.activated"] += 1
                log.info("running the pipeline of %s", rid)
            else:
                self.counters["standby.deactivated"] += 1
                if self._fusion_factory is not None:
                    track.fusion = self._fusion_factory(rid)
                log.info("no longer running the pipeline of %s (another backend does)", rid)
        self._standby = not all(t.active for t in self.tracks.values())

    def serve_cameras(self, camera_ids: Collection[str] | None) -> None:
        """The cameras whose messages reach this pipeline (``None``: every camera of the site,
        the default). A backend serving some areas of a large site subscribes to their cameras
        only: the robots' predicted views are projected into those, and after a cold start the
        synchronizer waits for those (not for cameras whose messages never come here)."""
        ids = None if camera_ids is None else sorted(camera_ids)
        if self.router is not None:
            self.router.serve_cameras(ids)
        self.sync.expect_cameras(ids)

    @property
    def active_robots(self) -> list[str]:
        """The robots whose full pipeline runs here, sorted."""
        return sorted(rid for rid, t in self.tracks.items() if t.active)

    def on_external_pose(self, est: PoseEstimate) -> None:
        """A fused pose of a robot published by a backend (on ``.../pose``): kept for the
        robots not run here (their predictions and a takeover's prior); the echo of this
        backend's own poses, and poses of robots it runs, are ignored (counted
        ``external_pose.ignored``)."""
        track = self._track(est.robot_id)
        if track is None:
            return
        if track.active or est.source != "fused":
            self.counters["external_pose.ignored"] += 1
            return
        if track.add_external(est):
            self.counters["external_pose.used"] += 1
        else:
            self.counters["external_pose.out_of_order"] += 1

    def step(self, message: Message, arrival_ns: int) -> PipelineOutput:
        """What the service does when ``message`` arrives at ``arrival_ns``: its clock tick
        first (:meth:`poll`), the idle upkeep the worker runs before a message arrives
        (:meth:`maintain`), then the message (:meth:`feed`). Replays and experiments drive
        the pipeline with this, message by message in arrival order, and so compute what the
        service does."""
        out = self.poll(arrival_ns)
        while self.maintain():  # the worker's idle upkeep between two messages
            pass
        out += self.feed(message, arrival_ns)
        return out

    def on_detections(self, msg: RobotDetections, arrival_ns: int) -> PipelineOutput:
        if self.router is not None and msg.detections:
            msg = self._route(msg)
        if msg.detections and self._standby:
            # detections of robots another backend runs: not synchronized here
            one = next(iter(self.tracks.values())) if len(self.tracks) == 1 else None
            for det in msg.detections:
                track = self.tracks.get(det.robot_id) if det.robot_id else one
                if track is not None and not track.active:
                    self.counters["standby.detections"] += 1
        return self._solve_all(self.sync.push(msg, arrival_ns), arrival_ns)

    def _route(self, msg: RobotDetections) -> RobotDetections:
        """``msg`` with its detections named after the robots they go to (several robots:
        :class:`~backend_service.detection_router.DetectionRouter`, each robot's
        :meth:`RobotTrack.prediction` at the image's stamp on the common clock)."""
        assert self.router is not None
        cam = self.site.cameras.get(msg.camera_id)
        stamp_ns = int(msg.stamp_ns) + (int(cam.clock_offset_ns) if cam is not None else 0)
        return self.router.route(msg, self._predictions_at(stamp_ns))

    def _predictions_at(self, stamp_ns: int) -> dict[str, RobotPrediction | None]:
        """Every robot's :meth:`RobotTrack.prediction` at ``stamp_ns`` (common clock)."""
        # the images of one frame-set share one stamp: one set of predictions serves them all
        cached = self._predictions
        if cached is not None and cached[0] == stamp_ns:
            return cached[1]
        cfg = self.config.association
        predictions = {rid: t.prediction(stamp_ns, cfg) for rid, t in self.tracks.items()}
        self._predictions = (stamp_ns, predictions)
        return predictions

    def _cameras_seeing(self, robot_id: str, stamp_ns: int) -> frozenset[str] | None:
        """The synchronizer's :attr:`~backend_service.sync.FrameSetSynchronizer.relevant_cameras`
        on a site with several robots: the cameras whose detections the router can give
        ``robot_id`` at ``stamp_ns`` (those where its prediction has a keypoint in the image;
        ``None``, any camera, without a prediction). The other cameras' messages cannot add to
        its frame-set, so it does not wait for them: a robot's pose goes out when the cameras
        that can see it have reported, not when the whole site has."""
        assert self.router is not None
        return self.router.cameras_seeing(robot_id, self._predictions_at(stamp_ns))

    def poll(self, now_ns: int) -> PipelineOutput:
        """Emit the frame-sets whose wait is over at ``now_ns`` and solve them."""
        return self._solve_all(self.sync.poll(now_ns), now_ns)

    def flush(self) -> PipelineOutput:
        """Emit and solve every open frame-set (end of a recording)."""
        return self._solve_all(self.sync.flush(), None)

    def maintain(self) -> bool:
        """One slice of deferred upkeep: the due marginalization of the robot whose pose graph
        is furthest past its window (``deferred_upkeep``; pose graphs without ``maintain`` have
        none). True when one ran. The service's worker calls it when no message waits, so the
        ISAM2 rebuilds of several robots (~8 ms each, more on a loaded host) neither stack up in
        one frame-set nor delay one."""
        backlog, rid = max(((int(getattr(t.fusion, "marginalization_due", 0)), rid)
                            for rid, t in self.tracks.items() if t.fusion is not None),
                           default=(0, ""))
        if backlog <= 0:
            return False
        ran = bool(self.tracks[rid].fusion.maintain())  # type: ignore[union-attr]
        if ran:
            self.counters["upkeep.marginalizations"] += 1
        return ran

    def on_odometry(self, odom: Odometry) -> PipelineOutput:
        track = self._track(odom.robot_id)
        if track is None:
            return PipelineOutput()
        motion = track.static.update(odom.stamp_ns, odom.vx, odom.vy, odom.wz)
        if motion.still_since_ns is None:
            track.averager.reset()
        track.add_odometry(odom)
        out = PipelineOutput()
        if track.fusion is not None and track.active:
            fused = track.fusion.add_odometry(odom)
            if fused is not None:
                out.fused.append(self._stamp_fused(track, fused))
        return out

    def on_localization(self, est: PoseEstimate) -> None:
        """The robot's own localization (a prior source)."""
        track = self._track(est.robot_id)
        if track is not None:
            track.add_localization(est)

    def problems(self, now_ns: int) -> list[str]:
        """Reasons the pipeline is unhealthy at ``now_ns`` (empty when healthy): the
        synchronizer's camera problems, inputs dropped as ahead of the clock within the last
        few seconds, a fusion that restarted on a bad odometry stamp."""
        out = list(self.sync.problems(now_ns))
        for what, at in sorted(self._future_at.items()):
            if now_ns - at <= PROBLEM_HOLD_NS:
                out.append(f"{what.replace('_', ' ')} stamps ahead of the clock (dropped)")
        for rid, track in sorted(self.tracks.items()):
            counters = getattr(track.fusion, "counters", None) or {}
            resets = int(counters.get("odometry_stamp_reset", 0))
            if resets > self._fusion_resets_seen.get(rid, 0):
                self._fusion_resets_seen[rid] = resets
                self._fusion_reset_at[rid] = now_ns
            at = self._fusion_reset_at.get(rid)
            if at is not None and now_ns - at <= PROBLEM_HOLD_NS:
                out.append(f"fusion of {rid} restarted after a bad odometry stamp")
        out.extend(self.camera_health.problems())
        return out

    def reset_camera_health(self, camera_id: str | None = None) -> None:
        """Forget what the camera-health monitor gathered about ``camera_id`` (every camera
        when ``None``): a camera judged moved is back in the solve and judged afresh. A
        recalibrated camera (a new calibrated pose in :attr:`site`) needs no reset."""
        self.camera_health.reset(camera_id)

    # -- internals ---------------------------------------------------------------------------

    def _future(self, stamp_ns: int, arrival_ns: int, counter: str) -> bool:
        if not self.site.clock.too_far_ahead(stamp_ns, arrival_ns):
            return False
        self.counters[counter] += 1
        self._future_at[counter] = arrival_ns
        return True

    def _track(self, robot_id: str) -> RobotTrack | None:
        track = self.tracks.get(robot_id)
        if track is None:
            self.counters["unknown_robot"] += 1
        return track

    def _solve_all(self, frame_sets: list[FrameSet], now_ns: int | None) -> PipelineOutput:
        out = PipelineOutput()
        for fs in frame_sets:
            out += self._solve(fs)
        return out

    def _solve(self, fs: FrameSet) -> PipelineOutput:
        out = PipelineOutput()
        # an unnamed frame-set can only come from a one-robot site (the synchronizer's rule)
        track = self._track(fs.robot_id) if fs.robot_id else next(iter(self.tracks.values()))
        if track is None:
            return out
        if not track.active:  # another backend runs this robot
            self.counters["standby.frame_sets"] += 1
            return out
        prior, source, prior_cov = track.prior(fs.stamp_ns)
        health = self.camera_health
        health.check_calibration(self.site.cameras)
        excluded = health.excluded
        seen = fs  # what the cameras saw, the left-out ones too (still compared)
        if excluded and any(o.camera_id in excluded for o in fs.observations):
            kept = tuple(o for o in fs.observations if o.camera_id not in excluded)
            self.counters["camera_health.excluded_views"] += len(fs.observations) - len(kept)
            fs = FrameSet(fs.robot_id, fs.stamp_ns, kept)
        t0 = time.perf_counter()
        result = estimate_pose(fs, self.site, prior, self.config.solver, prior_cov)
        solve_s = time.perf_counter() - t0
        if (result.ok and result.T_world_robot is not None
                and len(seen.observations) > self.config.camera_health.min_other_cameras
                and health.due(track.robot_id, fs.stamp_ns)):
            ids = set(health.select(seen.camera_ids))
            self._watch_cameras(track, FrameSet(seen.robot_id, seen.stamp_ns, tuple(
                o for o in seen.observations if o.camera_id in ids)), result)
        static = track.static_at(fs.stamp_ns)
        averaged: PoseEstimate | None = None
        if not result.ok or result.estimate is None:
            self.counters["no_estimate"] += 1
            self.counters[f"no_estimate.{result.reason.split(':')[0][:40]}"] += 1
        else:
            self.counters["estimates"] += 1
            out.camera.append(self._stamp_camera(track, result.estimate))
            stop = track.motion.still_since_ns
            done = self.config.multi_frame.once_per_stop and track.averaged_stop_ns == stop
            if static:
                # standing still: single frames are not fused, their average is (once)
                avg = None if done else track.averager.add(result)
                if avg is not None and avg.estimate is not None:
                    averaged = self._stamp_camera(track, avg.estimate)
                    out.camera.append(averaged)
                    out.fused.extend(self._fuse(track, averaged))
                    track.averager.reset()
                    track.averaged_stop_ns = stop
                    self.counters["averaged"] += 1
            else:
                track.averager.reset()
                if self.config.fuse_while_moving:
                    out.fused.extend(self._fuse(track, out.camera[-1]))
        out.solves.append(SolveRecord(track.robot_id, fs, prior, source, result, static,
                                      averaged, solve_s, prior_cov))
        return out

    def _watch_cameras(self, track: RobotTrack, fs: FrameSet, result: PoseResult) -> None:
        """The camera-health monitor's look at a solved frame-set (the views as the solver
        weighed them, the joint solution)."""
        cameras, uv, w = solver_views(fs, self.site, self.config.solver)
        if len(cameras) < self.config.camera_health.min_other_cameras:
            return
        model = self.site.robot_model(fs.robot_id or None)
        assert result.T_world_robot is not None
        self.camera_health.observe(track.robot_id, fs.stamp_ns, cameras,
                                   model.keypoints_base_m, result.T_world_robot, uv, w)

    def _fuse(self, track: RobotTrack, est: PoseEstimate) -> list[PoseEstimate]:
        if track.fusion is None:
            return []
        fused = track.fusion.add_camera_estimate(est)
        return [] if fused is None else [self._stamp_fused(track, fused)]

    def _stamp_camera(self, track: RobotTrack, est: PoseEstimate) -> PoseEstimate:
        est = est.numbered(track.seq_camera, track.world_frame)
        track.seq_camera += 1
        track.last_camera = est
        return est

    def _stamp_fused(self, track: RobotTrack, fused: PoseEstimate) -> PoseEstimate:
        fused = fused.numbered(track.seq_fused, track.world_frame)
        track.seq_fused += 1
        return fused

    # -- status --------------------------------------------------------------------------------

    def counter_snapshot(self) -> Mapping[str, int]:
        """Pipeline, synchronizer and pose-graph counters (flat, dotted names)."""
        out: dict[str, int] = dict(self.counters)
        if self.router is not None:
            out.update({f"association.{k}": int(v) for k, v in self.router.counters.items()})
        out.update({f"sync.{k}": int(v) for k, v in self.sync.counters.items()})
        for cam, per in self.sync.camera_counters.items():
            out.update({f"sync.camera.{cam}.{k}": int(v) for k, v in per.items() if v})
        out.update({f"camera_health.{k}": int(v)
                    for k, v in self.camera_health.counters.items()})
        for rid, t in self.tracks.items():
            counters = getattr(t.fusion, "counters", None)
            if counters:
                out.update({f"fusion.{rid}.{k}": int(v) for k, v in counters.items()})
        return out
