"""Static detection and the correction rule (robot_bridge.policy), without transport."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.geometry import MotionState, StaticDetector, wrap_angle
from core.pose import PlanarPose
from core.site import Thresholds
from protocol.messages import PoseEstimate
from robot_bridge.adapters.base import LocalizationPose
from robot_bridge.policy import (
    ALREADY_SENT,
    AWAITING_AGREEMENT,
    HEADING_JUMP_TOO_LARGE,
    JUMP_TOO_LARGE,
    MOVING,
    NO_ESTIMATE,
    OUTSIDE_FLOOR,
    RATE_LIMITED,
    SETTLING,
    SMALL_OFFSET,
    UNCERTAIN,
    UNFIT_FOR_INIT,
    WINDOW_EXCEEDED,
    CorrectionDecision,
    CorrectionPolicy,
    TrustConfig,
    floor_area_around,
    floor_covariance,
    inside_floor_area,
    position_std_m,
)

TH = Thresholds()
S = 1_000_000_000
T0 = 1_700_000_000 * S


def estimate(x=1.0, y=2.0, theta=0.3, stamp_ns=T0, std_m=0.02, flags=(), source="cameras"):
    cov = np.diag([std_m**2, std_m**2, math.radians(1.0) ** 2])
    return PoseEstimate("hsr", stamp_ns, 0, x, y, theta, cov, source, ("cam_a",), flags=flags)


def static_motion(since_ns=T0 - 2 * S, stop_id=1) -> MotionState:
    return MotionState(T0, since_ns, True, stop_id)


def loc(x=1.0, y=2.0, theta=0.3, lost=False) -> LocalizationPose:
    return LocalizationPose(T0, x, y, theta, lost=lost)


def test_angle_and_offset_helpers() -> None:
    # one convention, [-pi, pi): pi itself is -pi
    assert wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(2 * math.pi + 0.1) == pytest.approx(0.1)
    d, a = PlanarPose(0, 0, math.pi - 0.01).distance_to(PlanarPose(3, 4, -math.pi + 0.01))
    assert d == pytest.approx(5.0) and a == pytest.approx(0.02)
    cov = np.array([[0.04, 0.0, 0], [0, 0.01, 0], [0, 0, 1.0]])
    assert position_std_m(cov) == pytest.approx(0.2)
    assert position_std_m(np.full((3, 3), np.nan)) == math.inf


def test_static_detection_needs_the_dwell_time_and_counts_stops() -> None:
    det = StaticDetector.from_thresholds(TH)
    dt = S // 50
    t = T0
    for _ in range(50):  # moving
        t += dt
        assert not det.update(t, 0.3, 0.0, 0.1).is_static
    assert det.state.still_since_ns is None
    stop_start = t + dt
    states = []
    for _ in range(60):  # 1.2 s still, dwell is 1.0 s
        t += dt
        states.append(det.update(t, 0.0, 0.0, 0.0))
    first_static = next(i for i, s in enumerate(states) if s.is_static)
    assert states[first_static].stamp_ns - stop_start >= TH.static_dwell_s * S
    assert all(not s.is_static for s in states[:first_static])
    assert {s.stop_id for s in states[first_static:]} == {1}
    # a single fast sample ends the stop; the next still period is stop 2
    assert not det.update(t + dt, 0.0, 0.0, 0.5).is_static
    t += dt
    for _ in range(60):
        t += dt
        det.update(t, 0.005, 0.0, 0.0)  # below threshold: still
    assert det.state.is_static and det.state.stop_id == 2


def test_rule_never_sends_while_moving_or_settling() -> None:
    pol = CorrectionPolicy(TH)
    far = estimate(x=1.5)
    assert pol.decide(far, loc(), MotionState(T0, None, False, 0), T0).reason == MOVING
    assert pol.decide(far, loc(), MotionState(T0, T0 - S // 2, False, 0), T0).reason == SETTLING
    assert pol.decide(far, None, MotionState(T0, None, False, 0), T0).reason == MOVING


def test_rule_correction_small_offset_jump_and_estimate_age() -> None:
    pol = CorrectionPolicy(TH)
    m = static_motion()
    assert pol.decide(estimate(x=1.03), loc(), m, T0).reason == SMALL_OFFSET
    assert pol.decide(estimate(theta=0.3 + math.radians(1.5)), loc(), m, T0).reason == SMALL_OFFSET
    d = pol.decide(estimate(x=1.2), loc(), m, T0)
    assert d.send and d.kind == "correction" and d.offset_m == pytest.approx(0.2)
    d = pol.decide(estimate(theta=0.3 + math.radians(5)), loc(), m, T0)
    assert d.send and d.offset_rad == pytest.approx(math.radians(5))
    assert pol.decide(estimate(x=2.5), loc(), m, T0).reason == JUMP_TOO_LARGE
    # an estimate observed before the stop began refers to another place
    old = estimate(x=1.2, stamp_ns=m.still_since_ns - 1)
    assert pol.decide(old, loc(), m, T0).reason == NO_ESTIMATE
    assert pol.decide(None, loc(), m, T0).reason == NO_ESTIMATE


def test_rule_gates_on_covariance() -> None:
    pol = CorrectionPolicy(TH)
    wide = estimate(x=1.3, std_m=TH.correction_max_std_m * 1.5)
    assert pol.decide(wide, loc(), static_motion(), T0).reason == UNCERTAIN
    assert pol.decide(wide, None, static_motion(), T0).reason == UNCERTAIN


def test_kidnapped_robot_gets_an_initialization_whatever_the_distance() -> None:
    """Far from anything is fine (no floor area configured) once three consecutive estimates
    agree (the default ``init_agreement_count``)."""
    pol = CorrectionPolicy(TH)
    far = [estimate(x=8.0 + 0.01 * i, y=-3.0, theta=-2.0, stamp_ns=T0 - S + i) for i in range(3)]
    for i, est in enumerate(far):
        pol.observe(est)
        if i < 2:
            assert pol.decide(est, None, static_motion(), T0).reason == AWAITING_AGREEMENT
    for localization in (None, loc(lost=True), loc(x=math.nan)):
        d = pol.decide(far[-1], localization, static_motion(), T0)
        assert d.send and d.kind == "initialization"
    lateral = estimate(flags=("single_camera", "lateral_only"))
    pol.observe(lateral)
    assert pol.decide(lateral, None, static_motion(), T0).reason == UNFIT_FOR_INIT


def test_one_pose_per_stop_and_rate_limit() -> None:
    pol = CorrectionPolicy(TH)
    m1 = static_motion(stop_id=1)
    assert pol.decide(estimate(x=1.2), loc(), m1, T0).send
    pol.mark_sent(m1, T0)
    assert pol.decide(estimate(x=1.2), loc(), m1, T0 + 10 * S).reason == ALREADY_SENT
    m2 = MotionState(T0 + S, T0, True, 2)
    assert pol.decide(estimate(x=1.2), loc(), m2, T0 + S).reason == RATE_LIMITED
    later = T0 + round(TH.correction_min_interval_s * S)
    assert pol.decide(estimate(x=1.2), loc(), m2, later).send


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(0.0, 0.5), st.floats(-1.0, 1.0), st.integers(1, 200),
            st.floats(-3.0, 3.0), st.booleans(),
        ),
        min_size=1,
        max_size=60,
    )
)
def test_property_no_pose_is_ever_decided_while_moving(steps) -> None:
    det = StaticDetector.from_thresholds(TH)
    pol = CorrectionPolicy(TH)
    t = T0
    for speed, yaw_rate, dt_ms, offset, localized in steps:
        t += dt_ms * 1_000_000
        m = det.update(t, speed, 0.0, yaw_rate)
        d = pol.decide(estimate(x=1.0 + offset, stamp_ns=t), loc() if localized else None, m, t)
        if d.send:
            assert m.is_static and speed <= TH.static_max_speed_mps
            assert abs(yaw_rate) <= TH.static_max_yaw_rate_radps
            pol.mark_sent(m, t)


# --------------------------------------------------------------------------------------------
# what the bridge trusts (issue 17): covariance floor, heading and accumulated jumps, the
# correction window, the initialization's floor area and agreement
# --------------------------------------------------------------------------------------------


def test_covariance_floor() -> None:
    floor_m, floor_rad = 0.02, math.radians(1.0)
    zero = floor_covariance(np.zeros((3, 3)), floor_m, floor_rad)
    assert np.allclose(zero, np.diag([floor_m**2, floor_m**2, floor_rad**2]))
    # a thin ellipse is widened only across, keeping its orientation
    R = np.array([[math.cos(0.7), -math.sin(0.7)], [math.sin(0.7), math.cos(0.7)]])
    cov = np.zeros((3, 3))
    cov[:2, :2] = R @ np.diag([0.1**2, 1e-8]) @ R.T
    cov[2, 2] = 0.1
    out = floor_covariance(cov, floor_m, floor_rad)
    assert np.allclose(np.linalg.eigvalsh(out[:2, :2]), [floor_m**2, 0.1**2])
    assert out[2, 2] == 0.1
    wide = np.diag([0.04, 0.09, 0.2])
    assert np.array_equal(floor_covariance(wide, floor_m, floor_rad), wide)
    # the gate sees the floor: with a floor above the gate nothing passes
    strict = CorrectionPolicy(TH, TrustConfig(position_std_floor_m=TH.correction_max_std_m * 2))
    assert strict.decide(estimate(x=1.2, std_m=0.0), loc(), static_motion(), T0).reason == UNCERTAIN


def test_heading_jump_is_limited() -> None:
    pol = CorrectionPolicy(TH)
    turned = estimate(theta=0.3 + math.radians(TH.correction_max_jump_deg + 5))
    assert pol.decide(turned, loc(), static_motion(), T0).reason == HEADING_JUMP_TOO_LARGE
    assert pol.decide(estimate(theta=0.3 + math.radians(20)), loc(), static_motion(), T0).send


def _send(pol: CorrectionPolicy, est: PoseEstimate, localization: LocalizationPose, stop_id: int,
          now_ns: int, seq: int) -> CorrectionDecision:
    m = MotionState(now_ns, now_ns - 2 * S, True, stop_id)
    est = dataclasses.replace(est, stamp_ns=now_ns - S)  # observed during this stop
    d = pol.decide(est, localization, m, now_ns)
    if d.send:
        pol.mark_sent(m, now_ns, d, localization, seq)
    return d


def test_repeated_sub_limit_jumps_do_not_accumulate() -> None:
    """0.6 m each time, relative to where the robot now believes it is: the second would put
    the robot 1.2 m from its own (uncorrected) localization, beyond one jump; so would a second
    20 deg turn. After the window, a new jump is allowed."""
    pol = CorrectionPolicy(TH)
    t = T0
    assert _send(pol, estimate(x=1.6), loc(), 1, t, 0).send
    t += 10 * S
    d = _send(pol, estimate(x=2.2), loc(x=1.6), 2, t, 1)
    assert d.reason == JUMP_TOO_LARGE and d.offset_m == pytest.approx(0.6)
    pol2 = CorrectionPolicy(TH)
    assert _send(pol2, estimate(theta=0.3 + math.radians(20)), loc(), 1, T0, 0).send
    d = _send(pol2, estimate(theta=0.3 + math.radians(40)), loc(theta=0.3 + math.radians(20)), 2,
              T0 + 10 * S, 1)
    assert d.reason == HEADING_JUMP_TOO_LARGE
    # the window passed: the correction is no longer in the reference
    later = T0 + round((TH.correction_window_s + 1) * S)
    assert _send(pol, estimate(x=2.2), loc(x=1.6), 3, later, 2).send


def test_correction_window_bounds_the_total() -> None:
    """Back and forth by 0.6 m: no net drift, but 1.2 m of correction within the window is
    over the rate limit; a refused correction does not count."""
    pol = CorrectionPolicy(TH)
    assert _send(pol, estimate(x=1.6), loc(), 1, T0, 0).send
    d = _send(pol, estimate(x=1.0), loc(x=1.6), 2, T0 + 10 * S, 1)
    assert d.reason == WINDOW_EXCEEDED
    assert [a.seq for a in pol.window(T0 + 10 * S)] == [0]
    pol.on_result(0, accepted=False)  # the robot refused it: nothing to count
    assert pol.window(T0 + 10 * S) == []
    assert _send(pol, estimate(x=1.6), loc(), 2, T0 + 10 * S, 1).send


def test_initialization_needs_the_floor_area_and_agreement() -> None:
    pol = CorrectionPolicy(TH, TrustConfig(floor_area=(0.0, 0.0, 20.0, 12.0)))
    m = static_motion()
    outside = [estimate(x=40.0, y=6.0, stamp_ns=T0 - S + i) for i in range(5)]
    for est in outside:
        pol.observe(est)
    assert pol.decide(outside[-1], None, m, T0).reason == OUTSIDE_FLOOR
    # two places 0.5 m apart, alternating: never three in a row that agree
    for i in range(6):
        est = estimate(x=5.0 + 0.5 * (i % 2), y=6.0, stamp_ns=T0 - S + 10 + i)
        pol.observe(est)
        assert pol.decide(est, None, m, T0).reason == AWAITING_AGREEMENT
    for i in range(3):
        est = estimate(x=5.0 + 0.01 * i, y=6.0, stamp_ns=T0 - S + 20 + i)
        pol.observe(est)
    assert pol.agreement(est, m.still_since_ns) == 3
    assert pol.decide(est, None, m, T0).kind == "initialization"
    # estimates from before the stop do not count towards the agreement
    assert pol.agreement(est, est.stamp_ns) == 1
    # nor does one that is not the newest of its source
    assert pol.agreement(outside[0], 0) == 0


def test_floor_area_helpers_and_config_checks() -> None:
    assert floor_area_around([(7.0, 3.0), (13.0, 9.0)], 2.0) == (5.0, 1.0, 15.0, 11.0)
    assert inside_floor_area(5.0, 11.0, (5.0, 1.0, 15.0, 11.0))
    assert not inside_floor_area(4.9, 5.0, (5.0, 1.0, 15.0, 11.0))
    assert inside_floor_area(1e6, -1e6, ())
    with pytest.raises(ValueError, match="floor_area"):
        TrustConfig(floor_area=(1.0, 0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="floor_area"):
        TrustConfig(floor_area=(0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="init_agreement_count"):
        TrustConfig(init_agreement_count=0)
