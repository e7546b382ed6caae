"""The continuous pose output: the backend's estimates as a pose topic the robot can fuse.

One-shot corrections (:mod:`robot_bridge.policy`) reach the robot only when it is static,
because the HSR localizer and AMCL accept a new pose only then. A lab running
robot_localization or Nav2 also wants the allocentric pose as a *measurement*, continuously,
like motion capture or GPS: :class:`PoseOutput` decides, at a configured rate, which estimates
go out (the newest fused one, optionally the newest camera-only one, each at most once and
only while fresh) and, optionally, the ``map -> odom`` transform implied by the newest fused
estimate and the odometry at its stamp.

Transport-free: it is fed the estimates and odometry the bridge accepted and returns what is
due; the adapter publishes it (``publish_pose`` / ``publish_transform``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Final

import numpy as np

from core.geometry import se2_compose, se2_inverse
from core.history import StampedHistory, lerp_se2
from core.site import ClockPolicy
from protocol.messages import NS_PER_S, PoseEstimate
from robot_bridge.adapters.base import MapToOdom

#: odometry kept to find the robot's odometry pose at an estimate's stamp
ODOMETRY_HISTORY: Final = 2048


@dataclasses.dataclass(frozen=True)
class PoseOutputConfig:
    """The robot bridge's continuous pose output (site file section ``pose_output``).

    ``rate_hz``: how often the newest estimates are published (0 turns the output off).
    ``fused`` / ``cameras``: publish the fused estimate (topic ``smartedge/pose``) and / or the
    camera-only one (``smartedge/camera_pose``). An estimate older than the site's
    ``clock.max_age_ms`` at publication is not published (after a stall the robot gets nothing
    rather than the past). ``map_to_odom``: also publish the ``map -> odom`` transform on
    ``/tf`` (only when the robot's own localizer does not: two publishers of one transform
    fight). ``odom_frame``: the child frame of that transform when the odometry does not name
    one. ``transform_tolerance_s``:
    the transform is stamped this far after the latest estimate, as AMCL does, and republished
    at ``rate_hz`` with the same offset from the bridge clock. ``odometry_match_s``: the
    odometry must bracket the estimate's stamp, or end at most this long before it.
    """

    rate_hz: float = 10.0
    fused: bool = True
    cameras: bool = False
    map_to_odom: bool = False
    odom_frame: str = "odom"
    transform_tolerance_s: float = 0.1
    odometry_match_s: float = 0.2

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 0.0 <= self.rate_hz <= 1000.0):
            raise ValueError(f"rate_hz {self.rate_hz}: expected 0 (off) to 1000")
        for name in ("transform_tolerance_s", "odometry_match_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} {value}: expected a finite value >= 0")
        if not self.odom_frame.strip():
            raise ValueError("odom_frame is empty")

    @property
    def streams(self) -> tuple[str, ...]:
        """The estimate streams published: ``fused``, ``cameras``."""
        return tuple(s for s, on in (("fused", self.fused), ("cameras", self.cameras)) if on)

    @property
    def enabled(self) -> bool:
        return self.rate_hz > 0.0 and bool(self.streams or self.map_to_odom)


@dataclasses.dataclass(frozen=True)
class PoseOutputBatch:
    """What is due now: ``poses`` as (stream, estimate) pairs, and the transform (or
    ``None``). ``skipped``: reasons something was due but not sent (``stale_fused``,
    ``map_to_odom_no_odometry``...), for the bridge's counters."""

    poses: tuple[tuple[str, PoseEstimate], ...] = ()
    transform: MapToOdom | None = None
    skipped: tuple[str, ...] = ()


#: an estimate's ``source`` → its output stream
_STREAM_OF_SOURCE: Final = {"fused": "fused", "cameras": "cameras"}


