"""Nothing lost without a count (issue #17 item 5): odometry replayed to a backend that comes
back, what overflows the replay window counted; corrections confirmed (or not) by the robot's
own localization."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import PoseCorrection
from robot_bridge.adapters.base import LocalizationPose, OdometrySample
from robot_bridge.bridge import BridgeConfig, RobotBridge

S = 1_000_000_000
T0 = 1_700_000_000 * S
DT = S // 50


def drive(bridge: RobotBridge, t_from: int, t_to: int) -> list:
    out = []
    t = t_from
    while t < t_to:
        out.extend(bridge.on_robot_odometry(
            OdometrySample(t, (t - T0) * 1e-9 * 0.3, 0.0, 0.0, vx=0.3), t).odometry)
        t += DT
    return out


def test_odometry_of_a_backend_outage_is_replayed_when_it_returns() -> None:
    bridge = RobotBridge(BridgeConfig("hsr"))
    bridge.on_backend_heartbeat(T0)
    drive(bridge, T0, T0 + 2 * S)
    bridge.on_backend_heartbeat(T0 + 2 * S)
    bridge.on_backend_gone(T0 + 2 * S + DT)  # the backend process died
    during = drive(bridge, T0 + 2 * S, T0 + 7 * S)  # published, but nobody listened
    assert bridge.tick(T0 + 7 * S).odometry == ()
    bridge.on_backend_heartbeat(T0 + 7 * S)  # the restarted backend's first status
    replay = bridge.tick(T0 + 7 * S + DT).odometry
    assert [m.stamp_ns for m in replay] == [m.stamp_ns for m in during]
    assert bridge.counters["odometry_replayed"] == len(during) == 250
    assert bridge.tick(T0 + 7 * S + 2 * DT).odometry == ()  # once
    assert "odometry_lost" not in bridge.counters
    # a heartbeat while alive replays nothing
    bridge.on_backend_heartbeat(T0 + 7 * S + 3 * DT)
    assert bridge.tick(T0 + 7 * S + 4 * DT).odometry == ()


def test_an_outage_longer_than_the_replay_window_is_counted() -> None:
    bridge = RobotBridge(BridgeConfig("hsr", odometry_replay_s=1.0))
    bridge.on_backend_heartbeat(T0)
    drive(bridge, T0, T0 + S)
    bridge.on_backend_heartbeat(T0 + S)
    bridge.on_backend_gone(T0 + S + DT)
    drive(bridge, T0 + S, T0 + 5 * S)  # 4 s away, 1 s kept
    bridge.on_backend_heartbeat(T0 + 5 * S)
    replay = bridge.tick(T0 + 5 * S + DT).odometry
    lost = bridge.counters["odometry_lost"]
    assert 1.0 * 50 - 2 <= len(replay) <= 1.0 * 50 + 1
    assert lost + len(replay) == 200  # every message of the outage: replayed or counted


class _Localizer:
    """The robot's localization: it takes a correction (or ignores it when ``deaf``)."""

    def __init__(self, deaf: bool = False) -> None:
        self.pose = np.array([1.3, 1.0, 0.2])
        self.deaf = deaf

    def reading(self, stamp_ns: int) -> LocalizationPose:
        return LocalizationPose(stamp_ns, *self.pose)

    def take(self, c: PoseCorrection) -> None:
        if not self.deaf:
            self.pose = np.array([c.x, c.y, c.theta])


@pytest.mark.parametrize("deaf", [False, True])
def test_corrections_are_confirmed_by_the_robots_localization(deaf: bool) -> None:
    bridge = RobotBridge(BridgeConfig("hsr"))
    robot = _Localizer(deaf)
    c = PoseCorrection("hsr", T0, 0, 1.0, 1.0, 0.2, np.eye(3) * 1e-4, "correction",
                       offset_m=0.3, offset_rad=0.0, frame_id="map")
    bridge.on_robot_localization(robot.reading(T0 - S // 10), T0)
    bridge.on_correction_result(c, accepted=True)
    robot.take(c)
    for i in range(1, 40):  # 4 s of localization at 10 Hz
        t = T0 + i * S // 10
        bridge.on_robot_localization(robot.reading(t), t)
        bridge.tick(t)
    counters = bridge.counters
    if deaf:  # "applied" meant only that the publish call succeeded
        assert counters["corrections_unconfirmed"] == 1 and "corrections_confirmed" not in counters
    else:
        assert counters["corrections_confirmed"] == 1 and "corrections_unconfirmed" not in counters


def test_a_robot_without_localization_is_unverifiable() -> None:
    bridge = RobotBridge(BridgeConfig("hsr", correction_confirm_s=1.0))
    c = PoseCorrection("hsr", T0, 0, 1.0, 1.0, math.pi / 2, np.eye(3) * 1e-4, "initialization",
                       frame_id="map")
    bridge.tick(T0)
    bridge.on_correction_result(c, accepted=True)
    bridge.tick(T0 + 2 * S)
    assert bridge.counters["corrections_unverifiable"] == 1
