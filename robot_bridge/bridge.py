"""The robot bridge core: robot odometry in, ``Odometry`` to the backend out, pose corrections
to the robot when it is static.

Transport-free: a :class:`RobotBridge` is fed readings and messages through ``on_*`` methods and
returns an :class:`Outbox` of messages to publish (``odometry`` → backend) and poses to push
(``corrections`` → the robot adapter, and to the correction key for monitoring). The Zenoh
service shell owns the sessions, subscriptions, status publication and liveliness; tests feed
the core directly.

Local autonomy: nothing here waits for the backend. Odometry is converted and returned at once
whatever the link state; when no heartbeat of the backend (its status message or liveliness
token, :meth:`RobotBridge.on_backend_heartbeat`) arrived for ``backend_timeout_s`` the status
says ``backend lost`` and the robot keeps navigating on its own localization. Pose estimates are
not heartbeats: anyone able to put one must not be able to fake the backend's health.

Bad input (wrong types, NaN, stamps in the future beyond the clock tolerance or going
backwards, other robots' poses, a ``source`` that does not match the key) is counted in
:attr:`RobotBridge.counters` and dropped; no ``on_*`` method raises. What the bridge demands of
an estimate before it moves the robot: :class:`robot_bridge.policy.TrustConfig`.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Mapping
from typing import Any, Final

from core.geometry import MotionState, StaticDetector, invert_transform, wrap_angle
from core.pose import PlanarPose
from core.site import ClockPolicy, Site, Thresholds
from protocol.errors import ProtocolError
from protocol.messages import Odometry, PoseCorrection, PoseEstimate, ServiceStatus
from robot_bridge.adapters.base import LocalizationPose, OdometrySample, RobotAdapter
from robot_bridge.policy import (
    HEADING_JUMP_TOO_LARGE,
    JUMP_TOO_LARGE,
    NS_PER_S,
    OUTSIDE_FLOOR,
    SEND,
    UNCERTAIN,
    UNFIT_FOR_INIT,
    WINDOW_EXCEEDED,
    CorrectionDecision,
    CorrectionPolicy,
    TrustConfig,
    floor_area_around,
    localization_known,
)
from robot_bridge.pose_output import PoseOutput, PoseOutputConfig

log = logging.getLogger(__name__)

SERVICE_NAME: Final = "robot-bridge"
#: Source preference when both a fused and a camera-only estimate exist for the current stop.
SOURCE_PREFERENCE: Final = ("fused", "cameras")
#: The ``source`` an estimate must carry on each robot topic (``protocol.keys``).
SOURCE_OF_TOPIC: Final = {"pose": "fused", "camera_pose": "cameras"}
#: The ``bridge`` section's keys that are :class:`BridgeConfig` fields (the rest: TrustConfig).
_BRIDGE_KEYS: Final = frozenset({"backend_timeout_s", "robot_timeout_s", "odometry_replay_s",
                                 "correction_confirm_s"})
#: refusals of the newest estimate after which the bridge tries the other recent estimates of
#: the stop: a stream of implausible estimates that always holds the newest stamp (a peer
#: posing as the backend without the router's access control) must not starve the genuine ones
FALLBACK_REASONS: Final = frozenset({JUMP_TOO_LARGE, HEADING_JUMP_TOO_LARGE, WINDOW_EXCEEDED,
                                     OUTSIDE_FLOOR, UNCERTAIN, UNFIT_FOR_INIT})
#: recent estimates kept per source for that fallback
RECENT_ESTIMATES: Final = 64
#: at most this many odometry messages are kept for a replay to a returning backend
ODOMETRY_REPLAY_MAX: Final = 8192


@dataclasses.dataclass(frozen=True)
class BridgeConfig:
    """Configuration of one bridge (one robot).

    ``backend_timeout_s``: no status message or liveliness token of the backend for this long
    means the backend (or the link) is lost. ``robot_timeout_s``: the same for robot odometry.
    ``world_frame``: the frame estimates must be expressed in (the site's world frame).
    ``pose_output``: the continuous pose output (site file section ``pose_output``).
    ``odometry_replay_s``: odometry published while the backend was away (a restart, a link
    loss) is published again when it returns, up to this much of it (older is counted
    ``odometry_lost``). ``correction_confirm_s``: after a correction, the robot's own
    localization must move to it within this long (``corrections_confirmed``, else
    ``corrections_unconfirmed``); robots that report no localization are counted
    ``corrections_unverifiable``. ``clock``: the site's clock policy (``clock`` section): estimates
    and odometry stamped more than ``clock.max_future_ms`` ahead of the bridge's clock are refused
    (the hosts' clocks must agree this well, e.g. chrony). ``trust``: what an estimate must satisfy,
    :class:`robot_bridge.policy.TrustConfig`, from the ``bridge`` section's other keys (defaults):
    ``position_std_floor_m`` (0.02), ``yaw_std_floor_deg`` (1), ``init_agreement_count`` (3),
    ``init_agreement_m`` (0.2), ``init_agreement_deg`` (10), ``floor_area`` (``[x_min, y_min, x_max,
    y_max]``; default: the cameras' positions +- ``floor_margin_m``) and ``floor_margin_m`` (10);
    docs/robot_bridge.md, "What the bridge trusts". Built in code without a site, no floor area
    bounds the initialization.
    """

    robot_id: str
    thresholds: Thresholds = dataclasses.field(default_factory=Thresholds)
    backend_timeout_s: float = 3.0
    robot_timeout_s: float = 1.0
    odometry_replay_s: float = 30.0
    correction_confirm_s: float = 3.0
    world_frame: str = "map"
    pose_output: PoseOutputConfig = dataclasses.field(default_factory=PoseOutputConfig)
    trust: TrustConfig = dataclasses.field(default_factory=TrustConfig)
    clock: ClockPolicy = dataclasses.field(default_factory=ClockPolicy)

    @classmethod
    def from_site(cls, site: Site, robot_id: str) -> BridgeConfig:
        """The bridge of ``robot_id``: the site's thresholds, clock and world frame, its ``bridge``
        section (``backend_timeout_s``, ``robot_timeout_s`` and the :class:`TrustConfig` keys,
        ``floor_area`` as ``[x_min, y_min, x_max, y_max]``) and its ``pose_output`` section;
        errors name the file and the key. Without a ``floor_area`` the initialization is bounded
        by the cameras' positions grown by ``floor_margin_m``."""
        reader = site.section_reader()
        pose_output = reader.section("pose_output", site.section("pose_output"),
                                     PoseOutputConfig)
        node = dict(reader.mapping("bridge", site.section("bridge")))
        trust_keys = {f.name for f in dataclasses.fields(TrustConfig)}
        reader.no_unknown("bridge", node, set(_BRIDGE_KEYS) | trust_keys)
        floor = node.pop("floor_area", None)
        trust = reader.section(
            "bridge", {k: v for k, v in node.items() if k in trust_keys}, TrustConfig, int_lo=1)
        if floor is not None:
            area: tuple[float, ...] = tuple(
                float(v) for v in reader.vector("bridge.floor_area", floor, 4))
            if not (area[0] < area[2] and area[1] < area[3]):
                raise reader.fail("bridge.floor_area",
                                  "expected [x_min, y_min, x_max, y_max] with min < max")
        else:
            cameras_xy = [invert_transform(cam.T_cam_world)[:2, 3]
                          for cam in site.cameras.values()]
            area = floor_area_around(cameras_xy, trust.floor_margin_m)
            log.info("bridge.floor_area not set in %s: initial poses bounded to the cameras' "
                     "positions +- %.1f m: x %.1f..%.1f, y %.1f..%.1f", site.source_path,
                     trust.floor_margin_m, area[0], area[2], area[1], area[3])
        trust = dataclasses.replace(trust, floor_area=area)
        return reader.section(
            "bridge", {k: v for k, v in node.items() if k in _BRIDGE_KEYS}, cls,
            fields=set(_BRIDGE_KEYS),
            base=cls(robot_id, site.thresholds, world_frame=site.world_frame,
                     pose_output=pose_output, trust=trust, clock=site.clock))


@dataclasses.dataclass(frozen=True)
class Outbox:
    """What one call produced: ``odometry`` to publish to the backend, ``corrections`` to push
    to the robot (and to publish on the correction key)."""

    odometry: tuple[Odometry, ...] = ()
    corrections: tuple[PoseCorrection, ...] = ()

    def __add__(self, other: Outbox) -> Outbox:
        return Outbox(self.odometry + other.odometry, self.corrections + other.corrections)

    def __bool__(self) -> bool:
        return bool(self.odometry or self.corrections)


@dataclasses.dataclass(frozen=True)
class BridgeStatus:
    """Health of the bridge at ``now_ns``.

    ``state``: ``starting`` (nothing heard yet), ``ok``, or ``degraded`` (backend or robot
    silent); ``detail`` says which in words. ``last_decision``: reason of the latest correction
    decision (``send``, ``moving``, ``offset_below_threshold``...).
    """

    now_ns: int
    state: str
    detail: str
    backend_alive: bool
    robot_alive: bool
    localization_known: bool
    is_static: bool
    stop_id: int
    last_decision: str
    counters: Mapping[str, int]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


class RobotBridge:
    """Bridge core for one robot (see module docstring). Not thread-safe: one worker loop
    calls it."""

    def __init__(self, config: BridgeConfig) -> None:
        self.config = config
        th = config.thresholds
        # stamps ahead of the bridge's clock by more than the site's clock policy are refused
        self._max_future_ns = config.clock.max_future_ns
        self._backend_timeout_ns = round(config.backend_timeout_s * NS_PER_S)
        self._robot_timeout_ns = round(config.robot_timeout_s * NS_PER_S)
        self._static = StaticDetector.from_thresholds(th)
        self._policy = CorrectionPolicy(th, config.trust)
        self._counters: dict[str, int] = {}
        self._now_ns = 0
        self._odom_seq = 0
        self._correction_seq = 0
        self._last_odom_stamp_ns: int | None = None
        self._last_odom_rx_ns: int | None = None
        self._last_backend_ns: int | None = None
        self._backend_gone = False
        self._localization: LocalizationPose | None = None
        self._estimates: dict[str, PoseEstimate] = {}
        # every accepted estimate of the last moments per source, newest stamp or not
        self._recent: dict[str, collections.deque[PoseEstimate]] = {}
        self._fallback_context: tuple[int, int] | None = None
        self._fallback_refused: set[tuple[str, int, int]] = set()
        self._last_decision: CorrectionDecision = CorrectionDecision("moving")
        self._counted: collections.deque[tuple[Any, str]] = collections.deque(maxlen=8)
        self._pose_output = PoseOutput(config.pose_output, config.world_frame, config.clock)
        self._warned: set[str] = set()
        # odometry published recently, for a backend that comes back (see odometry_replay_s)
        self._sent_odometry: collections.deque[Odometry] = collections.deque()
        self._replay_window_ns = round(config.odometry_replay_s * NS_PER_S)
        self._pending_replay: list[Odometry] = []
        # the correction whose effect on the robot's localization is being checked, and when
        # it was applied (bridge clock)
        self._confirming: tuple[PoseCorrection, int] | None = None
        self._confirm_ns = round(config.correction_confirm_s * NS_PER_S)

    # ---------------------------------------------------------------------------------------
    # inputs
    # ---------------------------------------------------------------------------------------

    def on_robot_odometry(self, sample: Any, receive_ns: int | None = None) -> Outbox:
        """One odometry reading from the robot adapter (:class:`OdometrySample`).

        Returns the :class:`Odometry` message to publish to the backend (at once, whatever the
        backend's state), plus a correction when this sample completes a stop's dwell time.
        ``receive_ns``: when it arrived, on the same clock as the stamps (the service passes
        its wall clock): stamps more than ``clock.max_future_ms`` after it are rejected. ``None``:
        unknown (replay), the stamp is trusted.
        """
        try:
            return self._on_odometry(sample, receive_ns)
        except Exception:  # the robot must never be stopped by a bridge bug
            log.exception("unexpected error on robot odometry")
            self._count("internal_error")
            return Outbox()

    def on_robot_localization(self, pose: Any, receive_ns: int | None = None) -> Outbox:
        """The robot's own map-frame pose (:class:`LocalizationPose`), or ``None`` when the
        robot has none (never localized)."""
        try:
            if pose is not None and not isinstance(pose, LocalizationPose):
                return self._reject("invalid_localization", f"type {type(pose).__name__}")
            if pose is not None and (not _is_int(pose.stamp_ns) or pose.stamp_ns < 0):
                return self._reject("invalid_localization", "bad stamp")
            if pose is not None and not pose.lost and not pose.is_finite:
                return self._reject("invalid_localization", "non-finite pose")
            if pose is not None and pose.frame_id != self.config.world_frame:
                return self._reject("wrong_frame_localization", pose.frame_id)
            self._advance(receive_ns)
            self._count("received_localization")
            self._localization = pose
            self._check_confirmation()
            return self._evaluate()
        except Exception:
            log.exception("unexpected error on robot localization")
            self._count("internal_error")
            return Outbox()

    def on_pose_estimate(
        self, estimate: Any, receive_ns: int | None = None, topic: str | None = None
    ) -> Outbox:
        """A pose estimate of the backend (``source`` ``fused`` or ``cameras``); may produce a
        correction when the robot is static. ``topic``: the robot topic it came on (``pose``
        or ``camera_pose``): its ``source`` must match (else ``source_key_mismatch``).
        ``receive_ns``: as for odometry, stamps beyond the clock tolerance after it are
        refused. Not a sign of life of the backend (:meth:`on_backend_heartbeat` is)."""
        try:
            return self._on_estimate(estimate, receive_ns, topic)
        except Exception:
            log.exception("unexpected error on pose estimate")
            self._count("internal_error")
            return Outbox()

    def on_backend_heartbeat(self, receive_ns: int | None = None) -> None:
        """The backend is alive: its status message or liveliness token was seen (the only
        signs of life; estimates are not). A backend that returns after being lost (a restart,
        a link loss) gets the odometry published since it was last seen again, oldest first,
        with the next :meth:`pump` / :meth:`tick` (``odometry_replayed``)."""
        self._advance(receive_ns)
        was_alive = self.backend_alive()
        since = self._last_backend_ns
        self._last_backend_ns = self._now_ns
        self._backend_gone = False
        if not was_alive and since is not None and self._sent_odometry:
            self._pending_replay = [m for m in self._sent_odometry if m.stamp_ns >= since]
            if self._pending_replay:
                log.info("backend back after %.1f s: replaying %d odometry messages",
                         (self._now_ns - since) * 1e-9, len(self._pending_replay))

    def on_backend_gone(self, receive_ns: int | None = None) -> None:
        """The backend's liveliness token disappeared: lost now, without waiting the timeout."""
        self._advance(receive_ns)
        self._backend_gone = True

    def on_correction_result(self, correction: PoseCorrection, accepted: bool) -> None:
        """What the adapter said when the correction was pushed: counted for the status and
        logged, one line per correction (info when accepted, warning when refused)."""
        self._count("corrections_accepted" if accepted else "corrections_refused")
        self._policy.on_result(correction.seq, accepted)
        if accepted:
            if self._confirming is not None:  # superseded before it could be confirmed
                self._count("corrections_unconfirmed")
            self._confirming = (correction, self._now_ns)
        log.log(
            logging.INFO if accepted else logging.WARNING,
            "%s %d %s %s: (%.3f, %.3f, %.1f deg), offset %.3f m / %.1f deg",
            correction.kind, correction.seq,
            "applied to" if accepted else "refused by", self.config.robot_id,
            correction.x, correction.y, math.degrees(correction.theta),
            correction.offset_m, math.degrees(correction.offset_rad),
        )

    def tick(self, now_ns: int) -> Outbox:
        """Advance the bridge clock to ``now_ns`` (ns, same clock as the odometry stamps) and
        re-evaluate the correction rule. Call it periodically (e.g. 10 Hz)."""
        try:
            if not _is_int(now_ns) or now_ns < 0:
                return self._reject("invalid_tick", repr(now_ns)[:40])
            self._advance(now_ns)
            self._check_confirmation()
            replay, self._pending_replay = self._pending_replay, []
            if replay:
                self._count("odometry_replayed", len(replay))
            return Outbox(odometry=tuple(replay)) + self._evaluate()
        except Exception:
            log.exception("unexpected error on tick")
            self._count("internal_error")
            return Outbox()

    def pump(self, adapter: RobotAdapter, now_ns: int) -> Outbox:
        """One step of a worker loop between a robot adapter and this core (no transport).

        Reads the adapter's new odometry and its latest localization, feeds them in, ticks at
        ``now_ns``, pushes any corrections to the robot (:meth:`apply`) and
        returns everything produced (odometry to publish; corrections to publish for
        monitoring). Adapter exceptions are counted as ``adapter_error``, never raised.
        """
        out = Outbox()
        try:
            samples = list(adapter.read_odometry())
        except Exception:
            log.exception("adapter %s: read_odometry failed", adapter.name)
            self._count("adapter_error")
            samples = []
        for sample in samples:
            out = out + self.on_robot_odometry(sample, now_ns)
        try:
            localization = adapter.read_localization()
        except Exception:
            log.exception("adapter %s: read_localization failed", adapter.name)
            self._count("adapter_error")
        else:
            if localization is not None and localization is not self._localization:
                out = out + self.on_robot_localization(localization, now_ns)
        return self.apply(adapter, out + self.tick(now_ns))

    def apply(self, adapter: RobotAdapter, outbox: Outbox) -> Outbox:
        """Push every correction of ``outbox`` to the robot with ``adapter.apply_correction``
        and record the answer (:meth:`on_correction_result`). The one place a correction
        reaches the robot: :meth:`pump` uses it for the corrections it decides, a service loop
        for those decided on an incoming estimate (:meth:`on_pose_estimate`). Returns
        ``outbox`` unchanged (to publish); adapter exceptions are counted as
        ``adapter_error`` and the correction as refused, never raised."""
        for correction in outbox.corrections:
            try:
                accepted = bool(adapter.apply_correction(correction))
            except Exception:
                log.exception("adapter %s: apply_correction failed", adapter.name)
                self._count("adapter_error")
                accepted = False
            self.on_correction_result(correction, accepted)
        return outbox

    def publish_pose_output(self, adapter: RobotAdapter, now_ns: int) -> int:
        """Hand the pose output due at ``now_ns`` (:class:`PoseOutput`) to the adapter: the
        newest accepted estimates (``publish_pose``) and the map -> odom transform
        (``publish_transform``). Counts ``pose_output_<stream>`` / ``pose_output_tf`` when
        the adapter sent them, ``..._failed`` when it did not (or cannot),
        ``pose_output_stale_<stream>`` and ``pose_output_map_to_odom_no_odometry`` for what
        was due but not sendable. Returns the number of messages sent; never raises."""
        try:
            batch = self._pose_output.due(int(now_ns))
        except Exception:
            log.exception("unexpected error in the pose output")
            self._count("internal_error")
            return 0
        for why in batch.skipped:
            self._count(f"pose_output_{why}")
        sent = 0
        calls: list[tuple[str, Callable[[], bool]]] = [
            (f"pose_output_{stream}", functools.partial(adapter.publish_pose, est, stream))
            for stream, est in batch.poses]
        if batch.transform is not None:
            calls.append(("pose_output_tf",
                          functools.partial(adapter.publish_transform, batch.transform)))
        for counter, call in calls:
            try:
                ok = bool(call())
            except Exception:
                log.exception("adapter %s: pose output failed", adapter.name)
                self._count("adapter_error")
                ok = False
            if ok:
                sent += 1
                self._count(counter)
            else:
                self._count(f"{counter}_failed")
        return sent

    # ---------------------------------------------------------------------------------------
    # status
    # ---------------------------------------------------------------------------------------

    @property
    def counters(self) -> Mapping[str, int]:
        return dict(self._counters)

    @property
    def motion(self) -> MotionState:
        return self._static.state

    def backend_alive(self, now_ns: int | None = None) -> bool:
        """A heartbeat of the backend (status or liveliness) arrived within
        ``backend_timeout_s`` and its liveliness token has not gone since."""
        now = self._now_ns if now_ns is None else max(now_ns, self._now_ns)
        return (
            not self._backend_gone
            and self._last_backend_ns is not None
            and now - self._last_backend_ns <= self._backend_timeout_ns
        )

    def status(self, now_ns: int | None = None) -> BridgeStatus:
        """Health at ``now_ns`` (default: the bridge clock)."""
        now = self._now_ns if now_ns is None else max(int(now_ns), self._now_ns)
        backend = self.backend_alive(now)
        robot = (
            self._last_odom_rx_ns is not None
            and now - self._last_odom_rx_ns <= self._robot_timeout_ns
        )
        problems = []
        if self._last_odom_rx_ns is None and self._last_backend_ns is None:
            state = "starting"
            problems.append("waiting for robot odometry and backend")
        else:
            if not robot:
                problems.append(
                    "robot lost: no odometry"
                    if self._last_odom_rx_ns is None
                    else f"robot lost: no odometry for {(now - self._last_odom_rx_ns) / 1e9:.1f} s"
                )
            if not backend:
                if self._last_backend_ns is None:
                    problems.append("backend lost: never heard")
                elif self._backend_gone:
                    problems.append("backend lost: liveliness token gone or status stopping")
                else:
                    silent_s = (now - self._last_backend_ns) / 1e9
                    problems.append(f"backend lost: no status or liveliness for {silent_s:.1f} s")
                problems.append("robot navigates on its own localization")
            state = "degraded" if problems else "ok"
        return BridgeStatus(
            now_ns=now,
            state=state,
            detail="; ".join(problems),
            backend_alive=backend,
            robot_alive=robot,
            localization_known=localization_known(self._localization),
            is_static=self._static.state.is_static,
            stop_id=self._static.state.stop_id,
            last_decision=self._last_decision.reason,
            counters=dict(self._counters),
        )

    def service_status(self, now_ns: int, seq: int, uptime_s: float = 0.0) -> ServiceStatus:
        """The :class:`ServiceStatus` message of this bridge (``robot-bridge/<robot_id>``)."""
        st = self.status(now_ns)
        peers = ("backend",) if st.backend_alive else ()
        return ServiceStatus(
            service=SERVICE_NAME,
            instance_id=self.config.robot_id,
            stamp_ns=st.now_ns,
            seq=seq,
            state=st.state,
            uptime_s=max(0.0, float(uptime_s)),
            counters=st.counters,
            peers_alive=peers,
            detail=(st.detail or f"static={st.is_static} last_decision={st.last_decision}")[
                :1000
            ],
        )

    # ---------------------------------------------------------------------------------------
    # internals
    # ---------------------------------------------------------------------------------------

    def _remember_odometry(self, msg: Odometry) -> None:
        """Keep ``msg`` for a replay; what falls out of the window unheard by any backend is
        counted ``odometry_lost``."""
        self._sent_odometry.append(msg)
        buf = self._sent_odometry
        while buf and (len(buf) > ODOMETRY_REPLAY_MAX
                       or msg.stamp_ns - buf[0].stamp_ns > self._replay_window_ns):
            old = buf.popleft()
            if not self.backend_alive() and (
                    self._last_backend_ns is not None and old.stamp_ns >= self._last_backend_ns):
                self._count("odometry_lost")

    def _check_confirmation(self) -> None:
        """Whether the robot's localization moved to the correction being checked: within
        half the correction's offset (at least 2 cm / 1 deg) of it, reported after it was
        applied. Decided once per correction."""
        if self._confirming is None:
            return
        correction, applied_ns = self._confirming
        loc = self._localization
        if loc is not None and not loc.lost and loc.stamp_ns >= correction.stamp_ns:
            tol_m = max(0.02, 0.5 * correction.offset_m)
            tol_rad = max(math.radians(1.0), 0.5 * correction.offset_rad)
            d_m, d_rad = loc.pose.distance_to(PlanarPose.of(correction))
            if d_m <= tol_m and d_rad <= tol_rad:
                self._count("corrections_confirmed")
                self._confirming = None
                return
        if self._now_ns - applied_ns > self._confirm_ns:
            self._confirming = None
            if self._localization is None:
                self._count("corrections_unverifiable")
                return
            self._count("corrections_unconfirmed")
            log.warning(
                "%s %d for %s: the robot's localization did not move to it within %.1f s "
                "(it says (%.3f, %.3f, %.1f deg))", correction.kind, correction.seq,
                self.config.robot_id, self._confirm_ns * 1e-9, loc.x if loc else float("nan"),
                loc.y if loc else float("nan"),
                math.degrees(loc.theta) if loc else float("nan"))

    def _count(self, what: str, n: int = 1) -> None:
        self._counters[what] = self._counters.get(what, 0) + n

    def _reject(self, counter: str, why: str) -> Outbox:
        self._count(counter)
        log.debug("dropped (%s): %s", counter, why)
        return Outbox()

    def _advance(self, now_ns: int | None) -> None:
        if _is_int(now_ns) and now_ns > self._now_ns:  # type: ignore[operator]
            self._now_ns = int(now_ns)  # type: ignore[arg-type]

    def _future(self, what: str, stamp_ns: int, receive_ns: int | None) -> bool:
        # Only a receive time can tell: without one, a stamp after a gap in the data would look
        # like the future.
        if not _is_int(receive_ns):
            return False
        ahead_ns = stamp_ns - receive_ns  # type: ignore[operator]
        if ahead_ns <= self._max_future_ns:
            return False
        if what not in self._warned:  # once: a clock problem repeats on every message
            self._warned.add(what)
            log.warning("%s stamped %.0f ms ahead of the bridge's clock (clock.max_future_ms "
                        "%.0f): refused; check the hosts' clock synchronization or the sender",
                        what, ahead_ns / 1e6, self._max_future_ns / 1e6)
        return True

    def _on_odometry(self, sample: Any, receive_ns: int | None) -> Outbox:
        if not isinstance(sample, OdometrySample):
            return self._reject("invalid_odometry", f"type {type(sample).__name__}")
        if not _is_int(sample.stamp_ns) or sample.stamp_ns < 0:
            return self._reject("invalid_odometry", "bad stamp")
        if self._future("odometry", sample.stamp_ns, receive_ns):
            return self._reject("future_stamp_odometry", str(sample.stamp_ns))
        if self._last_odom_stamp_ns is not None and sample.stamp_ns <= self._last_odom_stamp_ns:
            return self._reject("out_of_order_odometry", str(sample.stamp_ns))
        try:
            theta = float(sample.theta)
            msg = Odometry(
                robot_id=self.config.robot_id,
                stamp_ns=sample.stamp_ns,
                seq=self._odom_seq,
                x=sample.x,
                y=sample.y,
                theta=wrap_angle(theta) if math.isfinite(theta) else theta,
                vx=sample.vx,
                vy=sample.vy,
                wz=sample.wz,
                covariance=sample.covariance,
                frame_id=sample.frame_id,
            )
        except (ProtocolError, TypeError, ValueError) as exc:
            return self._reject("invalid_odometry", str(exc))
        self._odom_seq += 1
        self._last_odom_stamp_ns = msg.stamp_ns
        self._advance(msg.stamp_ns)
        self._advance(receive_ns)
        self._last_odom_rx_ns = self._now_ns
        self._count("received_odometry")
        self._static.update(msg.stamp_ns, msg.vx, msg.vy, msg.wz)
        self._remember_odometry(msg)
        if math.isfinite(msg.theta):
            self._pose_output.on_odometry(msg.stamp_ns, msg.x, msg.y, msg.theta, msg.frame_id)
        return Outbox(odometry=(msg,)) + self._evaluate()

    def _on_estimate(self, estimate: Any, receive_ns: int | None, topic: str | None) -> Outbox:
        if not isinstance(estimate, PoseEstimate):
            return self._reject("invalid_estimate", f"type {type(estimate).__name__}")
        if estimate.robot_id != self.config.robot_id:
            return self._reject("other_robot_estimate", estimate.robot_id)
        if estimate.frame_id != self.config.world_frame:
            return self._reject("wrong_frame_estimate", estimate.frame_id)
        if topic is not None and SOURCE_OF_TOPIC.get(topic) != estimate.source:
            return self._reject("source_key_mismatch", f"{estimate.source} on {topic}")
        # refused before it can touch the newest-stamp state: a stamp from the future must not
        # make the genuine estimates after it look late
        if self._future("estimate", estimate.stamp_ns, receive_ns):
            return self._reject("future_stamp_estimate", str(estimate.stamp_ns))
        self._advance(receive_ns)
        self._count(f"received_estimate_{estimate.source}")
        self._recent.setdefault(estimate.source, collections.deque(maxlen=RECENT_ESTIMATES)
                                ).append(estimate)
        prev = self._estimates.get(estimate.source)
        if prev is None or estimate.stamp_ns >= prev.stamp_ns:
            self._estimates[estimate.source] = estimate
            self._policy.observe(estimate)
            self._pose_output.on_estimate(estimate)
        else:
            self._count("late_estimate")
        return self._evaluate()

    def _count_once(self, estimate: PoseEstimate, reason: str) -> None:
        """Count ``skip_<reason>`` once per (estimate, reason), not once per tick."""
        key = ((estimate.source, estimate.seq, estimate.stamp_ns), reason)
        if key not in self._counted:
            self._counted.append(key)
            self._count(f"skip_{reason}")

    def _best_estimate(self, motion: MotionState) -> PoseEstimate | None:
        """The preferred estimate observed during the current stop (fused over camera-only)."""
        if motion.still_since_ns is None:
            return None
        for source in SOURCE_PREFERENCE:
            est = self._estimates.get(source)
            if est is not None and est.stamp_ns >= motion.still_since_ns:
                return est
        return None

    def _fallback(self, motion: MotionState, refused: PoseEstimate) -> CorrectionDecision | None:
        """A sendable decision on another recent estimate of this stop (newest first, fused
        before camera-only) when the newest one was refused by a plausibility gate, or
        ``None``."""
        assert motion.still_since_ns is not None
        # an estimate a gate refused stays refused while the localization (a new reading at
        # least every pump) and the stop are the same: each is tried once, not at every
        # odometry message (2.4 ms per message with 64 forged estimates to try)
        context = (id(self._localization), motion.stop_id)
        if context != self._fallback_context:
            self._fallback_context = context
            self._fallback_refused.clear()
        for source in SOURCE_PREFERENCE:
            candidates = sorted(self._recent.get(source, ()), key=lambda e: -e.stamp_ns)
            for est in candidates:
                if est is refused or est.stamp_ns < motion.still_since_ns:
                    continue
                key = (est.source, est.seq, est.stamp_ns)
                if key in self._fallback_refused:
                    continue
                alt = self._policy.decide(est, self._localization, motion, self._now_ns)
                if alt.send:
                    return alt
                self._fallback_refused.add(key)
        return None

    def _evaluate(self) -> Outbox:
        motion = self._static.state
        estimate = self._best_estimate(motion)
        decision = self._policy.decide(estimate, self._localization, motion, self._now_ns)
        if (not decision.send and decision.reason in FALLBACK_REASONS
                and estimate is not None):
            self._count_once(estimate, decision.reason)
            alt = self._fallback(motion, estimate)
            if alt is not None:
                self._count("fallback_estimate")
                decision = alt
        self._last_decision = decision
        if decision.estimate is not None and not decision.send:
            self._count_once(decision.estimate, decision.reason)
        if not decision.send:
            return Outbox()
        est = decision.estimate
        assert est is not None and decision.kind is not None
        try:
            correction = PoseCorrection(
                robot_id=self.config.robot_id,
                stamp_ns=est.stamp_ns,
                seq=self._correction_seq,
                x=est.x,
                y=est.y,
                theta=wrap_angle(est.theta),
                covariance=self._policy.floored(est.covariance),
                kind=decision.kind,
                offset_m=decision.offset_m,
                offset_rad=decision.offset_rad,
                frame_id=self.config.world_frame,
            )
        except ProtocolError as exc:
            return self._reject("invalid_correction", str(exc))
        self._correction_seq += 1
        self._policy.mark_sent(motion, self._now_ns, decision, self._localization,
                               correction.seq)
        self._count("initializations_sent" if decision.kind == "initialization" else
                    "corrections_sent")
        # logged once, when the robot answers (on_correction_result)
        log.debug("%s %d decided for %s", decision.kind, correction.seq, self.config.robot_id)
        return Outbox(corrections=(correction,))


__all__ = [
    "SEND",
    "BridgeConfig",
    "BridgeStatus",
    "Outbox",
    "RobotBridge",
]
