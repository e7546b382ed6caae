"""When to push a pose to the robot's localization: static detection and the correction rule.

Pure and deterministic: no transport, no wall clock. Time is the robot's odometry stamps and
the ``now_ns`` the caller passes. The thresholds come from :class:`core.site.Thresholds`;
what the bridge demands of an estimate before it trusts it, from :class:`TrustConfig` (the
site file's ``bridge`` section).

The rule (paper Sec. III-C: corrections "sparsely at waypoints where the robot is static"):

1. The robot is *static* when its odometry velocities stayed below ``static_max_speed_mps`` and
   ``static_max_yaw_rate_radps`` for at least ``static_dwell_s``. Every such still period is one
   *stop* (numbered by ``stop_id``); any sample above the thresholds ends it. This is the one
   :class:`core.geometry.StaticDetector` (the backend averages with the same one);
   ``StaticDetector.from_thresholds`` builds it from the site's thresholds.
2. Only estimates observed during the current stop count (``stamp_ns >= still_since_ns``): an
   estimate from while the robot moved refers to another place than the robot's current
   localization.
3. At most one pose is pushed per stop, and never two within ``correction_min_interval_s``.
4. The estimate must be certain enough: position standard deviation (largest eigenvalue of the
   x/y covariance block) ``<= correction_max_std_m``. The covariance is first raised to the
   bridge's own floor (``position_std_floor_m``, ``yaw_std_floor_deg``): a sender claiming
   zero uncertainty is not believed, and the pose goes to the robot with the floored covariance.
5. *Initialization* (kidnapped robot): when the robot reports no localization or says it is
   lost, an estimate is sent as ``kind="initialization"`` only when it lies inside the site's
   floor area (``TrustConfig.floor_area``), is not flagged ``lateral_only`` (a single-camera
   update cannot fix a pose), and the last ``init_agreement_count`` estimates of its source in
   this stop agree with it within ``init_agreement_m`` / ``init_agreement_deg``.
6. *Correction*: otherwise the estimate is sent when it disagrees with the robot's own
   localization by more than ``correction_min_offset_m`` or ``correction_min_offset_deg``. It
   is refused when it is further than ``correction_max_jump_m`` / ``correction_max_jump_deg``
   from the robot's localization **or** from the *reference*: that localization with the
   bridge's own corrections of the last ``correction_window_s`` taken out (their x/y offsets
   summed as map-frame vectors, their heading offsets as angles). Repeated sub-limit
   corrections in one direction therefore cannot add up beyond one jump per window. And the
   corrections of a window may move the robot by at most ``correction_window_max_m`` and
   ``correction_window_max_deg`` in total (the sum of their offsets' sizes): a rate limit.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np
import numpy.typing as npt

from core.geometry import MotionState, angle_diff
from core.pose import PlanarPose
from core.site import Thresholds
from protocol.messages import NS_PER_S, PoseEstimate
from robot_bridge.adapters.base import LocalizationPose

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
HEADING_JUMP_TOO_LARGE: Final = "heading_jump_too_large"
WINDOW_EXCEEDED: Final = "correction_window_exceeded"
OUTSIDE_FLOOR: Final = "outside_floor_area"
AWAITING_AGREEMENT: Final = "awaiting_agreement"

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


def floor_covariance(
    covariance: np.ndarray, position_std_floor_m: float, yaw_std_floor_rad: float
) -> np.ndarray:
    """A (3, 3) (x, y, theta) covariance raised to a floor: every direction of the x/y block gets
    a standard deviation of at least ``position_std_floor_m`` (eigenvalues clamped from below)
    and theta at least ``yaw_std_floor_rad``. Adds a positive semi-definite matrix, so a valid
    covariance stays valid; a covariance already above the floor is returned unchanged."""
    cov = np.array(covariance, dtype=np.float64, copy=True).reshape(3, 3)
    cov = 0.5 * (cov + cov.T)
    eig, vec = np.linalg.eigh(cov[:2, :2])
    lift = np.maximum(position_std_floor_m**2 - eig, 0.0)
    if np.any(lift > 0.0):
        cov[:2, :2] += (vec * lift) @ vec.T
    cov[2, 2] = max(cov[2, 2], yaw_std_floor_rad**2)
    return cov


def floor_area_around(points_xy: npt.ArrayLike, margin_m: float
                      ) -> tuple[float, float, float, float]:
    """``(x_min, y_min, x_max, y_max)`` (m, world frame): the bounding box of ``points_xy``
    ((N, 2), e.g. the site cameras' positions) grown by ``margin_m`` on every side."""
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    if pts.size == 0:
        raise ValueError("no points to bound")
    lo, hi = pts.min(axis=0) - margin_m, pts.max(axis=0) + margin_m
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def inside_floor_area(x: float, y: float, area: Sequence[float]) -> bool:
    """``(x, y)`` lies in ``area`` = ``(x_min, y_min, x_max, y_max)``; an empty ``area`` (no
    floor area configured) contains everything."""
    if len(area) == 0:
        return True
    x_min, y_min, x_max, y_max = area
    return x_min <= x <= x_max and y_min <= y <= y_max


# --------------------------------------------------------------------------------------------
# What the bridge demands of an estimate
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TrustConfig:
    """What the bridge demands of an estimate before it moves the robot (site file section
    ``bridge``; docs/robot_bridge.md, "What the bridge trusts").

    How far ahead of the bridge's clock a stamp may be is the site's clock policy
    (``clock.max_future_ms``, :class:`~core.site.ClockPolicy`). ``position_std_floor_m`` /
    ``yaw_std_floor_deg``: the least uncertainty the bridge assumes of any estimate, whatever its
    covariance says (the gate and the covariance sent to the robot use the floored one).
    ``init_agreement_count``: a kidnapped robot is initialized only after this many consecutive
    estimates of one source in the stop agree within ``init_agreement_m`` and
    ``init_agreement_deg``. ``floor_area``: ``[x_min, y_min, x_max, y_max]`` (m, world frame):
    initial poses outside it are refused; when the site file has none, the bounding box of the
    cameras' positions grown by ``floor_margin_m``.
    """

    position_std_floor_m: float = 0.02
    yaw_std_floor_deg: float = 1.0
    init_agreement_count: int = 3
    init_agreement_m: float = 0.2
    init_agreement_deg: float = 10.0
    floor_margin_m: float = 10.0
    floor_area: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        area = tuple(float(v) for v in self.floor_area)
        if area and (len(area) != 4 or not all(math.isfinite(v) for v in area)):
            raise ValueError("floor_area: expected [x_min, y_min, x_max, y_max], finite numbers")
        if area and not (area[0] < area[2] and area[1] < area[3]):
            raise ValueError("floor_area: needs x_min < x_max and y_min < y_max")
        object.__setattr__(self, "floor_area", area)
        if self.init_agreement_count < 1:
            raise ValueError("init_agreement_count: at least 1")


@dataclasses.dataclass(frozen=True, eq=False)
class AppliedCorrection:
    """A correction the robot took: ``seq`` of the :class:`PoseCorrection`, ``sent_ns`` (bridge
    clock), ``dx_m``, ``dy_m``, ``dtheta_rad``: estimate minus localization (map frame, heading
    wrapped), and the sizes of that offset."""

    seq: int | None
    sent_ns: int
    dx_m: float
    dy_m: float
    dtheta_rad: float
    offset_m: float
    offset_rad: float


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
    """The stateful part of the rule: the stop and time of the last pose sent, the corrections
    of the window (for the jump and window limits), the recent estimates of each source (for
    the initialization's agreement).

    :meth:`decide` is side-effect free; :meth:`observe` records an accepted estimate,
    :meth:`mark_sent` a pose that was sent and :meth:`on_result` whether the robot took it.
    """

    def __init__(self, thresholds: Thresholds, trust: TrustConfig | None = None) -> None:
        self.thresholds = thresholds
        self.trust = trust if trust is not None else TrustConfig()
        self._min_interval_ns = round(thresholds.correction_min_interval_s * NS_PER_S)
        self._window_ns = round(thresholds.correction_window_s * NS_PER_S)
        self._yaw_floor_rad = math.radians(self.trust.yaw_std_floor_deg)
        self._last_sent_ns: int | None = None
        self._last_sent_stop_id: int | None = None
        self._applied: collections.deque[AppliedCorrection] = collections.deque()
        self._recent: dict[str, collections.deque[PoseEstimate]] = {}

    @property
    def last_sent_ns(self) -> int | None:
        return self._last_sent_ns

    def floored(self, covariance: np.ndarray) -> np.ndarray:
        """``covariance`` raised to the bridge's floor (:func:`floor_covariance`)."""
        return floor_covariance(covariance, self.trust.position_std_floor_m, self._yaw_floor_rad)

    def observe(self, estimate: PoseEstimate) -> None:
        """An estimate the bridge accepted (newest of its source): kept for the agreement."""
        recent = self._recent.setdefault(
            estimate.source, collections.deque(maxlen=self.trust.init_agreement_count))
        recent.append(estimate)

    def agreement(self, estimate: PoseEstimate, since_ns: int) -> int:
        """How many of the latest estimates of ``estimate``'s source, ending with ``estimate``
        itself and stamped at or after ``since_ns``, agree with it (within
        ``init_agreement_m`` / ``init_agreement_deg``); 0 when ``estimate`` is not the latest."""
        recent = self._recent.get(estimate.source)
        if not recent or recent[-1] is not estimate:
            return 0
        max_rad = math.radians(self.trust.init_agreement_deg)
        n = 0
        for other in reversed(recent):
            dist, dyaw = PlanarPose.of(estimate).distance_to(PlanarPose.of(other))
            if other.stamp_ns < since_ns or dist > self.trust.init_agreement_m or dyaw > max_rad:
                break
            n += 1
        return n

    def window(self, now_ns: int) -> list[AppliedCorrection]:
        """The corrections the robot took within ``correction_window_s`` before ``now_ns``."""
        return [a for a in self._applied if now_ns - a.sent_ns <= self._window_ns]

    def net_offset(self, estimate: PoseEstimate, localization: LocalizationPose, now_ns: int
                   ) -> tuple[float, float]:
        """Distance (m) and heading (rad) between ``estimate`` and the *reference*: the
        robot's ``localization`` with the window's corrections taken out. Equals the size of
        this correction plus those of the window, added as map-frame vectors (x/y) and angles,
        so corrections that keep pushing one way add up while noise cancels."""
        dx = estimate.x - localization.x
        dy = estimate.y - localization.y
        dtheta = angle_diff(estimate.theta, localization.theta)
        for applied in self.window(now_ns):
            dx, dy, dtheta = dx + applied.dx_m, dy + applied.dy_m, dtheta + applied.dtheta_rad
        return math.hypot(dx, dy), abs(dtheta)

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
        ``now_ns``: the bridge clock (for the rate limit and the correction window).
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
        if position_std_m(self.floored(estimate.covariance)) > th.correction_max_std_m:
            return CorrectionDecision(UNCERTAIN, estimate=estimate)
        if not localization_known(localization):
            if UNFIT_INIT_FLAGS.intersection(estimate.flags):
                return CorrectionDecision(UNFIT_FOR_INIT, estimate=estimate)
            if not inside_floor_area(estimate.x, estimate.y, self.trust.floor_area):
                return CorrectionDecision(OUTSIDE_FLOOR, estimate=estimate)
            if self.agreement(estimate, motion.still_since_ns) < self.trust.init_agreement_count:
                return CorrectionDecision(AWAITING_AGREEMENT, estimate=estimate)
            return CorrectionDecision(SEND, "initialization", estimate)
        assert localization is not None
        offset_m, offset_rad = PlanarPose.of(estimate).distance_to(localization.pose)
        if offset_m <= th.correction_min_offset_m and offset_rad <= math.radians(
            th.correction_min_offset_deg
        ):
            return CorrectionDecision(SMALL_OFFSET, None, estimate, offset_m, offset_rad)
        ref_m, ref_rad = self.net_offset(estimate, localization, now_ns)
        if max(offset_m, ref_m) > th.correction_max_jump_m:
            return CorrectionDecision(JUMP_TOO_LARGE, None, estimate, offset_m, offset_rad)
        if max(offset_rad, ref_rad) > math.radians(th.correction_max_jump_deg):
            return CorrectionDecision(HEADING_JUMP_TOO_LARGE, None, estimate, offset_m, offset_rad)
        window = self.window(now_ns)
        if (
            sum(a.offset_m for a in window) + offset_m > th.correction_window_max_m
            or sum(a.offset_rad for a in window) + offset_rad
            > math.radians(th.correction_window_max_deg)
        ):
            return CorrectionDecision(WINDOW_EXCEEDED, None, estimate, offset_m, offset_rad)
        return CorrectionDecision(SEND, "correction", estimate, offset_m, offset_rad)

    def mark_sent(
        self,
        motion: MotionState,
        now_ns: int,
        decision: CorrectionDecision | None = None,
        localization: LocalizationPose | None = None,
        seq: int | None = None,
    ) -> None:
        """Record that a pose was sent during ``motion``'s stop at ``now_ns``. With the
        ``decision`` (and the ``localization`` it was decided against), a correction joins the
        window (until :meth:`on_result` says the robot refused it); an initialization starts a
        new reference (empties the window)."""
        self._last_sent_ns = now_ns
        self._last_sent_stop_id = motion.stop_id
        while self._applied and now_ns - self._applied[0].sent_ns > self._window_ns:
            self._applied.popleft()
        if decision is None or decision.estimate is None:
            return
        if decision.kind == "initialization":
            self._applied.clear()
        elif decision.kind == "correction" and localization_known(localization):
            assert localization is not None
            est = decision.estimate
            self._applied.append(AppliedCorrection(
                seq, now_ns, est.x - localization.x, est.y - localization.y,
                angle_diff(est.theta, localization.theta), decision.offset_m,
                decision.offset_rad))

    def on_result(self, seq: int, accepted: bool) -> None:
        """The robot's answer to correction ``seq``: a refused one did not move the robot, so it
        leaves the window."""
        if not accepted:
            self._applied = collections.deque(a for a in self._applied if a.seq != seq)
