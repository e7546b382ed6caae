"""The bridge core fed like the service loop feeds it: a drifting planar robot (behind the sim
adapter interface) and camera / fused pose estimates of its true pose."""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np
import pytest

from core.geometry import angle_diff, se2_compose, se2_inverse, wrap_angle
from core.site import Thresholds
from protocol.messages import Odometry, PoseCorrection, PoseEstimate, ServiceStatus
from robot_bridge.adapters.base import LocalizationPose, OdometrySample
from robot_bridge.adapters.sim import SimRobotAdapter, SimulatedRobotPort
from robot_bridge.bridge import BridgeConfig, Outbox, RobotBridge

S = 1_000_000_000
T0 = 1_700_000_000 * S
DT_NS = S // 50  # 50 Hz odometry
TH = Thresholds()


class DriftingRobot:
    """A planar robot with the interface of ``simulation.robot.SimulatedRobot`` whose odometry
    over-reads distance and turns by a yaw bias, and whose localization is ``T_map_odom``
    composed with that odometry (a localizer drifting between corrections). Accepts
    corrections only while not moving. ``step`` drives it; ``step_to`` hands over the odometry
    of the steps made since the last call."""

    def __init__(self, pose=(0.0, 0.0, 0.0), *, scale=1.04, yaw_bias_rad_per_m=0.03,
                 T_map_odom=None) -> None:
        self.true = np.array(pose, dtype=float)
        self.odom = np.zeros(3)
        self.scale = scale
        self.yaw_bias = yaw_bias_rad_per_m
        self.t_ns = T0
        self.v = (0.0, 0.0)
        self.T_map_odom = np.array(pose if T_map_odom is None else T_map_odom, dtype=float)
        self._pending: list[Odometry] = []
        self.refused = 0

    def step(self, vx: float, wz: float) -> None:
        dt = DT_NS / S
        self.t_ns += DT_NS
        self.v = (vx, wz)
        x, y, th = self.true
        self.true = np.array([x + vx * dt * math.cos(th), y + vx * dt * math.sin(th),
                              wrap_angle(th + wz * dt)])
        ox, oy, oth = self.odom
        d = vx * dt * self.scale
        oth2 = oth + wz * dt + self.yaw_bias * abs(vx) * dt
        self.odom = np.array([ox + d * math.cos(oth), oy + d * math.sin(oth), wrap_angle(oth2)])
        self._pending.append(Odometry("hsr", self.t_ns, len(self._pending), *self.odom,
                                      vx=vx * self.scale, wz=wz))

    # --- SimulatedRobotPort -----------------------------------------------------------------
    @property
    def t_s(self) -> float:
        return (self.t_ns - T0) / S

    def stamp_ns(self, t_s: float) -> int:
        return T0 + round(t_s * S)

    def step_to(self, t_s: float) -> list[Odometry]:
        out, self._pending = self._pending, []
        return out

    def localization_pose(self) -> np.ndarray:
        return se2_compose(self.T_map_odom, self.odom)

    def apply_correction(self, pose, stamp_ns: int) -> bool:
        if self.v != (0.0, 0.0):
            self.refused += 1
            return False
        # choose T_map_odom so that T_map_odom ∘ odom == the corrected pose
        self.T_map_odom = se2_compose(np.asarray(pose, dtype=float), se2_inverse(self.odom))
        return True

    def localization_error(self) -> tuple[float, float]:
        x, y, th = self.localization_pose()
        return (math.hypot(x - self.true[0], y - self.true[1]),
                abs(angle_diff(th, self.true[2])))


def camera_estimate(robot: DriftingRobot, rng, sigma_m=0.01, sigma_deg=0.5, source="cameras",
                    seq=0, robot_id="hsr") -> PoseEstimate:
    x, y, th = robot.true
    cov = np.diag([sigma_m**2, sigma_m**2, math.radians(sigma_deg) ** 2])
    return PoseEstimate(
        robot_id, robot.t_ns, seq,
        float(x + rng.normal(0, sigma_m)), float(y + rng.normal(0, sigma_m)),
        float(wrap_angle(th + math.radians(rng.normal(0, sigma_deg)))),
        cov, source, ("cam_a", "cam_b"),
    )


