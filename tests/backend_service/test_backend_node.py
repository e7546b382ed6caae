"""Backend node pieces that need no network."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("gtsam")

from backend_service.service import RobotTrack


def test_ground_truth_interpolation_at_a_stamp() -> None:
    track = RobotTrack("hsr", fusion=None, averager=None)  # type: ignore[arg-type]
    for k in range(50):
        track.ground_truth.append((k * 100, (0.01 * k, 2.0, math.pi - 0.001 + 0.0001 * k)))
    assert track.truth_at(-1) is None and track.truth_at(4901) is None
    got = track.truth_at(1250)
    assert np.allclose(got[:2], [0.125, 2.0])
    # heading interpolates across the +-pi wrap, not through zero
    assert abs(abs(got[2]) - math.pi) < 0.01
    assert np.allclose(track.truth_at(100)[:2], [0.01, 2.0])
    assert np.allclose(track.truth_at(4900)[:2], [0.49, 2.0])
