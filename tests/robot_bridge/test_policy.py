"""Static detection and the correction rule (robot_bridge.policy), without transport."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.geometry import MotionState, StaticDetector, wrap_angle
from protocol.messages import PoseEstimate
from protocol.site import Thresholds
from robot_bridge.adapters.base import LocalizationPose
from robot_bridge.policy import (
    ALREADY_SENT,
    JUMP_TOO_LARGE,
    MOVING,
    NO_ESTIMATE,
    RATE_LIMITED,
    SETTLING,
    SMALL_OFFSET,
    UNCERTAIN,
    UNFIT_FOR_INIT,
    CorrectionPolicy,
    pose_offset,
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
    d, a = pose_offset(0, 0, math.pi - 0.01, 3, 4, -math.pi + 0.01)
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
    pol = CorrectionPolicy(TH)
    far = estimate(x=8.0, y=-3.0, theta=-2.0)
    for localization in (None, loc(lost=True), loc(x=math.nan)):
        d = pol.decide(far, localization, static_motion(), T0)
        assert d.send and d.kind == "initialization"
    lateral = estimate(flags=("single_camera", "lateral_only"))
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
