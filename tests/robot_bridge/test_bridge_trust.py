"""The attacks of issue 17 on the robot bridge, over real Zenoh on loopback, now refused and
counted: a fake fused pose stamped in the future, a zero-covariance estimate, repeated
sub-limit jumps, a kidnapped initialization outside the room, an initialization from estimates
that do not agree, an estimate whose source does not match its key, and estimates posing as
the backend's heartbeat.

The bridge is the service node (:class:`RobotBridgeNode` on the example site) with its own
Zenoh session; a second session is the peer (the attacker, or the backend). Each sample is
decoded and handed to the node by the runtime's ``dispatch``, as :class:`ZenohRunner` does;
time is the simulated robot's clock, so the runs are deterministic. Who may put on a key at
all is the router's access control (not tested here)."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

from core.runtime import Subscription, dispatch
from protocol import encode, keys
from protocol.messages import PoseCorrection, PoseEstimate, ServiceStatus
from robot_bridge.adapters.sim import SimRobotAdapter
from robot_bridge.service import RobotBridgeNode
from tests.conftest import wait_until
from tests.robot_bridge.test_bridge import DriftingRobot, S

zenoh = pytest.importorskip("zenoh")

#: what the genuine backend adds between a camera frame and the estimate reaching the bridge
LATENCY_NS = 60_000_000


class Rig:
    """A bridge node on a drifting robot, fed over Zenoh by a peer session.

    ``put`` publishes from the peer; ``step`` waits for everything put so far to arrive,
    dispatches it to the node at the robot's clock, advances the robot by one 50 Hz tick and
    ticks the node (which pumps the robot adapter)."""

    def __init__(self, pair: Any, site: Any, robot: DriftingRobot, *, localized: bool = True,
                 correction_source: str = "fused") -> None:
        bridge_side, self.peer, _ = pair
        self.robot = robot
        self.adapter = SimRobotAdapter(robot, localized=localized)
        self.node = RobotBridgeNode(
            site, "hsr", lambda session: self.adapter, correction_source=correction_source,
            advance=lambda now_ns: self.adapter.advance_to(robot.t_s))
        self.node.attach(bridge_side)
        self.site = self.node.site
        self.pose_key = keys.pose_key(self.site, "hsr")
        self.camera_pose_key = keys.camera_pose_key(self.site, "hsr")
        self.status_key = keys.status_key(self.site, "backend", "main")
        self._subs: list[tuple[Subscription, Any]] = [
            (sub, bridge_side.declare_subscriber(sub.key_expr, zenoh.handlers.FifoChannel(4096)))
            for sub in self.node.subscriptions() if not sub.liveliness
        ]
        self.sent = 0
        self.received = 0
        self.corrections: list[PoseCorrection] = []
        self.n = 0
        topic = self.pose_key if correction_source == "fused" else self.camera_pose_key
        self._publishers = {key: self.peer.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK)
            for key in (topic, self.status_key)}
        # a put before the peer knows the bridge's subscriptions would go nowhere
        assert wait_until(lambda: all(p.matching_status.matching
                                      for p in self._publishers.values()), 10.0)

    def status_message(self, state: str = "ok") -> ServiceStatus:
        return ServiceStatus("backend", "main", self.robot.t_ns, 0, state)

    def put(self, key: str, message: Any) -> None:
        self._publishers[key].put(encode(message))
        self.sent += 1

    def _drain(self) -> int:
        got = 0
        for sub, channel in self._subs:
            while (sample := channel.try_recv()) is not None:
                got += 1
                out = dispatch(self.node, sub, str(sample.key_expr), sample.payload.to_bytes(),
                               self.robot.t_ns)
                self._collect(out)
        self.received += got
        return got

    def _collect(self, out: Any) -> None:
        self.corrections.extend(o.message for o in out if o.key.endswith("/correction"))

    def step(self, vx: float = 0.0, heartbeat: bool = True) -> None:
        """One 50 Hz tick: what was put arrives (with the backend's status once a second when
        ``heartbeat``), then the robot moves and the node ticks."""
        self.n += 1
        if heartbeat and self.n % 50 == 1:
            self.put(self.status_key, self.status_message())
        assert wait_until(lambda: (self._drain(), self.received >= self.sent)[1], 5.0, 0.001), (
            f"{self.sent - self.received} samples lost on loopback")
        self.robot.step(vx, 0.0)
        self._collect(self.node.tick(self.robot.t_ns))

    def estimate(self, x: float, y: float, theta: float, *, stamp_ns: int | None = None,
                 std_m: float = 0.01, source: str = "fused", seq: int = 0) -> PoseEstimate:
        cov = np.diag([std_m**2, std_m**2, math.radians(0.5) ** 2])
        return PoseEstimate("hsr", self.robot.t_ns if stamp_ns is None else stamp_ns, seq,
                            x, y, theta, cov, source, ("cam_sw", "cam_se"))

    def genuine(self, seq: int, source: str = "fused") -> PoseEstimate:
        """The backend's estimate of the true pose, stamped one latency ago."""
        x, y, th = self.robot.true
        return self.estimate(float(x), float(y), float(th), stamp_ns=self.robot.t_ns - LATENCY_NS,
                             source=source, seq=seq)

    def localization(self) -> np.ndarray:
        return self.robot.localization_pose()

    @property
    def counters(self) -> dict[str, int]:
        return self.node.counters()

    def error_m(self) -> float:
        return self.robot.localization_error()[0]


