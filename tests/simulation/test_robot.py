"""Robot motion, odometry drift, internal localization drift and static-only corrections."""

from __future__ import annotations

import math

import numpy as np
import pytest

from simulation.robot import MotionPlan, SimulatedRobot
from simulation.scenario import load_scenario


@pytest.fixture(scope="module")
def scenario():
    return load_scenario()


def test_plan_stops_at_waypoints(scenario) -> None:
    wps = scenario.trajectory("traj3")
    plan = MotionPlan(wps, scenario.motion, np.random.default_rng(0))
    assert len(plan.stops) == len(wps)
    for st, wp in zip(plan.stops, wps, strict=False):
        mid = (st.t0_s + st.t1_s) / 2
        assert plan.is_static(mid)
        p = plan.pose_at(mid)[0]
        assert math.hypot(p[0] - wp.x, p[1] - wp.y) < 0.1
        assert st.t1_s - st.t0_s == pytest.approx(
            scenario.motion.start_s if st.index == 0 else scenario.motion.stop_s)
    v = plan.velocity_at(np.linspace(0, plan.duration_s, 2000))
    assert np.abs(v[:, 0]).max() <= scenario.motion.max_speed_mps + 1e-9
    assert np.abs(v[:, 1]).max() <= scenario.motion.max_yaw_rate_radps + 1e-9
    assert not plan.is_static(plan.stops[1].t0_s - 1.0)


def _drive(scenario, seed: int, distance_m: float) -> SimulatedRobot:
    plan = MotionPlan(scenario.trajectory("traj1"), scenario.motion, np.random.default_rng(seed))
    robot = SimulatedRobot(scenario, plan, np.random.default_rng(seed + 1000))
    t = 0.0
    while robot.travelled_m < distance_m and t < plan.duration_s:
        t += 0.5
        robot.step_to(t)
    return robot


def test_localization_error_after_5_m_exceeds_10_cm(scenario) -> None:
    errs = []
    for seed in range(12):
        robot = _drive(scenario, seed, 5.0)
        assert robot.travelled_m >= 5.0
        gt, loc = robot.ground_truth(), robot.localization_pose()
        errs.append(math.hypot(*(loc[:2] - gt[:2])))
    assert np.mean(errs) > 0.10
    assert np.mean(errs) < 0.5  # tens of cm, not metres (mean-reverting like AMCL)


def test_odometry_drifts_but_tracks_motion(scenario) -> None:
    robot = _drive(scenario, 3, 8.0)
    odom = robot.odometry_pose()
    # odom frame starts at the origin: compare travelled displacement magnitudes
    start = np.array([scenario.trajectory("traj1")[0].x, scenario.trajectory("traj1")[0].y])
    true_disp = np.linalg.norm(robot.ground_truth()[:2] - start)
    assert abs(np.linalg.norm(odom[:2]) - true_disp) < 0.1 * robot.travelled_m + 0.05
    assert np.linalg.norm(odom[:2]) != pytest.approx(true_disp, abs=1e-6)


def test_corrections_only_when_static(scenario) -> None:
    plan = MotionPlan(scenario.trajectory("traj3"), scenario.motion, np.random.default_rng(1))
    robot = SimulatedRobot(scenario, plan, np.random.default_rng(2))
    moving_t = plan.stops[1].t0_s - 2.0
    robot.step_to(moving_t)
    gt = robot.ground_truth()
    assert not robot.apply_correction(gt, robot.stamp_ns(moving_t))
    assert robot.corrections_refused == 1
    static_t = plan.stops[1].t0_s + 1.0
    robot.step_to(static_t)
    gt = robot.ground_truth()
    assert robot.apply_correction(gt, robot.stamp_ns(static_t - 0.2))
    np.testing.assert_allclose(robot.localization_pose(), gt, atol=1e-12)
    # a correction stamped while the robot was still moving is refused too
    assert not robot.apply_correction(gt, robot.stamp_ns(plan.stops[1].t0_s - 1.0))