class Harness:
    """Runs robot + bridge + (optional) backend estimates at 50 Hz odometry, 10 Hz estimates,
    and the backend's heartbeat (its status message) at 1 Hz."""

    def __init__(self, robot: DriftingRobot, *, seed=0, backend=True, localized=True) -> None:
        self.robot = robot
        self.adapter = SimRobotAdapter(robot, localized=localized)
        assert isinstance(robot, SimulatedRobotPort)
        self.bridge = RobotBridge(BridgeConfig(robot_id="hsr"))
        self.rng = np.random.default_rng(seed)
        self.backend = backend
        self.odometry: list[Odometry] = []
        self.corrections = []
        self.motion_at_correction = []
        self._seq = 0
        self._n = 0

    def run(self, seconds: float, vx: float = 0.0, wz: float = 0.0) -> None:
        for _ in range(round(seconds * 50)):
            self.robot.step(vx, wz)
            self._n += 1
            if self.backend and self._n % 50 == 1:
                self.bridge.on_backend_heartbeat(self.robot.t_ns)
            if self.backend and self._n % 5 == 0:
                out = self.bridge.on_pose_estimate(
                    camera_estimate(self.robot, self.rng, seq=self._seq), self.robot.t_ns)
                self._seq += 1
                self._collect(out, pushed=False)
            self.adapter.advance_to(self.robot.t_s)
            out = self.bridge.pump(self.adapter, self.robot.t_ns)
            self._collect(out, pushed=True)

    def _collect(self, out: Outbox, pushed: bool) -> None:
        if not pushed:  # decided on an estimate: push like the service loop does
            out = self.bridge.apply(self.adapter, out)
        self.odometry.extend(out.odometry)
        for c in out.corrections:
            self.corrections.append(c)
            self.motion_at_correction.append(self.robot.v)


def test_no_correction_while_moving() -> None:
    h = Harness(DriftingRobot(scale=1.1, yaw_bias_rad_per_m=0.1))
    h.run(20.0, vx=0.4, wz=0.05)  # drifts far beyond every threshold, never stops
    assert h.robot.localization_error()[0] > 0.3
    assert h.corrections == []
    assert len(h.odometry) == 1000
    assert h.bridge.counters.get("corrections_sent", 0) == 0


def test_one_correction_per_static_stop_when_needed() -> None:
    h = Harness(DriftingRobot())
    stops = 3
    for _ in range(stops):
        h.run(6.0, vx=0.5)  # 3 m: ~12 cm of drift plus heading error
        err_before = h.robot.localization_error()
        assert err_before[0] > TH.correction_min_offset_m
        n_before = len(h.corrections)
        h.run(4.0)  # stop: dwell 1 s, then estimates keep coming for 3 s
        assert len(h.corrections) == n_before + 1, "exactly one correction per stop"
        err_after = h.robot.localization_error()
        assert err_after[0] < 0.03 and err_after[1] < math.radians(1.5)
    assert all(v == (0.0, 0.0) for v in h.motion_at_correction)
    assert all(c.kind == "correction" for c in h.corrections)
    assert h.robot.refused == 0
    c = h.bridge.counters
    assert c["corrections_sent"] == stops and c["corrections_accepted"] == stops