@pytest.fixture
def rig(zenoh_pair, example_site):
    def make(robot: DriftingRobot | None = None, **kw: Any) -> Rig:
        return Rig(zenoh_pair, example_site, robot or DriftingRobot(), **kw)
    return make


def _three_stops_under_fakes(r: Rig, offset_m: float, ahead_ns: int) -> tuple[int, int]:
    """Three stops (4 s driving, 6 s stopped each) while a peer posts a fused pose
    ``offset_m`` ahead of the robot's localization, stamped ``ahead_ns`` after now, at 50 Hz,
    next to the backend's genuine estimates at 10 Hz; the robot must end each stop within 5 cm.
    Returns (fakes, genuine) sent."""
    fakes = genuine = 0
    for _stop in range(3):
        for k in range(500):
            loc = r.localization()
            r.put(r.pose_key, r.estimate(loc[0] + offset_m, loc[1], loc[2],
                                         stamp_ns=r.robot.t_ns + ahead_ns, std_m=0.001))
            fakes += 1
            if k % 5 == 0:
                r.put(r.pose_key, r.genuine(genuine))
                genuine += 1
            r.step(vx=0.5 if k < 200 else 0.0)
        assert r.error_m() < 0.05, r.counters
    return fakes, genuine


def test_future_stamped_fake_is_refused_and_genuine_estimates_still_used(rig) -> None:
    """The probe's attack: a fused pose 0.95 m off, stamped 0.3 s ahead, at 50 Hz, next to
    the backend's genuine estimates at 10 Hz. Every fake is refused; the genuine ones are not
    'late' and correct the robot at each stop."""
    r = rig(DriftingRobot(scale=1.04, yaw_bias_rad_per_m=0.01))
    fakes, genuine = _three_stops_under_fakes(r, 0.95, ahead_ns=300_000_000)
    c = r.counters
    assert c["bridge.future_stamp_estimate"] == fakes
    assert c["bridge.received_estimate_fused"] == genuine
    assert "bridge.late_estimate" not in c
    assert c["bridge.corrections_accepted"] == 3
    assert all(abs(x.offset_m) < 0.3 for x in r.corrections)


def test_zero_covariance_estimate_is_floored(rig) -> None:
    """A sender claiming zero uncertainty buys nothing: the pose goes to the robot with the
    bridge's floor, and a jump beyond the limit is refused whatever the covariance."""
    r = rig(DriftingRobot(T_map_odom=(1.5, 0.0, 0.0)))  # localization 1.5 m off
    zero = np.zeros((3, 3))
    for k in range(150):
        if k % 5 == 0:
            x, y, th = r.robot.true
            r.put(r.pose_key, PoseEstimate("hsr", r.robot.t_ns, k, float(x), float(y),
                                           float(th), zero, "fused"))
        r.step()
    assert r.corrections == []
    assert r.counters["bridge.skip_jump_too_large"] >= 1
    # within the limit it corrects, with the floored covariance
    r.robot.T_map_odom = np.array([0.3, 0.0, 0.0])
    for k in range(150):
        if k % 5 == 0:
            x, y, th = r.robot.true
            r.put(r.pose_key, PoseEstimate("hsr", r.robot.t_ns, 1000 + k, float(x), float(y),
                                           float(th), zero, "fused"))
        r.step(vx=0.3 if k < 25 else 0.0)  # a new stop
    assert len(r.corrections) == 1 and r.counters["bridge.corrections_accepted"] == 1
    cov = r.corrections[0].covariance
    trust = r.node.bridge.config.trust
    assert np.linalg.eigvalsh(cov[:2, :2]).min() == pytest.approx(trust.position_std_floor_m**2)
    assert cov[2, 2] == pytest.approx(math.radians(trust.yaw_std_floor_deg) ** 2)


