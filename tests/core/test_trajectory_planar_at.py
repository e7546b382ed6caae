"""Trajectory.planar_at: poses between two stamps interpolated (yaw the shorter way), exact
stamps as they are, nothing outside the trajectory or across a gap."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.trajectory import Trajectory, TrajectoryError


def test_interpolates_between_poses_and_refuses_gaps_and_outside() -> None:
    stamps = np.array([10.0, 10.1, 10.2, 11.0])
    poses = np.array([[0, 0, math.pi - 0.1], [0.1, 0.0, -math.pi + 0.1], [0.2, 0.1, -3.0],
                      [0.3, 0.1, -3.0]])
    traj = Trajectory.from_planar(stamps, poses)
    got, ok = traj.planar_at([10.05, 10.1, 9.0, 10.6, 11.5, 10.15], max_gap_s=0.2)
    assert ok.tolist() == [True, True, False, False, False, True]
    np.testing.assert_allclose(got[0, :2], [0.05, 0.0], atol=1e-12)
    assert abs(abs(got[0, 2]) - math.pi) < 1e-9  # across +-pi the short way, not through 0
    np.testing.assert_allclose(got[1], poses[1], atol=1e-12)
    assert np.isnan(got[2]).all() and np.isnan(got[3]).all()  # outside; a 0.8 s gap
    np.testing.assert_allclose(got[5, :2], [0.15, 0.05], atol=1e-12)
    _, ok_wide = traj.planar_at([10.6], max_gap_s=1.0)
    assert ok_wide.tolist() == [True]


def test_stamps_must_increase() -> None:
    traj = Trajectory.from_planar(np.array([1.0, 1.0]), np.zeros((2, 3)))
    with pytest.raises(TrajectoryError, match="not increasing at pose 1"):
        traj.planar_at([1.0], 0.1)
