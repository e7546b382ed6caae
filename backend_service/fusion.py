"""Pose-graph fusion of camera pose estimates with robot odometry (paper Sec. III-B, last part).

One :class:`PoseGraphFusion` per robot keeps an incremental GTSAM ISAM2 pose graph over planar
keyframes (``Pose2`` variables of the robot base in the map frame):

- odometry between consecutive keyframes is a ``BetweenFactorPose2``; keyframes are created by a
  distance / angle / time policy (:class:`FusionConfig`) from the buffered odometry samples;
- each camera pose estimate is a unary ``PriorFactorPose2`` at the estimate's own ``stamp_ns``
  with the estimate's covariance (the solver scales it with the reprojection residual and
  inversely with the number of cameras), wrapped in a robust (Huber or Cauchy) noise model.
  Estimates arrive late (edge latency): when the stamp falls between two keyframes, a keyframe
  is inserted there by interpolating the odometry and the between factor is split in two;
- the graph is optimized (one ISAM2 update) per new keyframe and per camera estimate;
- the fused pose is published at odometry rate: the latest optimized keyframe composed with the
  odometry since that keyframe, with its marginal covariance propagated along the odometry
  (the odometry buffer is a :class:`~core.history.StampedHistory`);
- memory stays bounded: when keyframes fall out of a sliding window (time and count), the old
  part of the graph is marginalized into a Gaussian prior on the oldest kept keyframe and ISAM2
  is rebuilt over the kept keyframes. That rebuild costs ~8 ms with the default window (200
  keyframes; 17 ms with 400) on a 2-core x86 VM; a service defers it
  (``deferred_marginalization``) to :meth:`PoseGraphFusion.maintain`, which its worker calls when
  no message waits, so it does not delay the poses of the frame-set being solved.

The graph itself (keyframes, factor records, ISAM2, marginalization) is
:mod:`backend_service.keyframe_graph`'s; this module decides what enters it and when.

Initialization: the odometry frame has no anchor in the map frame until the first camera
estimate (or :meth:`PoseGraphFusion.set_initial_pose`). Before that, odometry is only buffered
(bounded) and no fused pose is produced (``None``, counted as ``uninitialized``).

Frames and units: odometry poses ``T_odom_robot`` (x, y metres, theta radians) in the robot's odom
frame; fused and camera poses ``T_world_robot`` in the map frame. ``PoseEstimate.covariance``
is taken to be the (3, 3) covariance of (x, y, theta) along the map-frame axes; GTSAM keeps
covariances in the body frame of the pose, conversions happen at the boundary. Time comes only
from message stamps. Bad input never raises: it returns ``None`` and increments
``counters[reason]`` (see docs/fusion.md for the reasons).
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
import logging
import math
from typing import Final, NamedTuple

import gtsam
import numpy as np

from backend_service.keyframe_graph import FactorBatch, GraphFactor, Keyframe, KeyframeGraph
from core.geometry import rotation_z
from core.history import StampedHistory
from core.site import ClockPolicy, Site
from protocol.messages import NS_PER_S, Odometry, PoseEstimate

logger = logging.getLogger(__name__)

ROBUST_KERNELS: Final = ("huber", "cauchy", "none")


@dataclasses.dataclass(frozen=True)
class FusionConfig:
    """Parameters of :class:`PoseGraphFusion` (SI units; sigmas are standard deviations).

    Keyframe policy: a new keyframe when the odometry moved ``keyframe_distance_m`` or turned
    ``keyframe_angle_rad`` since the last keyframe, or ``keyframe_interval_s`` passed while the
    robot moved at all (more than ``static_motion_m`` / ``static_motion_rad``: a static robot
    adds no keyframes). A camera estimate whose odometry pose is within ``static_motion_*`` of an
    existing keyframe is attached to that keyframe instead of creating a new one.

    Odometry noise is a random walk, so variances add up along the path and splitting a between
    factor at a late camera stamp does not change the information it carries:
    ``var_xy = a² d + b² |dθ| + c² dt + floor²`` with ``a = odom_sigma_xy_m_per_sqrt_m`` etc.
    With ``use_odometry_covariance`` the increment of the message covariances between the two
    keyframes is used instead when it is positive definite.

    Camera priors: robust kernel ``robust_kernel`` (``huber``, ``cauchy`` or ``none``) with
    threshold ``robust_threshold`` in sigmas; ``camera_sigma_floor_*`` is added in quadrature
    to guard against over-confident estimates; estimates with a sigma above
    ``max_camera_sigma_m`` / ``max_camera_sigma_rad`` carry no information and are rejected.
    An estimate newer than the newest odometry waits (at most ``max_pending`` of them) for the
    odometry to cover its stamp, if it is at most the site's ``clock.max_age_ms`` ahead of that
    odometry (:class:`~core.site.ClockPolicy`; else ``camera_future``).

    Poisoned stamps: odometry is accepted in stamp order, so one message stamped far in the
    future (the service drops those against its clock, but a replay has none) would make every
    later message "out of order". After ``out_of_order_reset_count`` consecutive rejected
    messages that are themselves in order and more than ``out_of_order_reset_gap_s`` older than
    the newest accepted stamp (so a replay of odometry the fusion already has, e.g. by a robot
    bridge after a link loss, never counts), the newest accepted stamp is taken as the bad one:
    the graph restarts from the new stream as after an odometry jump (``odometry_stamp_reset``).

    Window: keyframes older than ``window_s`` before the latest one, or beyond
    ``max_keyframes``, are marginalized in batches of ``marginalize_batch`` (so the graph holds
    at most ``max_keyframes + marginalize_batch - 1`` keyframes; with deferred marginalization
    at most ``max_keyframes + 2 * marginalize_batch - 1``).
    """

    keyframe_distance_m: float = 0.25
    keyframe_angle_rad: float = 0.2
    keyframe_interval_s: float = 2.0
    static_motion_m: float = 0.002
    static_motion_rad: float = 0.002

    odom_sigma_xy_m_per_sqrt_m: float = 0.05
    odom_sigma_xy_m_per_sqrt_rad: float = 0.01
    odom_sigma_xy_m_per_sqrt_s: float = 0.0
    odom_sigma_theta_rad_per_sqrt_m: float = 0.03
    odom_sigma_theta_rad_per_sqrt_rad: float = 0.05
    odom_sigma_theta_rad_per_sqrt_s: float = 0.0
    odom_sigma_floor_m: float = 1e-4
    odom_sigma_floor_rad: float = 1e-4
    use_odometry_covariance: bool = False
    max_odometry_speed_m_s: float = 5.0
    max_odometry_rate_rad_s: float = 10.0
    odometry_jump_sigma_m: float = 0.1
    odometry_jump_sigma_rad: float = 0.1

    robust_kernel: str = "huber"
    robust_threshold: float = 1.345
    camera_sigma_floor_m: float = 0.005
    camera_sigma_floor_rad: float = 0.002
    max_camera_sigma_m: float = 5.0
    max_camera_sigma_rad: float = 3.0
    max_pending: int = 16
    out_of_order_reset_count: int = 25
    out_of_order_reset_gap_s: float = 5.0
    extra_iterations: int = 1
    relinearize_threshold: float = 0.01

    window_s: float = 300.0
    max_keyframes: int = 200
    marginalize_batch: int = 50
    pre_anchor_buffer_s: float = 10.0

    def __post_init__(self) -> None:
        positive = (
            "keyframe_distance_m",
            "keyframe_angle_rad",
            "keyframe_interval_s",
            "odom_sigma_floor_m",
            "odom_sigma_floor_rad",
            "max_odometry_speed_m_s",
            "max_odometry_rate_rad_s",
            "odometry_jump_sigma_m",
            "odometry_jump_sigma_rad",
            "robust_threshold",
            "camera_sigma_floor_m",
            "camera_sigma_floor_rad",
            "max_camera_sigma_m",
            "max_camera_sigma_rad",
            "relinearize_threshold",
            "window_s",
            "pre_anchor_buffer_s",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"FusionConfig.{name} must be a positive number, got {value!r}")
        for name in (f.name for f in dataclasses.fields(self)):
            value = getattr(self, name)
            if isinstance(value, float) and not (math.isfinite(value) and value >= 0):
                raise ValueError(f"FusionConfig.{name} must be finite and >= 0, got {value!r}")
        if self.robust_kernel not in ROBUST_KERNELS:
            raise ValueError(f"FusionConfig.robust_kernel must be one of {ROBUST_KERNELS}")
        if self.max_keyframes < 2 or self.marginalize_batch < 1 or self.max_pending < 1:
            raise ValueError("FusionConfig: max_keyframes >= 2, marginalize_batch >= 1, "
                             "max_pending >= 1")
        if self.out_of_order_reset_count < 1:
            raise ValueError("FusionConfig.out_of_order_reset_count must be >= 1")
        if self.extra_iterations < 0:
            raise ValueError("FusionConfig.extra_iterations must be >= 0")


def fusion_config_from_site(site: Site) -> FusionConfig:
    """The site file's ``fusion`` section as a :class:`FusionConfig` (every field optional;
    errors name the file and the key)."""
    return site.section_reader().section("fusion", site.section("fusion"), FusionConfig)


# --------------------------------------------------------------------------------------------
# small planar helpers
# --------------------------------------------------------------------------------------------


def _finite(*values: object) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in values)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return False


def _cov_body_to_world(cov_body: np.ndarray, theta_rad: float) -> np.ndarray:
    J = rotation_z(theta_rad)  # body-frame (x, y, theta) perturbations → map-frame axes
    cov = J @ cov_body @ J.T
    return 0.5 * (cov + cov.T)


def _cov_world_to_body(cov_world: np.ndarray, theta_rad: float) -> np.ndarray:
    J = rotation_z(theta_rad)
    cov = J.T @ cov_world @ J
    return 0.5 * (cov + cov.T)


def _interpolate(a: gtsam.Pose2, b: gtsam.Pose2, alpha: float) -> gtsam.Pose2:
    """The pose a fraction ``alpha`` in [0, 1] along the geodesic from ``a`` to ``b``."""
    return a.compose(gtsam.Pose2.Expmap(alpha * gtsam.Pose2.Logmap(a.between(b))))


def _motion(delta: gtsam.Pose2) -> tuple[float, float]:
    return math.hypot(delta.x(), delta.y()), abs(delta.theta())


class _OdomSample(NamedTuple):
    """One odometry reading: ``T_odom_robot`` and its (3, 3) covariance along odom axes (``None``
    unless ``use_odometry_covariance``)."""

    T_odom_robot: gtsam.Pose2
    cov_odom: np.ndarray | None


def _blend_odometry(a: _OdomSample, b: _OdomSample, alpha: float) -> _OdomSample:
    """The odometry ``alpha`` of the way from ``a`` to ``b``: the pose along the SE(2) geodesic,
    the covariance linear (at a reading's own stamp, ``alpha`` 0, that reading)."""
    if alpha == 0.0:
        return a
    cov = None if a.cov_odom is None or b.cov_odom is None else (
        (1 - alpha) * a.cov_odom + alpha * b.cov_odom)
    return _OdomSample(_interpolate(a.T_odom_robot, b.T_odom_robot, alpha), cov)


@dataclasses.dataclass(frozen=True)
class _PendingPrior:
    stamp_ns: int
    T_world_robot: gtsam.Pose2
    cov_world: np.ndarray
    robust: bool
    kind: str


class PoseGraphFusion:
    """Incremental (ISAM2) pose graph of one robot: odometry keyframes + camera priors.

    Feed every :class:`protocol.Odometry` of the robot to :meth:`add_odometry` (it returns the
    fused pose at that stamp) and every camera :class:`protocol.PoseEstimate` to
    :meth:`add_camera_estimate`, in arrival order. ``counters`` counts events and rejection
    reasons; ``last_reject_reason`` names the latest rejection. ``clock``: the site's clock
    policy (default :class:`~core.site.ClockPolicy`'s defaults).
    """

    def __init__(self, robot_id: str, config: FusionConfig | None = None,
                 clock: ClockPolicy | None = None, *,
                 deferred_marginalization: bool = False) -> None:
        self.robot_id = robot_id
        #: marginalize in :meth:`maintain`, not inside the call that made the window full
        #: (until the backlog reaches twice ``marginalize_batch``: then inline, counted
        #: ``marginalizations_overdue``)
        self.deferred_marginalization = deferred_marginalization
        self._marginalization_deferred = False  # one is due (checked by maintain())
        self.config = config if config is not None else FusionConfig()
        self.clock = clock if clock is not None else ClockPolicy()
        # a camera estimate waits for odometry at most one input age ahead of the newest
        self._max_camera_lead_ns = self.clock.max_age_ns
        self.counters: collections.Counter[str] = collections.Counter()
        self._ooo_run = 0  # consecutive out-of-order odometry messages
        self._ooo_last_stamp = 0
        self.last_reject_reason = ""
        self._seq = 0
        self._graph = KeyframeGraph(robot_id, robust_kernel=self.config.robust_kernel,
                                    robust_threshold=self.config.robust_threshold,
                                    relinearize_threshold=self.config.relinearize_threshold)
        # odometry in stamp order (only newer stamps are accepted): interpolation source for
        # keyframes at any stamp; trimmed at anchoring, marginalization and before the anchor
        self._odom: StampedHistory[_OdomSample] = StampedHistory(out_of_order="drop")
        self._pending: list[_PendingPrior] = []
        self._reset_graph()

    # ----------------------------------------------------------------------------------------
    # public API
    # ----------------------------------------------------------------------------------------

    @property
    def anchored(self) -> bool:
        """Whether the odometry is anchored in the map frame (a fused pose is available)."""
        return bool(self._graph.keyframes)

    @property
    def num_keyframes(self) -> int:
        return len(self._graph)

    @property
    def marginalization_due(self) -> int:
        """Keyframes the deferred marginalization would drop now (0: none deferred)."""
        if not self._marginalization_deferred:
            return 0
        drop = self._droppable()
        return drop if drop >= self.config.marginalize_batch else 0

    def maintain(self) -> bool:
        """Run the deferred marginalization if one is due (the ISAM2 rebuild, ~8 ms with the
        default window); True when it ran. A service calls this when its worker has no
        message waiting."""
        drop = self.marginalization_due
        if not drop:
            return False
        self._marginalize(drop)
        return True

    @property
    def oldest_keyframe_stamp_ns(self) -> int | None:
        return self._graph.stamps[0] if self._graph.stamps else None

    def graph_size(self) -> tuple[int, int]:
        """(variables, factors) currently held by ISAM2 (removed factor slots not counted)."""
        return self._graph.graph_size()

    def buffer_sizes(self) -> dict[str, int]:
        """Sizes of the internal buffers (for boundedness checks and status)."""
        return {
            "keyframes": len(self._graph),
            "odometry_samples": len(self._odom),
            "factor_records": self._graph.factor_records(),
            "pending_camera": len(self._pending),
        }

    def reset(self) -> None:
        """Forget the graph, the odometry buffer and pending estimates (counters are kept)."""
        self._odom.clear()
        self._pending.clear()
        self._reset_graph()

    def add_odometry(self, msg: Odometry) -> PoseEstimate | None:
        """Add one odometry sample (``T_odom_robot`` at ``msg.stamp_ns``).

        Returns the fused ``T_world_robot`` at ``msg.stamp_ns`` (source ``"fused"``, covariance
        (3, 3) along map axes), or ``None`` when not yet anchored or the message is rejected.
        """
        self.counters["odometry_received"] += 1
        reason = self._odometry_reason(msg)
        if reason:
            return self._reject(reason)
        stamp = int(msg.stamp_ns)
        T_odom = gtsam.Pose2(float(msg.x), float(msg.y), float(msg.theta))
        cov = None
        if self.config.use_odometry_covariance:
            cov = np.asarray(msg.covariance, dtype=np.float64)
        last = self._odom.latest()
        if last is not None:
            last_stamp = last.stamp_ns
            if stamp <= last_stamp:
                if not self._out_of_order_run(stamp, last_stamp):
                    return self._reject("odometry_out_of_order")
                self.counters["odometry_stamp_reset"] += 1
                logger.warning(
                    "robot %s: %d odometry messages in a row older than the newest accepted "
                    "stamp (%.3f s ahead of them): that stamp was bad; fusion restarts",
                    self.robot_id, self.config.out_of_order_reset_count,
                    (last_stamp - stamp) * 1e-9)
                return self._restart_after_jump(stamp, T_odom, cov)
            self._ooo_run = 0
            if self._is_jump(last.item.T_odom_robot, T_odom, (stamp - last_stamp) / NS_PER_S):
                return self._restart_after_jump(stamp, T_odom, cov)
        self._odom.insert(stamp, _OdomSample(T_odom, cov))
        self.counters["odometry_accepted"] += 1
        if not self.anchored:
            self._prune_pre_anchor_buffer()
        self._process_pending(stamp)
        if not self.anchored:
            self.counters["uninitialized"] += 1
            return None
        self._apply_keyframe_policy(stamp, self._odom.latest().item)  # type: ignore[union-attr]
        return self._fused_at_latest()

    def add_camera_estimate(self, est: PoseEstimate) -> PoseEstimate | None:
        """Add a camera pose estimate ``T_world_robot`` at its own ``est.stamp_ns``.

        Attached as a robust unary prior at that stamp (a keyframe is interpolated there if
        needed) and the graph is optimized. An estimate newer than the latest odometry is held
        until odometry covers its stamp (``camera_deferred``). Returns the fused pose at the
        latest odometry stamp after the update, or ``None`` (deferred / rejected).
        """
        self.counters["camera_received"] += 1
        if isinstance(est, PoseEstimate) and est.source == "fused":
            return self._reject("camera_fused_source")
        return self._add_prior(est, robust=self.config.robust_kernel != "none", kind="camera")

    def set_initial_pose(self, pose: PoseEstimate) -> PoseEstimate | None:
        """Anchor (or re-anchor) with a known ``T_world_robot`` at ``pose.stamp_ns``.

        For a robot that starts from a known pose (its own localization, a PnP initialization):
        a plain Gaussian prior (no robust kernel) with ``pose.covariance``. Same return and
        rejection rules as :meth:`add_camera_estimate`.
        """
        self.counters["initial_pose_received"] += 1
        return self._add_prior(pose, robust=False, kind="initial")

    def pose_at(self, stamp_ns: int) -> PoseEstimate | None:
        """Fused (smoothed) ``T_world_robot`` at any ``stamp_ns`` covered by the window.

        Between two keyframes the odometry is composed onto the earlier keyframe and the
        residual to the later keyframe's estimate is spread linearly in time. ``None`` outside
        the window or the odometry buffer.
        """
        newest = self._odom.latest()
        graph = self._graph
        if not graph.keyframes or stamp_ns < graph.stamps[0] or newest is None or (
                stamp_ns > newest.stamp_ns):
            return None
        i = graph.index_at(stamp_ns)
        kf = graph.keyframes[i]
        T_odom = self._odom_at(stamp_ns)
        if T_odom is None:
            return None
        T_world_kf, cov_kf = graph.estimate_and_cov(kf.key)
        delta = kf.T_odom_robot.between(T_odom.T_odom_robot)
        T_world = T_world_kf.compose(delta)
        if i + 1 < len(graph):
            nxt = graph.keyframes[i + 1]
            T_world_nxt = graph.estimate(nxt.key)
            predicted = T_world_kf.compose(kf.T_odom_robot.between(nxt.T_odom_robot))
            alpha = (stamp_ns - kf.stamp_ns) / max(1, nxt.stamp_ns - kf.stamp_ns)
            residual = gtsam.Pose2.Logmap(predicted.between(T_world_nxt))
            T_world = T_world.compose(gtsam.Pose2.Expmap(alpha * residual))
        cov_body = self._propagate(cov_kf, kf, T_odom, stamp_ns)
        return self._make_estimate(stamp_ns, T_world, cov_body)

    def latest(self) -> PoseEstimate | None:
        """Fused pose at the latest odometry stamp (``None`` if not anchored)."""
        return self._fused_at_latest() if self.anchored else None

    def keyframes(self) -> tuple[np.ndarray, np.ndarray]:
        """Keyframes in the window: stamps (K,) int64 ns and optimized poses (K, 3) x, y, theta
        of ``T_world_robot`` (metres, radians)."""
        return np.array(self._graph.stamps, dtype=np.int64), self._graph.poses()

    # ----------------------------------------------------------------------------------------
    # input checks
    # ----------------------------------------------------------------------------------------

    def _out_of_order_run(self, stamp: int, last_stamp: int) -> bool:
        """Count one more out-of-order odometry message; ``True`` once a run of
        ``out_of_order_reset_count`` of them, in order among themselves and all more than
        ``out_of_order_reset_gap_s`` older than ``last_stamp``, says the newest accepted stamp
        is the one that is wrong."""
        if last_stamp - stamp <= self.config.out_of_order_reset_gap_s * NS_PER_S:
            self._ooo_run = 0  # close to what the fusion has: a duplicate or a replay
            return False
        if self._ooo_run and stamp <= self._ooo_last_stamp:
            self._ooo_run = 0  # not a consistent stream: plain duplicates or a replay
        self._ooo_run += 1
        self._ooo_last_stamp = stamp
        if self._ooo_run >= self.config.out_of_order_reset_count:
            self._ooo_run = 0
            return True
        return False

    def _reject(self, reason: str) -> None:
        self.counters[reason] += 1
        self.last_reject_reason = reason
        logger.debug("robot %s: rejected (%s)", self.robot_id, reason)
        return None

    def _odometry_reason(self, msg: object) -> str:
        if not isinstance(msg, Odometry):
            return "odometry_invalid"
        if msg.robot_id != self.robot_id:
            return "odometry_wrong_robot"
        stamp = msg.stamp_ns
        if not isinstance(stamp, (int, np.integer)) or stamp < 0:
            return "odometry_invalid"
        if not _finite(msg.x, msg.y, msg.theta):
            return "odometry_invalid"
        if self.config.use_odometry_covariance:
            cov = np.asarray(msg.covariance)
            if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
                return "odometry_invalid"
        return ""

    def _prior_input(self, est: object) -> tuple[str, gtsam.Pose2 | None, np.ndarray | None]:
        """(reason, T_world_robot, covariance along map axes with floors) of a pose estimate."""
        if not isinstance(est, PoseEstimate):
            return "camera_invalid", None, None
        if est.robot_id != self.robot_id:
            return "camera_wrong_robot", None, None
        stamp = est.stamp_ns
        if not isinstance(stamp, (int, np.integer)) or stamp < 0:
            return "camera_invalid", None, None
        if not _finite(est.x, est.y, est.theta):
            return "camera_invalid", None, None
        try:
            cov = np.array(est.covariance, dtype=np.float64)
        except (TypeError, ValueError):
            return "camera_bad_covariance", None, None
        if cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            return "camera_bad_covariance", None, None
        cov = 0.5 * (cov + cov.T)
        cfg = self.config
        # an all-zero or singular covariance means "unknown", not "exact": reject it
        if float(np.min(np.linalg.eigvalsh(cov))) <= 1e-15 * max(1.0, float(np.max(np.abs(cov)))):
            return "camera_bad_covariance", None, None
        if max(cov[0, 0], cov[1, 1]) > cfg.max_camera_sigma_m**2 or (
            cov[2, 2] > cfg.max_camera_sigma_rad**2
        ):
            return "camera_uninformative", None, None
        floor_m2, floor_rad2 = cfg.camera_sigma_floor_m**2, cfg.camera_sigma_floor_rad**2
        cov = cov + np.diag([floor_m2, floor_m2, floor_rad2])
        return "", gtsam.Pose2(float(est.x), float(est.y), float(est.theta)), cov

    def _is_jump(self, a: gtsam.Pose2, b: gtsam.Pose2, dt_s: float) -> bool:
        dist_m, angle_rad = _motion(a.between(b))
        # a small allowance so that a single late sample after a short gap is not a "jump"
        return (
            dist_m > self.config.max_odometry_speed_m_s * dt_s + 0.05
            or angle_rad > self.config.max_odometry_rate_rad_s * dt_s + 0.05
        )

    # ----------------------------------------------------------------------------------------
    # odometry buffer and keyframes
    # ----------------------------------------------------------------------------------------

    def _odom_at(self, stamp_ns: int) -> _OdomSample | None:
        """Odometry pose (and covariance) interpolated at ``stamp_ns``; None outside buffer."""
        return self._odom.interpolate(stamp_ns, _blend_odometry)

    def _odometry_noise(
        self,
        T_a: gtsam.Pose2,
        cov_a: np.ndarray | None,
        T_b: gtsam.Pose2,
        cov_b: np.ndarray | None,
        dt_s: float,
    ) -> np.ndarray:
        """(3, 3) covariance of the odometry increment a → b in the body frame of b."""
        cfg = self.config
        if cov_a is not None and cov_b is not None:
            increment = _cov_world_to_body(cov_b - cov_a, T_b.theta())
            if float(np.min(np.linalg.eigvalsh(increment))) > cfg.odom_sigma_floor_m**2:
                return increment
            self.counters["odometry_covariance_fallback"] += 1
        dist_m, angle_rad = _motion(T_a.between(T_b))
        dt_s = max(0.0, dt_s)
        var_xy = (
            cfg.odom_sigma_xy_m_per_sqrt_m**2 * dist_m
            + cfg.odom_sigma_xy_m_per_sqrt_rad**2 * angle_rad
            + cfg.odom_sigma_xy_m_per_sqrt_s**2 * dt_s
            + cfg.odom_sigma_floor_m**2
        )
        var_theta = (
            cfg.odom_sigma_theta_rad_per_sqrt_m**2 * dist_m
            + cfg.odom_sigma_theta_rad_per_sqrt_rad**2 * angle_rad
            + cfg.odom_sigma_theta_rad_per_sqrt_s**2 * dt_s
            + cfg.odom_sigma_floor_rad**2
        )
        return np.diag([var_xy, var_xy, var_theta])

    def _between_record(self, a: Keyframe, b: Keyframe) -> GraphFactor:
        cov = self._odometry_noise(
            a.T_odom_robot, a.cov_odom, b.T_odom_robot, b.cov_odom,
            (b.stamp_ns - a.stamp_ns) / NS_PER_S,
        )
        measured = a.T_odom_robot.between(b.T_odom_robot)
        return GraphFactor("between", a.key, b.key, measured, cov, robust=False)

    def _apply_keyframe_policy(self, stamp: int, sample: _OdomSample) -> None:
        T_odom = sample.T_odom_robot
        last = self._graph.keyframes[-1]
        if stamp <= last.stamp_ns:
            return
        cfg = self.config
        dist_m, angle_rad = _motion(last.T_odom_robot.between(T_odom))
        moved = dist_m > cfg.static_motion_m or angle_rad > cfg.static_motion_rad
        dt_s = (stamp - last.stamp_ns) / NS_PER_S
        if (
            dist_m >= cfg.keyframe_distance_m
            or angle_rad >= cfg.keyframe_angle_rad
            or (moved and dt_s >= cfg.keyframe_interval_s)
        ):
            batch = FactorBatch()
            self._insert_keyframe(stamp, T_odom, sample.cov_odom, batch)
            if self._update(batch):
                self.counters["keyframes_created"] += 1
                self._maybe_marginalize()

    def _insert_keyframe(
        self, stamp: int, T_odom: gtsam.Pose2, cov_odom: np.ndarray | None, batch: FactorBatch
    ) -> int:
        """Add a keyframe at ``stamp`` (after the first one) to ``batch``: appended to the chain
        or, for a stamp between two keyframes, splitting their between factor in two."""
        kf = Keyframe(self._graph.new_key(), stamp, T_odom, cov_odom)
        if self._graph.insert(kf, self._between_record, batch):
            self.counters["keyframes_inserted"] += 1
        return kf.key

    def _keyframe_for(self, stamp: int, batch: FactorBatch) -> int | None:
        """Key of the keyframe at ``stamp``: an existing one the robot has not moved away from,
        or a new one interpolated from the odometry. None when the odometry does not cover it."""
        odom = self._odom_at(stamp)
        if odom is None:
            return None
        T_odom, cov_odom = odom
        cfg = self.config
        keyframes = self._graph.keyframes
        i = self._graph.index_at(stamp)
        for j in (i, i + 1):
            if 0 <= j < len(keyframes):
                dist_m, angle_rad = _motion(keyframes[j].T_odom_robot.between(T_odom))
                if dist_m <= cfg.static_motion_m and angle_rad <= cfg.static_motion_rad:
                    return keyframes[j].key
        return self._insert_keyframe(stamp, T_odom, cov_odom, batch)

    # ----------------------------------------------------------------------------------------
    # priors (camera estimates, initial pose)
    # ----------------------------------------------------------------------------------------

    def _add_prior(self, est: object, *, robust: bool, kind: str) -> PoseEstimate | None:
        reason, T_world, cov_world = self._prior_input(est)
        if reason:
            return self._reject(reason)
        assert T_world is not None and cov_world is not None and isinstance(est, PoseEstimate)
        stamp = int(est.stamp_ns)
        prior = _PendingPrior(stamp, T_world, cov_world, robust, kind)
        newest = self._odom.latest()
        if newest is None or stamp > newest.stamp_ns:
            if newest is not None and stamp - newest.stamp_ns > self._max_camera_lead_ns:
                return self._reject("camera_future")
            bisect.insort(self._pending, prior, key=lambda p: p.stamp_ns)
            self.counters["camera_deferred"] += 1
            if len(self._pending) > self.config.max_pending:
                self._pending.pop(0)
                self._reject("camera_pending_overflow")
            return None
        if not self._fuse_prior(prior):
            return None
        return self._fused_at_latest()

    def _process_pending(self, stamp_ns: int) -> None:
        while self._pending and self._pending[0].stamp_ns <= stamp_ns:
            self._fuse_prior(self._pending.pop(0))

    def _fuse_prior(self, prior: _PendingPrior) -> bool:
        stamp = prior.stamp_ns
        if not self.anchored or prior.kind == "initial":
            return self._anchor(prior)
        if stamp < self._graph.stamps[0]:
            self._reject("camera_too_old")
            return False
        batch = FactorBatch()
        key = self._keyframe_for(stamp, batch)
        if key is None:
            self._reject("camera_too_old")
            return False
        self._graph.add(batch, self._prior_record(prior, key))
        if not self._update(batch, iterations=1 + self.config.extra_iterations):
            return False
        self.counters[f"{prior.kind}_fused"] += 1
        self._maybe_marginalize()
        return True

    def _prior_record(self, prior: _PendingPrior, key: int) -> GraphFactor:
        cov_body = _cov_world_to_body(prior.cov_world, prior.T_world_robot.theta())
        return GraphFactor(prior.kind, -1, key, prior.T_world_robot, cov_body, prior.robust)

    def _anchor(self, prior: _PendingPrior) -> bool:
        """Start the graph at ``prior.stamp_ns`` (first estimate, or an explicit initial pose),
        then replay the buffered odometry after it through the keyframe policy."""
        odom = self._odom_at(prior.stamp_ns)
        if odom is None:
            self._reject("camera_too_old" if prior.kind == "camera" else "initial_too_old")
            return False
        self._reset_graph()
        kf = Keyframe(self._graph.new_key(), prior.stamp_ns, odom[0], odom[1])
        batch = FactorBatch()
        self._graph.start(kf, prior.T_world_robot, batch)
        self._graph.add(batch, self._prior_record(prior, kf.key))
        if not self._update(batch, iterations=1 + self.config.extra_iterations):
            return False
        self.counters[f"{prior.kind}_fused"] += 1
        self.counters["anchored"] += 1
        self._odom.trim_before(kf.stamp_ns)
        for stamp, sample in self._odom.newer_than(kf.stamp_ns):
            self._apply_keyframe_policy(stamp, sample)
        return True

    def _restart_after_jump(
        self, stamp: int, T_odom: gtsam.Pose2, cov: np.ndarray | None
    ) -> PoseEstimate | None:
        """Odometry jumped (reset/reboot of the robot's odometry): keep the map anchor by
        re-rooting the graph at the new sample with the last fused pose, inflated."""
        self.counters["odometry_jump"] += 1
        self.last_reject_reason = "odometry_jump"
        last = self._fused_at_latest() if self.anchored else None
        self.reset()
        self._odom.insert(stamp, _OdomSample(T_odom, cov))
        if last is None:
            return None
        cfg = self.config
        inflate = np.diag(
            [cfg.odometry_jump_sigma_m**2, cfg.odometry_jump_sigma_m**2,
             cfg.odometry_jump_sigma_rad**2]
        )
        prior = _PendingPrior(
            stamp, gtsam.Pose2(last.x, last.y, last.theta), last.covariance + inflate, False,
            "marginal",
        )
        if not self._anchor(prior):
            return None
        return self._fused_at_latest()

    # ------------------------------------------------------------------ the graph, fused poses

    def _reset_graph(self) -> None:
        self._graph.reset()
        self._marginalization_deferred = False

    def _update(self, batch: FactorBatch, iterations: int = 1) -> bool:
        """One ISAM2 update of the graph; a refused one empties it (``optimizer_error``)."""
        if self._graph.update(batch, iterations):
            return True
        self._marginalization_deferred = False
        self._reject("optimizer_error")
        return False

    def _propagate(
        self, cov_kf_body: np.ndarray, kf: Keyframe, odom: tuple, stamp_ns: int
    ) -> np.ndarray:
        """Covariance (body frame) of keyframe ∘ odometry increment: Ad(D⁻¹) Σ Ad(D⁻¹)ᵀ + Q."""
        T_odom, cov_odom = odom
        delta = kf.T_odom_robot.between(T_odom)
        adj = delta.inverse().AdjointMap()
        q = self._odometry_noise(
            kf.T_odom_robot, kf.cov_odom, T_odom, cov_odom, (stamp_ns - kf.stamp_ns) / NS_PER_S
        )
        cov = adj @ cov_kf_body @ adj.T + q
        return 0.5 * (cov + cov.T)

    def _fused_at_latest(self) -> PoseEstimate | None:
        stamp, odom = self._odom.latest()  # type: ignore[misc]
        kf = self._graph.keyframes[-1]
        T_world_kf, cov_kf = self._graph.estimate_and_cov(kf.key)
        T_world = T_world_kf.compose(kf.T_odom_robot.between(odom.T_odom_robot))
        cov_body = self._propagate(cov_kf, kf, odom, stamp)
        return self._make_estimate(stamp, T_world, cov_body)

    def _make_estimate(
        self, stamp_ns: int, T_world: gtsam.Pose2, cov_body: np.ndarray
    ) -> PoseEstimate | None:
        try:
            est = PoseEstimate(
                robot_id=self.robot_id,
                stamp_ns=int(stamp_ns),
                seq=self._seq,
                x=float(T_world.x()),
                y=float(T_world.y()),
                theta=float(T_world.theta()),
                covariance=_cov_body_to_world(cov_body, T_world.theta()),
                source="fused",
            )
        except ValueError as exc:  # protocol.ValidationError: numerically broken estimate
            logger.warning("robot %s: fused pose not publishable (%s)", self.robot_id, exc)
            return self._reject("fused_invalid")
        self._seq += 1
        return est

    # ----------------------------------------------------------------------------------------
    # bounded memory
    # ----------------------------------------------------------------------------------------

    def _prune_pre_anchor_buffer(self) -> None:
        self._odom.trim_to_age(int(self.config.pre_anchor_buffer_s * NS_PER_S))

    def _droppable(self) -> int:
        """Keyframes outside the window (time or count), keeping at least the latest."""
        return self._graph.droppable(int(self.config.window_s * NS_PER_S),
                                     self.config.max_keyframes)

    def _maybe_marginalize(self) -> None:
        drop = self._droppable()
        batch = self.config.marginalize_batch
        if drop < batch:
            return
        if self.deferred_marginalization:
            if drop < 2 * batch:
                self._marginalization_deferred = True  # maintain() runs it when idle
                return
            self.counters["marginalizations_overdue"] += 1
        self._marginalize(drop)

    def _marginalize(self, drop: int) -> None:
        """Fold the oldest ``drop`` keyframes into a prior on the oldest kept one
        (:meth:`KeyframeGraph.marginalize`) and trim the odometry before it."""
        self._marginalization_deferred = False
        root_stamp_ns = self._graph.stamps[drop]
        ok = self._graph.marginalize(drop)
        self._odom.trim_before(root_stamp_ns)
        if ok:
            self.counters["marginalizations"] += 1
        else:
            self._reject("optimizer_error")