def test_repeated_sub_limit_jumps_do_not_add_up(rig) -> None:
    """A peer pushing the robot 0.6 m further (and 20 deg) at each of 6 stops: the first
    correction goes out, the following ones would take the robot beyond one jump from where
    its own localization had it, and are refused and counted. The damage stays bounded."""
    r = rig()
    start = r.localization()
    for _stop in range(6):
        for k in range(250):  # 1 s driving, 4 s stopped
            loc = r.localization()
            if k % 2 == 0:  # 25 Hz, always relative to where the robot now believes it is
                r.put(r.pose_key, r.estimate(loc[0] + 0.6, loc[1], loc[2] + math.radians(20),
                                             std_m=0.001))
            r.step(vx=0.2 if k < 50 else 0.0)
    c = r.counters
    assert c["bridge.corrections_accepted"] == 1, c
    refused = c.get("bridge.skip_jump_too_large", 0) + c.get(
        "bridge.skip_heading_jump_too_large", 0)
    assert refused >= 5
    # moved by the one correction (0.6 m), never by the sum (3.6 m)
    travelled_m = 6 * 0.2
    drift = math.hypot(*(r.localization()[:2] - start[:2])) - travelled_m
    assert drift < 0.7, drift
    assert r.error_m() < 0.7


def test_kidnapped_initialization_outside_the_room_is_refused(rig) -> None:
    """A kidnapped robot in the room; a peer offers a consistent initial pose 30 m away,
    outside the site's floor area (no floor_area in the example site: the cameras' positions
    +- floor_margin_m). Refused and counted; the backend's genuine estimates then initialize."""
    r = rig(DriftingRobot((10.0, 6.0, 0.5), T_map_odom=(0.0, 0.0, 0.0)), localized=False)
    area = r.node.bridge.config.trust.floor_area
    assert area and not area[0] <= 40.0 <= area[2]
    for k in range(150):
        if k % 2 == 0:
            r.put(r.pose_key, r.estimate(40.0, 6.0, 0.5, seq=k))
        r.step()
    assert r.corrections == [] and r.adapter.read_localization() is None
    assert r.counters["bridge.skip_outside_floor_area"] >= 10
    for k in range(100):
        if k % 5 == 0:
            r.put(r.pose_key, r.genuine(k))
        r.step()
    assert [c.kind for c in r.corrections] == ["initialization"]
    assert r.error_m() < 0.05


