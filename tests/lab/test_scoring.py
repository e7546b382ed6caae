"""The one scoring module: estimates and corrections against a known truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lab.evaluation.scoring import (
    nearer_another_robot,
    pose_errors,
    rms_m,
    wrong_robot_corrections,
)
from protocol.messages import PoseCorrection, PoseEstimate

#: two robots standing still: a at the origin facing +x, b 2 m along x facing +y
TRUTH = {"a": np.array([0.0, 0.0, 0.0]), "b": np.array([2.0, 0.0, math.pi / 2])}


def truth_at(stamp_ns: int, robot_id: str) -> np.ndarray:
    return TRUTH[robot_id]


def _est(rid: str, x: float, y: float, theta: float, stamp_ns: int = 10) -> PoseEstimate:
    return PoseEstimate(rid, stamp_ns, 0, x, y, theta, np.eye(3) * 1e-4, "cameras")


def _corr(rid: str, x: float, y: float, stamp_ns: int = 10) -> PoseCorrection:
    return PoseCorrection(rid, stamp_ns, 0, x, y, 0.0, np.eye(3) * 1e-4, "correction")


def test_errors_are_against_each_estimates_own_robot_and_wrap_the_heading() -> None:
    # b's estimate is pi/2 - 0.05 one turn down: the heading error is 0.05, not 2 pi - 0.05
    dt, dth = pose_errors([_est("a", 0.3, 0.4, 0.1),
                           _est("b", 2.0, 0.0, math.pi / 2 - 2 * math.pi - 0.05)], truth_at)
    np.testing.assert_allclose(dt, [0.5, 0.0])
    np.testing.assert_allclose(dth, [0.1, 0.05], atol=1e-12)
    assert pose_errors([], truth_at)[0].size == 0
    assert rms_m(np.array([0.3, 0.4])) == pytest.approx(math.sqrt(0.125))
    assert math.isnan(rms_m(np.zeros(0)))


def test_an_estimate_nearer_another_robot_is_that_robots() -> None:
    assert not nearer_another_robot(_est("a", 0.9, 0.0, 0.0), truth_at, TRUTH)
    assert nearer_another_robot(_est("a", 1.1, 0.0, 0.0), truth_at, TRUTH)


def test_wrong_robot_corrections_by_key_by_taint_and_by_place() -> None:
    good = [_corr("a", 0.1, 0.0), _corr("b", 2.0, 0.1)]
    assert wrong_robot_corrections(good, truth_at, list(TRUTH)) == 0
    assert wrong_robot_corrections(good, truth_at, list(TRUTH), key_robots=["a", "a"]) == 1
    assert wrong_robot_corrections(good, truth_at, list(TRUTH), key_robots=["a", None]) == 0
    late = [_corr("a", 0.1, 0.0, stamp_ns=5), _corr("a", 0.1, 0.0, stamp_ns=20)]
    assert wrong_robot_corrections(late, truth_at, list(TRUTH), tainted_from_ns=20) == 1
    assert wrong_robot_corrections([_corr("a", 1.8, 0.0)], truth_at, list(TRUTH)) == 1
