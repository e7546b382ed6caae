"""The NEES table of ``evaluate paper``: e^T C^-1 e per source and camera count."""

from __future__ import annotations

import math

import numpy as np

from lab.experiments import RunResult, StopSample, nees_table


def _sample(n_cams: int, est: list[float], cov: np.ndarray | None) -> StopSample:
    s = StopSample("r", "t", "WP1", n_cams, 0, np.array([1.0, 2.0, math.pi - 0.01]),
                   {"one_frame": np.array(est)})
    if cov is not None:
        s.covariances["one_frame"] = cov
    return s


def test_nees_per_camera_count_with_wrapped_heading() -> None:
    cov = np.diag([0.01, 0.04, 0.0001])
    samples = [
        _sample(2, [1.1, 2.0, math.pi - 0.01], cov),        # 0.1^2 / 0.01 = 1
        _sample(2, [1.0, 2.4, -math.pi + 0.01], cov),       # 0.4^2/0.04 + 0.02^2/1e-4 = 8
        _sample(4, [1.0, 2.0, math.pi - 0.01], cov),        # 0
        _sample(1, [5.0, 5.0, 0.0], None),                  # no covariance: not counted
    ]
    run = RunResult("r", "t", False, 0, samples, np.zeros(0), np.zeros((0, 3)),
                    np.zeros((0, 3)), np.zeros((0, 3)), 1.0, 1.0, {})
    md, numbers = nees_table([run])
    row = numbers["one_frame"]
    assert math.isclose(row["2"], 4.5, rel_tol=1e-9)
    assert row["4"] == 0.0 and "1" not in row
    assert math.isclose(row["all"], 3.0, rel_tol=1e-9) and row["n_all"] == 3
    assert "| Cameras (1 frame) | n/a | 4.5 | 0.0 | 3.0 |" in md
    assert numbers["fused"] == {}