def test_initialization_needs_consecutive_estimates_that_agree(rig) -> None:
    """Estimates that jump between two places 0.5 m apart never initialize a kidnapped robot
    (an attacker interleaved with the backend cannot win); three in a row that agree do."""
    r = rig(DriftingRobot((10.0, 6.0, 0.5), T_map_odom=(0.0, 0.0, 0.0)), localized=False)
    for k in range(150):
        if k % 5 == 0:
            r.put(r.pose_key, r.estimate(10.0 + 0.5 * ((k // 5) % 2), 6.0, 0.5, seq=k))
        r.step()
    assert r.corrections == []
    assert r.counters["bridge.skip_awaiting_agreement"] >= 10
    n_estimates = 0
    for k in range(50):
        if k % 5 == 0:
            r.put(r.pose_key, r.genuine(1000 + k))
            n_estimates += 1
        r.step()
        if r.corrections:
            break
    assert [c.kind for c in r.corrections] == ["initialization"]
    assert n_estimates == r.node.bridge.config.trust.init_agreement_count


def test_source_must_match_the_key(rig) -> None:
    """A camera-only estimate on the fused key (or a fused one on the camera key) is counted
    and never used."""
    r = rig(DriftingRobot(T_map_odom=(0.3, 0.0, 0.0)))
    for k in range(150):
        if k % 5 == 0:
            r.put(r.pose_key, r.genuine(k, source="cameras"))
        r.step()
    assert r.corrections == []
    c = r.counters
    assert c["bridge.source_key_mismatch"] == 30 and "bridge.received_estimate_cameras" not in c


def test_fused_estimate_on_the_camera_key_is_counted(zenoh_pair, example_site) -> None:
    r = Rig(zenoh_pair, example_site, DriftingRobot(T_map_odom=(0.3, 0.0, 0.0)),
            correction_source="cameras")
    for k in range(150):
        if k % 5 == 0:
            r.put(r.camera_pose_key, r.genuine(k, source="fused"))
        r.step()
    assert r.corrections == [] and r.counters["bridge.source_key_mismatch"] == 30
    for k in range(50):  # the right source on that key is used
        if k % 5 == 0:
            r.put(r.camera_pose_key, r.genuine(k, source="cameras"))
        r.step()
    assert len(r.corrections) == 1 and r.counters["bridge.corrections_accepted"] == 1


def test_estimates_are_not_heartbeats(rig) -> None:
    """Only the backend's status (and liveliness) says the backend is alive: a stream of
    estimates does not, and a 'stopping' status marks it gone at once."""
    r = rig()
    for k in range(250):  # 5 s of estimates
        if k % 5 == 0:
            r.put(r.pose_key, r.genuine(k))
        r.step(heartbeat=False)
    st = r.node.bridge.status()
    assert not st.backend_alive and st.state == "degraded"
    assert "backend lost: never heard" in st.detail
    assert r.counters["bridge.received_estimate_fused"] == 50
    assert r.node.peers_alive() == ()
    r.put(r.status_key, r.status_message())  # the backend's status arrives
    r.step(heartbeat=False)
    assert r.node.bridge.backend_alive() and r.node.peers_alive() == ("backend",)
    for k in range(200):  # 4 s of estimates without a status: lost again
        if k % 5 == 0:
            r.put(r.pose_key, r.genuine(1000 + k))
        r.step(heartbeat=False)
    st = r.node.bridge.status()
    assert not st.backend_alive and "no status or liveliness" in st.detail
    r.put(r.status_key, r.status_message())
    r.step(heartbeat=False)
    assert r.node.bridge.backend_alive()
    r.put(r.status_key, r.status_message("stopping"))
    r.step(heartbeat=False)
    assert not r.node.bridge.backend_alive()
    assert "status stopping" in r.node.bridge.status().detail


def test_backend_liveliness_token_is_a_heartbeat(zenoh_pair, example_site) -> None:
    """The backend's liveliness token (declared by its runner) counts; its disappearance
    marks the backend lost at once."""
    bridge_side, backend_side, _ = zenoh_pair
    node = RobotBridgeNode(example_site, "hsr", lambda session: SimRobotAdapter(DriftingRobot()))
    sub = next(s for s in node.subscriptions() if s.liveliness)
    events: list[tuple[str, bool]] = []
    handle = bridge_side.liveliness().declare_subscriber(
        sub.key_expr, lambda s: events.append((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)),
        history=True)
    try:
        token = backend_side.liveliness().declare_token(
            keys.alive_key(node.site, "backend", "main"))
        assert wait_until(lambda: bool(events), 5.0)
        for key, present in events:
            node.alive(key, present)
        assert node.bridge.backend_alive(time.time_ns())
        events.clear()
        token.undeclare()
        assert wait_until(lambda: bool(events), 5.0)
        for key, present in events:
            node.alive(key, present)
        assert not node.bridge.backend_alive(time.time_ns())
    finally:
        handle.undeclare()


def test_refusals_appear_in_the_status_message(rig) -> None:
    """Each refusal is in the bridge's ServiceStatus counters, with its reason."""
    r = rig()
    loc = r.localization()
    r.put(r.pose_key, r.estimate(loc[0], loc[1], loc[2], stamp_ns=r.robot.t_ns + S))
    r.put(r.pose_key, r.genuine(1, source="cameras"))
    r.step()
    status = r.node.bridge.service_status(r.robot.t_ns, seq=0)
    assert status.counters["future_stamp_estimate"] == 1
    assert status.counters["source_key_mismatch"] == 1


def test_fakes_holding_the_newest_stamp_do_not_block_genuine_corrections(rig) -> None:
    """Probe ``forged_pose_stamped_now`` of docs/reliability.md: a peer posts a fused pose 1.5 m
    off, stamped *now* (inside the clock tolerance), at 50 Hz, so it always holds the newest stamp
    and the genuine estimates arrive 'late'. The fakes are refused as a jump too large; the
    bridge then falls back to the genuine estimates of the stop, and the robot is corrected at
    every stop."""
    r = rig(DriftingRobot(scale=1.04, yaw_bias_rad_per_m=0.01))
    _three_stops_under_fakes(r, 1.5, ahead_ns=0)
    c = r.counters
    assert c["bridge.late_estimate"] > 0 and c["bridge.skip_jump_too_large"] >= 3
    assert c["bridge.fallback_estimate"] == 3 == c["bridge.corrections_accepted"]
    assert all(abs(x.offset_m) < 0.3 for x in r.corrections)