def test_each_correction_is_applied_and_logged_once(caplog: pytest.LogCaptureFixture) -> None:
    """Whether decided in a pump or on an incoming estimate, a correction reaches the robot
    through RobotBridge.apply and gives exactly one info line."""
    h = Harness(DriftingRobot())
    with caplog.at_level(logging.DEBUG):
        for _ in range(2):
            h.run(6.0, vx=0.5)
            h.run(4.0)
    assert len(h.corrections) == 2
    lines = [r for r in caplog.records if r.levelno >= logging.INFO and "applied to" in
             r.getMessage()]
    assert [r.getMessage().split()[:2] for r in lines] == [
        ["correction", str(c.seq)] for c in h.corrections
    ]
    assert all(r.levelno == logging.INFO for r in lines)
    assert h.bridge.counters["corrections_accepted"] == 2
    assert not [r for r in caplog.records if r.levelno >= logging.INFO and r not in lines]


def test_apply_counts_a_refusal_and_an_adapter_error(caplog: pytest.LogCaptureFixture) -> None:
    robot = DriftingRobot()
    adapter = SimRobotAdapter(robot)
    bridge = RobotBridge(BridgeConfig(robot_id="hsr"))
    cov = np.eye(3) * 1e-4
    correction = PoseCorrection("hsr", T0, 0, 1.0, 0.0, 0.0, cov, "correction", 0.2, 0.0)
    robot.v = (0.5, 0.0)  # moving: the robot refuses
    with caplog.at_level(logging.INFO):
        out = bridge.apply(adapter, Outbox(corrections=(correction,)))
    assert out.corrections == (correction,)
    assert [r.levelno for r in caplog.records] == [logging.WARNING]
    assert "refused by hsr" in caplog.records[0].getMessage()

    class Broken(SimRobotAdapter):
        def apply_correction(self, correction):
            raise RuntimeError("driver crashed")

    bridge.apply(Broken(robot), Outbox(corrections=(correction,)))
    c = bridge.counters
    assert c["corrections_refused"] == 2 and c["adapter_error"] == 1


def test_service_node_applies_each_correction_once(
    example_site, caplog: pytest.LogCaptureFixture
) -> None:
    """The service node: a correction decided in its pump (estimates already there when the
    dwell ends) and one decided on an incoming estimate (the backend speaks up late) each reach
    the robot once, are published once and logged once."""
    from protocol import keys
    from robot_bridge.service import RobotBridgeNode

    robot = DriftingRobot()
    adapter = SimRobotAdapter(robot)
    applied: list[int] = []
    push = adapter.apply_correction

    def counting_push(correction: PoseCorrection) -> bool:
        applied.append(correction.seq)
        return push(correction)

    adapter.apply_correction = counting_push  # type: ignore[method-assign]
    node = RobotBridgeNode(
        example_site, "hsr", lambda session: adapter,
        advance=lambda now_ns: adapter.advance_to(robot.t_s),
    )
    node.attach(None)
    pose_key = keys.robot_key(node.site, "hsr", "pose")
    rng = np.random.default_rng(2)
    seq = 0
    from_handle: list[int] = []
    from_tick: list[int] = []

    def run(seconds: float, vx: float, estimates_after_s: float = 0.0) -> None:
        nonlocal seq
        for k in range(round(seconds * 50)):
            robot.step(vx, 0.0)
            if k % 5 == 0 and k / 50 >= estimates_after_s:
                est = camera_estimate(robot, rng, seq=seq, source="fused")
                seq += 1
                from_handle.extend(
                    o.message.seq for o in node.handle(pose_key, est, robot.t_ns)
                    if o.key.endswith("/correction")
                )
            from_tick.extend(
                o.message.seq for o in node.tick(robot.t_ns) if o.key.endswith("/correction")
            )

    with caplog.at_level(logging.INFO):
        caplog.clear()  # only the run's lines (building the node may log its configuration)
        run(6.0, vx=0.5)
        run(4.0, vx=0.0)  # estimates all along: decided when the dwell ends, in the pump
        run(6.0, vx=0.5)
        run(4.0, vx=0.0, estimates_after_s=2.0)  # decided on the first estimate
    assert from_tick == [0] and from_handle == [1]
    assert applied == [0, 1]
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
    assert [m.split()[:3] for m in lines] == [["correction", "0", "applied"],
                                              ["correction", "1", "applied"]]
    assert node.counters()["corrections_correction"] == 2
    assert node.counters()["bridge.corrections_accepted"] == 2
    assert robot.localization_error()[0] < 0.03