class PoseOutput:
    """Rate-limited selection of the pose output (module docstring). ``clock``: the site's clock
    policy (estimates older than ``max_age_ms`` are not published). Not thread-safe."""

    def __init__(self, config: PoseOutputConfig, world_frame: str = "map",
                 clock: ClockPolicy | None = None) -> None:
        self.config = config
        self.world_frame = world_frame
        self.clock = clock if clock is not None else ClockPolicy()
        self._period_ns = round(NS_PER_S / config.rate_hz) if config.rate_hz > 0 else 0
        self._tolerance_ns = round(config.transform_tolerance_s * NS_PER_S)
        self._match_ns = round(config.odometry_match_s * NS_PER_S)
        self._next_ns = 0
        self._latest: dict[str, PoseEstimate] = {}
        self._sent_stamp: dict[str, int] = {}
        # (x, y, theta) of the base in the odometry frame (m, rad) by stamp
        self._odometry: StampedHistory[tuple[float, float, float]] = StampedHistory(
            ODOMETRY_HISTORY, out_of_order="drop")
        self._odom_frame = config.odom_frame
        self._map_T_odom: np.ndarray | None = None
        self._map_T_odom_stamp_ns = -1  # stamp of the estimate it came from
        self._tf_tried_stamp_ns = -1  # the newest estimate it was tried with

    def on_estimate(self, estimate: PoseEstimate) -> None:
        """An estimate the bridge accepted (right robot, frame, stamp)."""
        stream = _STREAM_OF_SOURCE.get(estimate.source)
        if stream is None:
            return
        prev = self._latest.get(stream)
        if prev is None or estimate.stamp_ns >= prev.stamp_ns:
            self._latest[stream] = estimate

    def on_odometry(self, stamp_ns: int, x: float, y: float, theta: float,
                    frame_id: str | None = None) -> None:
        """An odometry reading the bridge accepted (stamps increasing; an older one is
        ignored)."""
        self._odometry.insert(int(stamp_ns), (float(x), float(y), float(theta)))
        if frame_id:
            self._odom_frame = frame_id

    def odometry_at(self, stamp_ns: int) -> np.ndarray | None:
        """The base's (x, y, theta) in the odometry frame at ``stamp_ns``: interpolated
        between the readings around it, or the newest when it ends at most
        ``odometry_match_s`` before; ``None`` otherwise (also across a gap of more than twice
        ``odometry_match_s`` between two readings: no motion is invented)."""
        last = self._odometry.latest()
        if last is None:
            return None
        if stamp_ns >= last.stamp_ns:
            return np.array(last.item) if stamp_ns - last.stamp_ns <= self._match_ns else None
        pose = self._odometry.interpolate(stamp_ns, lerp_se2, max_gap_ns=2 * self._match_ns)
        return None if pose is None else np.array(pose)

    def due(self, now_ns: int) -> PoseOutputBatch:
        """What to publish at ``now_ns`` (bridge clock, ns): nothing until a period has passed
        since the last call that published."""
        if not self.config.enabled or now_ns < self._next_ns:
            return PoseOutputBatch()
        self._next_ns = now_ns + self._period_ns
        poses: list[tuple[str, PoseEstimate]] = []
        skipped: list[str] = []
        for stream in self.config.streams:
            est = self._latest.get(stream)
            if est is None or self._sent_stamp.get(stream) == est.stamp_ns:
                continue
            self._sent_stamp[stream] = est.stamp_ns
            if self.clock.too_old(est.stamp_ns, now_ns):
                skipped.append(f"stale_{stream}")
                continue
            poses.append((stream, est))
        transform = None
        if self.config.map_to_odom:
            skipped.extend(self._update_map_to_odom())
            if self._map_T_odom is not None:
                x, y, theta = (float(v) for v in self._map_T_odom)
                transform = MapToOdom(
                    stamp_ns=max(now_ns, self._map_T_odom_stamp_ns) + self._tolerance_ns,
                    x=x, y=y, theta=theta,
                    parent_frame=self.world_frame, child_frame=self._odom_frame)
        return PoseOutputBatch(tuple(poses), transform, tuple(skipped))

    def _update_map_to_odom(self) -> list[str]:
        est = self._latest.get("fused")
        if est is None or est.stamp_ns <= self._tf_tried_stamp_ns:
            return []
        self._tf_tried_stamp_ns = est.stamp_ns  # one try (and one count) per estimate
        odom_T_base = self.odometry_at(est.stamp_ns)
        if odom_T_base is None:
            return ["map_to_odom_no_odometry"]
        map_T_base = np.array([est.x, est.y, est.theta])
        self._map_T_odom = se2_compose(map_T_base, se2_inverse(odom_T_base))
        self._map_T_odom_stamp_ns = est.stamp_ns
        return []
