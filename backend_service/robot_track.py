"""The pipeline's state for one robot (:class:`RobotTrack`): its static detector, averager and
pose graph, the sources a solve's prior comes from (the fused pose, its own localization, a pose
another backend published, carried forward with odometry), its predictions for the
association, and the sequence numbers of what it publishes.
"""

from __future__ import annotations

import collections
from typing import Final

import numpy as np

from backend_service.association import AssociationConfig, RobotPrediction, predicted_covariance
from backend_service.multi_frame import MultiFrameAverager
from backend_service.pipeline_config import PRIOR_SOURCES, Fusion, PipelineConfig
from core.geometry import MotionState, StaticDetector, se2_between, se2_compose
from core.history import StampedHistory
from core.pose import PlanarPose
from core.site import ClockPolicy
from protocol.messages import Odometry, PoseEstimate

#: How many of the robot's own localization messages are kept for the prior lookup.
LOCALIZATION_BUFFER: Final = 64
#: How many recent predictions per robot are kept for reuse (:meth:`RobotTrack.prediction`).
PREDICTIONS_KEPT: Final = 4
#: How many odometry messages per robot are kept to carry another backend's pose forward.
ODOMETRY_BUFFER: Final = 512
#: How long a robot's pose published by another backend (its owner) is carried forward with
#: the robot's odometry, for its prediction and a takeover's prior (seconds).
EXTERNAL_CARRY_S: Final = 5.0
#: The largest gap between an external pose's stamp and the odometry it is carried from (ns).
_EXTERNAL_ODOM_GAP_NS: Final = 200_000_000