def test_no_correction_when_the_offset_is_small() -> None:
    h = Harness(DriftingRobot(scale=1.0, yaw_bias_rad_per_m=0.0))
    for _ in range(3):
        h.run(3.0, vx=0.5)
        h.run(3.0)
    assert h.corrections == []
    assert h.bridge.counters.get("skip_offset_below_threshold", 0) > 0


def test_kidnapped_start_gets_the_initial_pose_from_cameras() -> None:
    true_start = (4.2, -1.3, 2.5)
    h = Harness(DriftingRobot(true_start, T_map_odom=(0.0, 0.0, 0.0)), seed=3, localized=False)
    assert h.adapter.read_localization() is None
    h.run(3.0)
    assert [c.kind for c in h.corrections] == ["initialization"]
    c = h.corrections[0]
    assert c.frame_id == "map"
    dist, dyaw = h.robot.localization_error()
    assert dist < 0.05 and dyaw < math.radians(2.0)
    # afterwards the robot is localized: driving and stopping gives ordinary corrections only
    h.run(6.0, vx=0.5)
    h.run(3.0)
    assert [c.kind for c in h.corrections][1:] in ([], ["correction"])


def test_kidnapped_robot_waits_for_a_stop_before_initialization() -> None:
    h = Harness(DriftingRobot((1.0, 1.0, 0.0), T_map_odom=(0.0, 0.0, 0.0)), localized=False)
    h.run(5.0, vx=0.3)
    assert h.corrections == []
    h.run(2.0)
    assert [c.kind for c in h.corrections] == ["initialization"]


def test_large_jump_is_rejected_for_a_localized_robot() -> None:
    # localization 2 m off (> max jump 1 m)
    h = Harness(DriftingRobot((0.0, 0.0, 0.0), T_map_odom=(2.0, 0.0, 0.0)))
    h.run(4.0)
    assert h.corrections == []
    assert h.bridge.counters["skip_jump_too_large"] >= 1


def test_link_loss_leaves_the_robot_running() -> None:
    h = Harness(DriftingRobot(scale=1.02, yaw_bias_rad_per_m=0.002))
    h.run(2.0, vx=0.5)
    st = h.bridge.status()
    assert st.state == "ok" and st.backend_alive
    h.backend = False  # backend / link gone
    n_odom = len(h.odometry)
    t_start = time.perf_counter()
    h.run(20.0, vx=0.5)
    h.run(5.0)
    elapsed = time.perf_counter() - t_start
    assert len(h.odometry) == n_odom + 1250, "odometry keeps flowing"
    assert h.robot.true[0] > 10.0, "the robot kept driving on its own"
    assert elapsed < 2.0, "nothing blocks (1250 steps)"
    st = h.bridge.status()
    assert st.state == "degraded" and not st.backend_alive
    assert "backend lost" in st.detail and "own localization" in st.detail
    assert h.corrections == []
    status_msg = h.bridge.service_status(h.robot.t_ns, seq=0, uptime_s=27.0)
    assert isinstance(status_msg, ServiceStatus) and status_msg.state == "degraded"
    # the backend comes back: status recovers and the overdue correction goes out
    h.backend = True
    h.run(3.0)
    assert h.bridge.status().state == "ok"
    assert len(h.corrections) == 1, h.bridge.counters
    # liveliness DELETE marks the backend lost at once
    h.bridge.on_backend_gone(h.robot.t_ns)
    assert h.bridge.status().state == "degraded"
    h.bridge.on_backend_heartbeat(h.robot.t_ns)
    assert h.bridge.status().state == "ok"


