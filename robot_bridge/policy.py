"""When to push a pose to the robot's localization: static detection and the correction rule.

Pure and deterministic: no transport, no wall clock. Time is the robot's odometry stamps and
the ``now_ns`` the caller passes. All thresholds come from :class:`protocol.site.Thresholds`.

The rule (paper Sec. III-C: corrections "sparsely at waypoints where the robot is static"):

1. The robot is *static* when its odometry velocities stayed below ``static_max_speed_mps`` and
   ``static_max_yaw_rate_radps`` for at least ``static_dwell_s``. Every such still period is one
   *stop* (numbered by ``stop_id``); any sample above the thresholds ends it. This is the one
   :class:`protocol.geometry.StaticDetector` (the backend averages with the same one);
   ``StaticDetector.from_thresholds`` builds it from the site's thresholds.
2. Only estimates observed during the current stop count (``stamp_ns >= still_since_ns``): an
   estimate from while the robot moved refers to another place than the robot's current
   localization.
3. At most one pose is pushed per stop, and never two within ``correction_min_interval_s``.
4. The estimate must be certain enough: position standard deviation (largest eigenvalue of the
   x/y covariance block) ``<= correction_max_std_m``.
5. *Initialization* (kidnapped robot): when the robot reports no localization or says it is
   lost, the first such estimate is sent as ``kind="initialization"``, whatever its distance,
   unless it is flagged ``lateral_only`` (a single-camera update that cannot fix a pose).
6. *Correction*: otherwise the estimate is sent when it disagrees with the robot's own
   localization by more than ``correction_min_offset_m`` or ``correction_min_offset_deg``, and
   rejected when the disagreement exceeds ``correction_max_jump_m`` (a wrong camera solve must
   not teleport a localized robot).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Final

import numpy as np

from protocol.geometry import MotionState, angle_diff
from protocol.messages import PoseEstimate
from protocol.site import Thresholds
from robot_bridge.adapters.base import LocalizationPose

NS_PER_S: Final = 1_000_000_000

# Why a pose was (not) sent; also the counter names of the bridge (``skip_<reason>``).
SEND: Final = "send"
MOVING: Final = "moving"
SETTLING: Final = "settling"
NO_ESTIMATE: Final = "no_estimate_this_stop"
ALREADY_SENT: Final = "already_sent_this_stop"
RATE_LIMITED: Final = "rate_limited"
UNCERTAIN: Final = "covariance_too_large"
UNFIT_FOR_INIT: Final = "unfit_for_initialization"
SMALL_OFFSET: Final = "offset_below_threshold"
JUMP_TOO_LARGE: Final = "jump_too_large"

#: Estimate flags that make an estimate unusable as an initial pose.
UNFIT_INIT_FLAGS: Final = frozenset({"lateral_only"})


def position_std_m(covariance: np.ndarray) -> float:
    """Largest position standard deviation (m) of a (3, 3) (x, y, theta) covariance: the square
    root of the largest eigenvalue of its x/y block. ``inf`` when it is not finite."""
    block = np.asarray(covariance, dtype=np.float64)[:2, :2]
    if not np.all(np.isfinite(block)):
        return math.inf
    eig_max = float(np.max(np.linalg.eigvalsh(0.5 * (block + block.T))))
    return math.sqrt(max(eig_max, 0.0))


def pose_offset(
    x_a: float, y_a: float, theta_a: float, x_b: float, y_b: float, theta_b: float
) -> tuple[float, float]:
    """Distance (m) and absolute heading difference (rad, in [0, pi]) of two planar poses in
    the same frame."""
    return math.hypot(x_a - x_b, y_a - y_b), abs(angle_diff(theta_a, theta_b))


# --------------------------------------------------------------------------------------------
# Correction decision
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class CorrectionDecision:
    """What to do with an estimate. ``kind`` is ``"initialization"`` / ``"correction"`` when a
    pose is to be sent (``reason == "send"``), ``None`` otherwise; ``reason`` says why not.
    ``offset_m`` / ``offset_rad``: estimate vs robot localization (0 when unknown)."""

    reason: str
    kind: str | None = None
    estimate: PoseEstimate | None = None
    offset_m: float = 0.0
    offset_rad: float = 0.0

    @property
    def send(self) -> bool:
        return self.reason == SEND


def localization_known(localization: LocalizationPose | None) -> bool:
    """The robot has a usable localization (reported, finite, not flagged lost)."""
    return localization is not None and not localization.lost and localization.is_finite


class CorrectionPolicy:
    """The stateful part of the rule: remembers the stop and the time of the last pose sent.

    :meth:`decide` is side-effect free; :meth:`mark_sent` records a pose that was sent.
    """

    def __init__(self, thresholds: Thresholds) -> None:
        self.thresholds = thresholds
        self._min_interval_ns = round(thresholds.correction_min_interval_s * NS_PER_S)
        self._last_sent_ns: int | None = None
        self._last_sent_stop_id: int | None = None

    @property
    def last_sent_ns(self) -> int | None:
        return self._last_sent_ns

    def decide(
        self,
        estimate: PoseEstimate | None,
        localization: LocalizationPose | None,
        motion: MotionState,
        now_ns: int,
    ) -> CorrectionDecision:
        """Apply the rule (module docstring) to the best estimate of the current stop.

        ``estimate``: a world-frame pose of this robot (already validated); ``localization``:
        the robot's own map-frame pose or ``None``; ``motion``: the static detector's state;
        ``now_ns``: the bridge clock (for the rate limit).
        """
        th = self.thresholds
        if not motion.is_static:
            return CorrectionDecision(MOVING if motion.still_since_ns is None else SETTLING)
        if self._last_sent_stop_id == motion.stop_id:
            return CorrectionDecision(ALREADY_SENT)
        if (
            estimate is None
            or motion.still_since_ns is None
            or estimate.stamp_ns < motion.still_since_ns
        ):
            return CorrectionDecision(NO_ESTIMATE)
        if self._last_sent_ns is not None and now_ns - self._last_sent_ns < self._min_interval_ns:
            return CorrectionDecision(RATE_LIMITED, estimate=estimate)
        if position_std_m(estimate.covariance) > th.correction_max_std_m:
            return CorrectionDecision(UNCERTAIN, estimate=estimate)
        if not localization_known(localization):
            if UNFIT_INIT_FLAGS.intersection(estimate.flags):
                return CorrectionDecision(UNFIT_FOR_INIT, estimate=estimate)
            return CorrectionDecision(SEND, "initialization", estimate)
        assert localization is not None
        offset_m, offset_rad = pose_offset(
            estimate.x, estimate.y, estimate.theta, localization.x, localization.y,
            localization.theta,
        )
        if offset_m <= th.correction_min_offset_m and offset_rad <= math.radians(
            th.correction_min_offset_deg
        ):
            return CorrectionDecision(SMALL_OFFSET, None, estimate, offset_m, offset_rad)
        if offset_m > th.correction_max_jump_m:
            return CorrectionDecision(JUMP_TOO_LARGE, None, estimate, offset_m, offset_rad)
        return CorrectionDecision(SEND, "correction", estimate, offset_m, offset_rad)

    def mark_sent(self, motion: MotionState, now_ns: int) -> None:
        """Record that a pose was sent during ``motion``'s stop at ``now_ns``."""
        self._last_sent_ns = now_ns
        self._last_sent_stop_id = motion.stop_id
