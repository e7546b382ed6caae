"""The covariance's parts: averaging, the prior combination's bookkeeping, config checks, and
the detector error figures the defaults come from."""

from __future__ import annotations

import math

import numpy as np
import pytest

from backend_service.covariance import (
    CovarianceParts,
    ErrorModel,
    fuse_with_prior,
    valid_covariance,
)
from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.multi_frame import MultiFrameAverager, MultiFrameConfig
from core.pose import PlanarPose
from lab.evaluation.keypoints import common_error_summary, detection_common_error
from tests.backend_service.pose_synth import example_site, make_frame_set

SITE = example_site()
TRUTH = PlanarPose(10.0, 6.0, 0.4)


def _results(n: int, config: SolverConfig) -> list:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        fs = make_frame_set(SITE, TRUTH, ["cam_ne", "cam_sw"], 1.0, rng, stamp_ns=10**9 + i)
        res = estimate_pose(fs, SITE, TRUTH, config)
        assert res.ok and res.covariance_parts is not None
        out.append(res)
    return out


def test_parts_add_up_and_calibration_is_systematic() -> None:
    res = _results(1, SolverConfig(extrinsic_sigma_m=0.02, extrinsic_sigma_deg=0.2))[0]
    parts = res.covariance_parts
    np.testing.assert_allclose(parts.total, res.estimate.covariance, rtol=1e-12, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(parts.systematic) > 0)
    none = _results(1, SolverConfig(extrinsic_sigma_m=0.0, extrinsic_sigma_deg=0.0))[0]
    assert np.all(none.covariance_parts.systematic == 0)
    # more calibration error: more systematic covariance, the per-frame part unchanged
    np.testing.assert_allclose(none.covariance_parts.frame, parts.frame, rtol=1e-9)
    resid = _results(1, SolverConfig(covariance_model="residual"))[0]
    assert np.trace(resid.estimate.covariance) < np.trace(parts.frame)  # correlated terms add


@pytest.mark.parametrize("rho", [0.0, 0.5, 1.0])
def test_average_shrinks_only_the_per_frame_part(rho: float) -> None:
    results = _results(5, SolverConfig())
    avg = MultiFrameAverager.from_config(MultiFrameConfig(count=5, frame_correlation=rho))
    out = None
    for r in results:
        out = avg.add(r)
    assert out is not None and out.covariance_parts is not None
    sys_mean = np.mean([r.covariance_parts.systematic for r in results], axis=0)
    frame_mean = np.mean([r.covariance_parts.frame for r in results], axis=0)
    np.testing.assert_allclose(out.covariance_parts.systematic, sys_mean, rtol=1e-9)
    expected = sys_mean + frame_mean * (rho + (1 - rho) / 5)
    np.testing.assert_allclose(out.estimate.covariance, expected, rtol=1e-9, atol=1e-15)


def test_frame_correlation_out_of_range_is_an_error() -> None:
    with pytest.raises(ValueError, match="frame_correlation"):
        MultiFrameConfig(frame_correlation=1.5)


@pytest.mark.parametrize("field,value", [("single_camera", "heuristic"),
                                         ("covariance_model", "magic"),
                                         ("extrinsic_sigma_m", -0.01),
                                         ("detection_scale_sigma", math.nan)])
def test_bad_solver_config_names_the_field(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        SolverConfig(**{field: value})


def test_fuse_with_prior_is_the_information_weighted_mean() -> None:
    C = np.diag([0.01, 0.0004, 0.001])  # long along x (the viewing ray)
    parts = CovarianceParts(0.5 * C, 0.5 * C)
    P = np.diag([0.0004, 0.01, 0.001])
    q_s, q_p = np.array([1.1, 2.0, 0.1]), np.array([1.0, 2.1, 0.0])
    out = fuse_with_prior(q_s, parts, q_p, P)
    assert out.used
    # x from the prior (it knows x), y from the solve, theta halfway
    assert abs(out.q[0] - 1.0) < 0.01 and abs(out.q[1] - 2.0) < 0.01
    assert abs(out.q[2] - 0.05) < 1e-9
    np.testing.assert_allclose(out.parts.total, np.linalg.inv(np.linalg.inv(C)
                                                              + np.linalg.inv(P)), rtol=1e-9)
    far = fuse_with_prior(q_s, parts, q_p + np.array([2.0, 0.0, 0.0]), P)
    assert not far.used and np.array_equal(far.q, q_s) and far.parts is parts


def test_fuse_with_prior_wraps_the_heading() -> None:
    C = np.diag([1e-4, 1e-4, 0.01])
    out = fuse_with_prior(np.array([0.0, 0.0, math.pi - 0.05]), CovarianceParts(C, 0 * C),
                          np.array([0.0, 0.0, -math.pi + 0.05]), C)
    assert out.used and abs(abs(out.q[2]) - math.pi) < 1e-9


@pytest.mark.parametrize("cov", [None, np.eye(2), np.full((3, 3), np.nan),
                                 np.diag([1.0, -1.0, 1.0]), "abc"])
def test_invalid_prior_covariance_is_none(cov: object) -> None:
    assert valid_covariance(cov) is None


def test_error_model_any() -> None:
    assert not ErrorModel().any and ErrorModel(extrinsic_sigma_deg=0.1).any


def test_detection_common_error_recovers_shift_and_scale() -> None:
    rng = np.random.default_rng(0)
    true_px = rng.uniform(100, 200, (12, 2))
    c = true_px.mean(axis=0)
    found = c + 1.03 * (true_px - c) + np.array([2.0, -1.0])
    found[4] += 40.0  # one gross keypoint error is left out of the fit
    row = detection_common_error(found, true_px)
    np.testing.assert_allclose(row[:3], [2.0, -1.0, 0.03], atol=1e-9)
    assert row[3] < 1e-9
    rows = [np.array([s, -s, 0.01 * s, 0.5]) for s in rng.normal(0, 1.0, 400)]
    summary = common_error_summary(rows)
    # the RMS of |N(0, 1)| without its largest 5 %: 0.87
    assert abs(summary["shift_px"] - 0.87) < 0.06 and abs(summary["scale"] - 0.0087) < 0.0012
    gross = rows + [np.array([140.0, 90.0, 1.1, 0.5])] * 5  # swapped detections: trimmed
    assert common_error_summary(gross)["shift_px"] < 1.0
    assert common_error_summary([]) == {}