def test_fused_estimate_is_preferred_over_camera_only() -> None:
    robot = DriftingRobot()
    robot.T_map_odom = np.array([0.3, 0.0, 0.0])
    bridge = RobotBridge(BridgeConfig(robot_id="hsr"))
    adapter = SimRobotAdapter(robot)
    rng = np.random.default_rng(1)
    out = Outbox()
    for i in range(100):
        robot.step(0.0, 0.0)
        if i == 10:  # both arrive while the stop's dwell time is still running
            cam = camera_estimate(robot, rng)
            fused = dataclasses.replace(cam, x=cam.x + 0.01, source="fused")
            out = out + bridge.on_pose_estimate(fused) + bridge.on_pose_estimate(cam)
        adapter.advance_to(robot.t_s)
        out = out + bridge.pump(adapter, robot.t_ns)
    assert len(out.corrections) == 1
    assert out.corrections[0].x == pytest.approx(fused.x)
    assert out.corrections[0].stamp_ns == fused.stamp_ns


def test_garbage_is_counted_never_raised() -> None:
    bridge = RobotBridge(BridgeConfig(robot_id="hsr"))
    good = OdometrySample(T0, 0.0, 0.0, 0.0)
    assert len(bridge.on_robot_odometry(good, T0).odometry) == 1
    cov_bad = np.array([[1.0, 2.0, 0], [0, 1.0, 0], [0, 0, 1.0]])  # not symmetric
    bad = [
        None, "odom", {"x": 1.0}, 42,
        OdometrySample(T0 + 1, math.nan, 0.0, 0.0),
        OdometrySample(T0 + 2, 0.0, math.inf, 0.0),
        OdometrySample(T0 + 3, 0.0, 0.0, 0.0, vx=math.nan),
        OdometrySample(T0 + 4, 0.0, 0.0, math.nan),
        OdometrySample(T0 + 5, "1.0", 0.0, 0.0),
        OdometrySample(T0 + 6, 0.0, 0.0, 0.0, covariance=cov_bad),
        OdometrySample(T0 + 7, 0.0, 0.0, 0.0, covariance=np.eye(2)),
        OdometrySample(T0 + 8, 0.0, 0.0, 0.0, frame_id="bad/frame"),
        OdometrySample(-5, 0.0, 0.0, 0.0),
        OdometrySample(1.5, 0.0, 0.0, 0.0),
        OdometrySample(T0 + 3600 * S, 0.0, 0.0, 0.0),  # an hour in the future
        OdometrySample(T0 - S, 0.0, 0.0, 0.0),  # older than the last one
    ]
    for item in bad:
        out = bridge.on_robot_odometry(item, T0 + 10 * S // 1000)
        assert not out
    for item in (None, "pose", 3.0, OdometrySample(T0, 0, 0, 0)):
        assert not bridge.on_pose_estimate(item)
    cov = np.eye(3) * 1e-4
    other = PoseEstimate("other_robot", T0, 0, 0.0, 0.0, 0.0, cov, "cameras")
    odd_frame = PoseEstimate("hsr", T0, 0, 0.0, 0.0, 0.0, cov, "cameras", frame_id="odom")
    future = PoseEstimate("hsr", T0 + 3600 * S, 0, 0.0, 0.0, 0.0, cov, "cameras")
    for est in (other, odd_frame, future):
        assert not bridge.on_pose_estimate(est, T0)
    for pose in ("map", LocalizationPose(T0, math.nan, 0.0, 0.0),
                 LocalizationPose(-1, 0.0, 0.0, 0.0),
                 LocalizationPose(T0, 0, 0, 0, frame_id="odom")):
        assert not bridge.on_robot_localization(pose)
    assert not bridge.tick("now")  # type: ignore[arg-type]
    c = bridge.counters
    assert c["invalid_odometry"] == 14
    assert c["future_stamp_odometry"] == 1 and c["out_of_order_odometry"] == 1
    assert c["invalid_estimate"] == 4
    assert c["other_robot_estimate"] == 1 and c["wrong_frame_estimate"] == 1
    assert c["future_stamp_estimate"] == 1
    assert c["invalid_localization"] == 3 and c["wrong_frame_localization"] == 1
    assert c["invalid_tick"] == 1
    assert "internal_error" not in c
    # and the bridge still works
    out = bridge.on_robot_odometry(OdometrySample(T0 + S, 0.1, 0.0, 0.0))
    assert len(out.odometry) == 1, bridge.counters


def test_adapter_exceptions_are_counted() -> None:
    class Broken(DriftingRobot):
        def localization_pose(self):
            raise RuntimeError("robot driver crashed")

        def apply_correction(self, pose, stamp_ns):
            raise RuntimeError("robot driver crashed")

    robot = Broken(T_map_odom=(0.5, 0.0, 0.0))
    adapter = SimRobotAdapter(robot)
    bridge = RobotBridge(BridgeConfig(robot_id="hsr"))
    rng = np.random.default_rng(0)
    for i in range(100):
        robot.step(0.0, 0.0)
        adapter.advance_to(robot.t_s)
        if i % 10 == 0:
            bridge.on_pose_estimate(camera_estimate(robot, rng, seq=i), robot.t_ns)
        out = bridge.pump(adapter, robot.t_ns)
        assert len(out.odometry) == 1
    c = bridge.counters
    assert c["adapter_error"] == 101  # 100 localization reads + 1 correction push
    assert c["initializations_sent"] == 1 and c["corrections_refused"] == 1
    with pytest.raises(TypeError):
        SimRobotAdapter(object())  # type: ignore[arg-type]


def _run_simulated(feedback: bool, localized: bool = True):
    """simulation.SimulatedRobot on Traj. 3 (stops at waypoints), camera estimates of the true
    pose (1 cm / 0.5 deg noise) at 10 Hz while it stands still; bridge + sim adapter at 50 Hz."""
    scenario_mod = pytest.importorskip("simulation.scenario")
    runner_mod = pytest.importorskip("simulation.runner")
    run = runner_mod.SimulationRun(scenario_mod.load_scenario(), "traj3", seed=4)
    robot = run.robot
    adapter = SimRobotAdapter(robot, localized=localized)
    bridge = RobotBridge(BridgeConfig(robot_id=robot.robot_id))
    rng = np.random.default_rng(5)
    errors, corrections, stop_end_errors = [], [], []
    n_steps = int(run.duration_s * 50)
    stop_ends = [min(round(st.t1_s * 50) - 1, n_steps - 1) for st in run.stops]
    for k in range(1, n_steps):
        t_s = k / 50
        adapter.advance_to(t_s)
        now = robot.stamp_ns(t_s)
        if feedback and k % 5 == 0 and robot.is_static(t_s):
            gt = robot.ground_truth()
            est = PoseEstimate(
                robot.robot_id, now, k, float(gt[0] + rng.normal(0, 0.01)),
                float(gt[1] + rng.normal(0, 0.01)),
                float(wrap_angle(gt[2] + math.radians(rng.normal(0, 0.5)))),
                np.diag([1e-4, 1e-4, math.radians(0.5) ** 2]), "cameras", ("cam_a", "cam_b"))
            out = bridge.apply(adapter, bridge.on_pose_estimate(est, now))
            corrections.extend(out.corrections)
        corrections.extend(bridge.pump(adapter, now).corrections)
        if adapter.localized:
            loc, gt = robot.localization_pose(), robot.ground_truth()
            errors.append(math.hypot(loc[0] - gt[0], loc[1] - gt[1]))
            if k in stop_ends:
                stop_end_errors.append(errors[-1])
    return run, robot, bridge, corrections, np.array(errors), np.array(stop_end_errors)


def test_simulated_robot_with_and_without_feedback() -> None:
    run, robot, bridge, corrections, err_fb, stop_fb = _run_simulated(feedback=True)
    _, _, _, none, err_open, stop_open = _run_simulated(feedback=False)
    assert none == []
    assert 1 <= len(corrections) <= len(run.stops)
    assert robot.corrections_refused == 0, "corrections are only sent while static"
    assert bridge.counters.get("corrections_accepted", 0) == len(corrections)
    # leaving each waypoint, the robot's localization is within the correction threshold
    # (plus camera noise); without feedback it is whatever it drifted to
    assert len(stop_fb) == len(run.stops)
    assert np.all(stop_fb < TH.correction_min_offset_m + 0.03), stop_fb
    assert stop_fb.mean() < 0.5 * stop_open.mean(), (stop_fb, stop_open)
    assert np.sqrt(np.mean(err_fb**2)) < np.sqrt(np.mean(err_open**2))


def test_simulated_kidnapped_robot_is_initialized_at_the_first_stop() -> None:
    run, robot, bridge, corrections, errors, _ = _run_simulated(feedback=True, localized=False)
    assert corrections[0].kind == "initialization"
    assert bridge.counters["initializations_sent"] == 1
    assert errors[0] < 0.05  # first localized step: the initial pose from the cameras
    assert corrections[0].stamp_ns < robot.stamp_ns(run.stops[0].t1_s)
    assert all(c.kind == "correction" for c in corrections[1:])


def test_bridge_section_holds_what_the_bridge_trusts(example_site_path) -> None:
    """The trust keys of the site file's ``bridge`` section; ``floor_area`` explicit or the
    cameras' positions +- ``floor_margin_m``; bad values name the file and the key."""
    import yaml

    from core.site import parse_site
    from protocol.errors import SiteConfigError

    doc = yaml.safe_load(example_site_path.read_text())

    def config(**bridge):
        site = parse_site({**doc, "bridge": bridge}, "site.yaml", example_site_path.parent)
        return BridgeConfig.from_site(site, "hsr")

    default = config()
    # the example's cameras stand at x 7..13, y 3..9
    assert default.trust.floor_area == pytest.approx((-3.0, -7.0, 23.0, 19.0))
    c = config(init_agreement_count=5, floor_area=[-1, -2.5, 20, 12], backend_timeout_s=4.0)
    assert c.trust.init_agreement_count == 5
    assert c.trust.floor_area == (-1.0, -2.5, 20.0, 12.0) and c.backend_timeout_s == 4.0
    assert config(floor_margin_m=1.0).trust.floor_area == pytest.approx((6.0, 2.0, 14.0, 10.0))
    for bridge, key in (({"floor_area": [0, 0, 1]}, "bridge.floor_area"),
                        ({"floor_area": [5, 0, 1, 1]}, "bridge.floor_area"),
                        ({"init_agreement_count": 0}, "bridge.init_agreement_count"),
                        # the bridge's own tolerance gave way to the site's clock policy
                        ({"clock_tolerance_ms": 20.0}, "bridge.clock_tolerance_ms"),
                        ({"clock_tolerance": 1}, "bridge.clock_tolerance")):
        with pytest.raises(SiteConfigError, match=key.replace(".", r"\.")) as err:
            config(**bridge)
        assert "site.yaml" in str(err.value)
    # the bridge refuses what is stamped further ahead than the site's clock.max_future_ms
    site = parse_site({**doc, "clock": {"max_future_ms": 20.0}}, "site.yaml",
                      example_site_path.parent)
    bridge = RobotBridge(BridgeConfig.from_site(site, "hsr"))
    assert not bridge.on_robot_odometry(OdometrySample(T0 + 21_000_000, 0.0, 0.0, 0.0), T0)
    assert bridge.on_robot_odometry(OdometrySample(T0 + 19_000_000, 0.0, 0.0, 0.0), T0)
    assert bridge.counters["future_stamp_odometry"] == 1