class RobotTrack:
    """The pipeline's state for one robot: static detector, averager, pose graph, prior
    sources, and the sequence numbers of what it publishes. ``clock``: the site's clock policy
    (a prior is used only when stamped within ``max_age_ms`` of the solve)."""

    def __init__(self, robot_id: str, config: PipelineConfig, fusion: Fusion | None,
                 world_frame: str, clock: ClockPolicy | None = None,
                 prediction_reuse_ns: int = 20_000_000) -> None:
        self.robot_id = robot_id
        self.config = config
        self.fusion = fusion
        self.world_frame = world_frame
        self.static = StaticDetector(config.static_max_speed_mps,
                                     config.static_max_yaw_rate_radps, config.static_dwell_s)
        self.averager = MultiFrameAverager.from_config(config.multi_frame)
        self.last_camera: PoseEstimate | None = None
        self.last_odometry: Odometry | None = None
        #: the stop (its still-since stamp) that already has its average
        self.averaged_stop_ns: int | None = None
        self.seq_camera = 0
        self.seq_fused = 0
        #: whether this backend runs the robot's pipeline (solve, fusion); a robot run by
        #: another backend keeps only its prediction (:meth:`BackendPipeline.set_active`)
        self.active = True
        #: the newest pose of the robot published by the backend that runs it (a robot this
        #: backend does not run): its prediction, and a takeover's prior
        self.external: PoseEstimate | None = None
        self._odometry: StampedHistory[Odometry] = StampedHistory(ODOMETRY_BUFFER,
                                                                  out_of_order="insert")
        self._external_carry_ns = round(EXTERNAL_CARRY_S * 1e9)
        self._dwell_ns = round(config.static_dwell_s * 1e9)
        self._max_age_ns = (clock if clock is not None else ClockPolicy()).max_age_ns
        # the robot's own localization; messages may overtake each other on the way
        self._localization: StampedHistory[PoseEstimate] = StampedHistory(
            LOCALIZATION_BUFFER, out_of_order="insert")
        self._prediction_reuse_ns = int(prediction_reuse_ns)
        # recent predictions (stamp, prediction): images of neighbouring frame-sets may arrive
        # interleaved, each group reuses its own
        self._predictions: collections.deque[tuple[int, RobotPrediction | None]] = (
            collections.deque(maxlen=PREDICTIONS_KEPT))

    @property
    def motion(self) -> MotionState:
        return self.static.state

    @property
    def anchored(self) -> bool:
        return self.fusion is not None and self.fusion.anchored

    def static_at(self, stamp_ns: int) -> bool:
        """The robot had stood still for the dwell time at ``stamp_ns``."""
        since = self.static.state.still_since_ns
        return since is not None and stamp_ns - since >= self._dwell_ns

    def add_localization(self, est: PoseEstimate) -> None:
        self._localization.insert(est.stamp_ns, est)

    def add_odometry(self, odom: Odometry) -> None:
        self.last_odometry = odom
        self._odometry.insert(odom.stamp_ns, odom)

    def add_external(self, est: PoseEstimate) -> bool:
        """Another backend's published pose of this robot; False when older than the one
        kept (messages may overtake each other). Like a new odometry or camera estimate of a
        robot run here, it serves the predictions of the stamps routed after it: the images
        of a frame-set already being routed keep the predictions they started with (one set
        of predictions, and one projection into every camera, per frame-set; an owner
        publishes 20 poses a second, so forgetting them made a backend project every robot
        into its cameras again several times within one frame-set)."""
        if self.external is not None and est.stamp_ns <= self.external.stamp_ns:
            return False
        self.external = est
        return True

    def forget_predictions(self) -> None:
        """Drop the predictions kept for reuse (what they came from has changed)."""
        self._predictions.clear()

    def external_at(self, stamp_ns: int) -> tuple[PlanarPose, np.ndarray, float] | None:
        """The robot's pose at ``stamp_ns`` from the newest pose its owner published: carried
        by the robot's odometry between the two stamps (each within 0.2 s of an odometry
        message), else, within the clock policy's ``max_age_ms``, as published; ``None`` when
        older than :data:`EXTERNAL_CARRY_S` or too old to use without odometry. Returns the
        pose, the published covariance and the seconds it was carried over."""
        ext = self.external
        if ext is None:
            return None
        gap_ns = abs(stamp_ns - ext.stamp_ns)
        if gap_ns > self._external_carry_ns:
            return None
        pose = np.array([ext.x, ext.y, ext.theta])
        at_ext = self._odometry.nearest(ext.stamp_ns, max_gap_ns=_EXTERNAL_ODOM_GAP_NS)
        at_now = self._odometry.nearest(stamp_ns, max_gap_ns=_EXTERNAL_ODOM_GAP_NS)
        if at_ext is not None and at_now is not None:
            a, b = at_ext.item, at_now.item
            pose = se2_compose(pose, se2_between(np.array([a.x, a.y, a.theta]),
                                                 np.array([b.x, b.y, b.theta])))
        elif gap_ns > self._max_age_ns:
            return None
        return (PlanarPose(float(pose[0]), float(pose[1]), float(pose[2])),
                np.asarray(ext.covariance, np.float64), gap_ns * 1e-9)

    def _localization_at(self, stamp_ns: int) -> PoseEstimate | None:
        near = self._localization.nearest(stamp_ns, max_gap_ns=self._max_age_ns)
        return None if near is None else near.item

    def _fused_at(self, stamp_ns: int) -> PoseEstimate | None:
        if self.fusion is None or not self.fusion.anchored:
            return None
        return self.fusion.pose_at(stamp_ns) or self.fusion.latest()

    def prior(self, stamp_ns: int) -> tuple[PlanarPose | None, str, np.ndarray | None]:
        """The pose a solve at ``stamp_ns`` starts from, its source (the one prior rule) and
        its covariance where the prior is independent of the cameras (the robot's own
        localization; ``None`` for the pose graph, which already holds the camera estimates
        and does the combining itself, and for the last camera estimate)."""
        lookups = {"fused": self._fused_at, "localization": self._localization_at,
                   "camera": self._camera_at}
        other = next(s for s in PRIOR_SOURCES if s != self.config.prior)
        # "external": after a takeover, the previous owner's last published pose (its pose
        # graph's), carried forward by the odometry; before the robot's own localization when
        # the fused pose comes first
        order = ((self.config.prior, "camera", "external", other)
                 if self.config.prior == "fused" else (self.config.prior, "camera", other,
                                                       "external"))
        for source in order:
            if source == "external":
                external = self.external_at(stamp_ns)
                if external is not None:
                    return external[0], "external", None
                continue
            est = lookups[source](stamp_ns)
            if est is not None:
                cov = est.covariance if source == "localization" else None
                return PlanarPose(est.x, est.y, est.theta), source, cov
        return None, "none", None

    def _camera_at(self, stamp_ns: int) -> PoseEstimate | None:
        last = self.last_camera
        if last is not None and abs(stamp_ns - last.stamp_ns) <= self._max_age_ns:
            return last
        return None

    def prediction(self, stamp_ns: int, config: AssociationConfig) -> RobotPrediction | None:
        """Where this robot is expected at ``stamp_ns``, for matching detections to robots
        (:mod:`backend_service.association`): the fused pose (the pose graph at the stamp, or
        its newest pose carried forward with the last odometry velocity), else the newest
        camera estimate, else the robot's own localization (its bridge; a robot the cameras
        have not localized yet) with at least the wide ``unlocalized_sigma_*`` covariance; each
        only when stamped within the clock policy's ``max_age_ms`` of ``stamp_ns``. ``None``:
        no prediction, the robot takes no unnamed detections. One prediction serves the images
        stamped within ``prediction_reuse_ns`` of it (the site's sync window: the images of one
        frame-set share it, and so one projection of all the robots into every camera,
        :class:`~backend_service.association.ViewCache`); its covariance grows by the motion
        possible over that span."""
        for cached_ns, cached in self._predictions:
            if abs(cached_ns - stamp_ns) <= self._prediction_reuse_ns:
                return cached
        pred = self._predict(stamp_ns, config)
        self._predictions.append((stamp_ns, pred))
        return pred

    def _predict(self, stamp_ns: int, config: AssociationConfig) -> RobotPrediction | None:
        candidates: list[tuple[str, PoseEstimate | None]] = []
        if self.fusion is not None and self.fusion.anchored:
            candidates.append(("fused", self.fusion.pose_at(stamp_ns) or self.fusion.latest()))
        candidates.append(("camera", self._camera_at(stamp_ns)))
        if not any(est is not None and abs(stamp_ns - est.stamp_ns) <= self._max_age_ns
                   for _, est in candidates):
            # not run here (or just taken over): the pose its owner published, carried
            # forward by the odometry; the robot's own localization only after that
            external = self.external_at(stamp_ns)
            if external is not None:
                pose, ext_cov, carried_s = external
                cov = predicted_covariance(ext_cov, carried_s + self._prediction_reuse_ns * 1e-9,
                                           "fused", config)
                return RobotPrediction(self.robot_id, pose, cov, "fused")
        candidates.append(("localization", self._localization_at(stamp_ns)))
        for source, est in candidates:
            if est is None or abs(stamp_ns - est.stamp_ns) > self._max_age_ns:
                continue
            dt_s = (stamp_ns - est.stamp_ns) * 1e-9
            x, y, theta = est.x, est.y, est.theta
            odom = self.last_odometry
            if odom is not None and dt_s != 0.0:
                # carried to the stamp with the body velocities of the last odometry
                c, s = np.cos(theta), np.sin(theta)
                x += (odom.vx * c - odom.vy * s) * dt_s
                y += (odom.vx * s + odom.vy * c) * dt_s
                theta += odom.wz * dt_s
            cov = predicted_covariance(est.covariance,
                                       abs(dt_s) + self._prediction_reuse_ns * 1e-9, source,
                                       config)
            return RobotPrediction(self.robot_id, PlanarPose(x, y, theta), cov, source)
        return None
