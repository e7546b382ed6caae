"""Single-camera MAP treatment (``SolverConfig.single_camera="map"``), Monte Carlo.

One camera of the example site sees the robot at ~3 m and ~6 m. The detections follow exactly
the configured error model (fresh extrinsic error of the camera per trial, per-detection shift
and scale about the keypoints' centroid, independent pixel noise). The prior is drawn from its
stated covariance P (good: 5 cm / 2 deg, bad: 20 cm / 5 deg). The MAP combination of the plain
solve and the prior must be no worse, on average, than the better of the two; without a
(valid) prior covariance it must be the plain solve itself; a prior that contradicts the image
is rejected by the gate.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from backend_service.estimate import PoseResult, SolverConfig, estimate_pose
from backend_service.frame_set import FrameSet
from core.camera import CameraModel
from core.pose import PlanarPose
from tests.backend_service.pose_synth import (
    ERRORS,
    ROBOT,
    detect_with_errors,
    example_site,
    pose_error,
    project_pose,
    true_camera,
)

SITE = example_site()
KP_BASE = np.asarray(SITE.robot_model(ROBOT).keypoints_base_m, dtype=np.float64)
CAMERA = "cam_sw"  # at (7, 3, 2.5)

MAP = SolverConfig(single_camera="map", **ERRORS)  # the default robust loss
PLAIN = dataclasses.replace(MAP, single_camera="plain")

GEOMETRIES = {
    "near": (PlanarPose(9.1, 5.1, 0.4), 3.0),   # (truth, ground distance to the camera, m)
    "far": (PlanarPose(11.3, 7.1, 1.0), 5.9),
}
P_GOOD = np.diag([0.05**2, 0.05**2, math.radians(2.0) ** 2])
P_BAD = np.diag([0.2**2, 0.2**2, math.radians(5.0) ** 2])
TRIALS = 200

#: Noise margins of "MAP is no worse than the better of solve and prior". The information-
#: weighted combination has, per component, a variance no larger than either input's, so in
#: expectation it is at least as good as the better one. The three errors are measured on the
#: same trials (paired), so the sampling noise of their difference is far below that of each
#: mean; what remains is the first-order (linearized, robust-loss) slack of the combination:
#: 10 % of the better mean (2-6 mm of position at these distances, 0.06-0.15 deg of yaw).
#: A fusion that weighted the inputs wrongly (prior as trusted as a sharp solve, or the other
#: way round) is off by far more (the prior's errors are 1.5-12 times the solve's here).
MARGIN = 0.10


def draw_frame_set(truth: PlanarPose, cam: CameraModel, rng: np.random.Generator) -> FrameSet:
    """One detection of ``truth`` by the (true) camera ``cam`` with fresh detection errors
    (:func:`pose_synth.detect_with_errors`)."""
    obs = detect_with_errors(truth, cam, KP_BASE, rng)
    assert obs is not None and int(np.count_nonzero(obs.keypoint_scores)) >= 3
    return FrameSet.from_observations(ROBOT, [obs])


def draw_prior(truth: PlanarPose, P: np.ndarray, rng: np.random.Generator) -> PlanarPose:
    x, y, theta = truth.as_array() + np.linalg.cholesky(P) @ rng.normal(size=3)
    return PlanarPose(float(x), float(y), float(theta))


def assert_same_result(a: PoseResult, b: PoseResult) -> None:
    assert a.ok and b.ok, (a.reason, b.reason)
    assert a.pose is not None and b.pose is not None
    assert a.estimate is not None and b.estimate is not None
    assert np.array_equal(a.pose.as_array(), b.pose.as_array())
    assert np.array_equal(a.estimate.covariance, b.estimate.covariance)


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_geometry_is_single_camera_at_the_stated_distance(geometry: str) -> None:
    truth, dist = GEOMETRIES[geometry]
    _, ok = project_pose(SITE, truth, CAMERA)
    assert ok.all()
    c = SITE.camera(CAMERA).position_world
    assert abs(math.hypot(truth.x - c[0], truth.y - c[1]) - dist) < 0.1


@pytest.mark.parametrize("prior_name", ["good", "bad"])
@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_map_is_no_worse_than_the_better_of_solve_and_prior(geometry: str,
                                                            prior_name: str) -> None:
    truth, _ = GEOMETRIES[geometry]
    P = P_GOOD if prior_name == "good" else P_BAD
    rng = np.random.default_rng(7)
    err: dict[str, list[tuple[float, float]]] = {"map": [], "plain": [], "prior": []}
    used = 0
    for _ in range(TRIALS):
        fs = draw_frame_set(truth, true_camera(SITE, CAMERA, rng), rng)
        prior = draw_prior(truth, P, rng)
        a = estimate_pose(fs, SITE, prior, MAP, P)
        b = estimate_pose(fs, SITE, prior, PLAIN, P)
        assert a.ok and b.ok, (a.reason, b.reason)
        assert a.pose is not None and b.pose is not None and a.estimate is not None
        assert "single_camera" in a.estimate.flags
        used += "map_prior" in a.estimate.flags
        err["map"].append(pose_error(a.pose, truth))
        err["plain"].append(pose_error(b.pose, truth))
        err["prior"].append(pose_error(prior, truth))
    mean = {k: np.mean(v, axis=0) for k, v in err.items()}
    # the prior is drawn from its own covariance: the 99.9 % gate lets nearly all of them in
    assert used >= 0.97 * TRIALS, used
    for i, what in ((0, "position m"), (1, "yaw rad")):
        best = min(mean["plain"][i], mean["prior"][i])
        assert mean["map"][i] <= (1.0 + MARGIN) * best, (
            what, mean["map"][i], mean["plain"][i], mean["prior"][i])
        if geometry == "far" and prior_name == "good":
            # the prior is informative here (the far solve is weak): it must actually help,
            # or a MAP that ignored the prior would pass the bound above (measured ~0.8x)
            assert mean["map"][i] < 0.9 * mean["plain"][i], (what, mean["map"][i],
                                                            mean["plain"][i])


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_without_prior_covariance_map_is_the_plain_solve(geometry: str) -> None:
    truth, _ = GEOMETRIES[geometry]
    rng = np.random.default_rng(8)
    for _ in range(50):
        fs = draw_frame_set(truth, true_camera(SITE, CAMERA, rng), rng)
        prior = draw_prior(truth, P_GOOD, rng)
        a = estimate_pose(fs, SITE, prior, MAP, None)
        b = estimate_pose(fs, SITE, prior, PLAIN, None)
        assert_same_result(a, b)
        assert a.estimate is not None and b.estimate is not None
        assert a.estimate.flags == b.estimate.flags
        assert "map_prior" not in a.estimate.flags


@pytest.mark.parametrize("geometry", list(GEOMETRIES))
def test_prior_far_outside_its_covariance_is_rejected(geometry: str) -> None:
    truth, _ = GEOMETRIES[geometry]
    rng = np.random.default_rng(9)
    for k in range(24):
        fs = draw_frame_set(truth, true_camera(SITE, CAMERA, rng), rng)
        angle = 2 * math.pi * k / 24  # 1 m off in every direction, along and across the ray
        prior = PlanarPose(truth.x + math.cos(angle), truth.y + math.sin(angle), truth.theta)
        a = estimate_pose(fs, SITE, prior, MAP, P_GOOD)
        b = estimate_pose(fs, SITE, prior, PLAIN, P_GOOD)
        assert_same_result(a, b)
        assert a.estimate is not None
        assert "prior_rejected" in a.estimate.flags and "map_prior" not in a.estimate.flags


@pytest.mark.parametrize("cov", [
    np.diag([0.05**2, -0.05**2, 0.001]),          # not positive definite
    np.zeros((3, 3)),                              # singular
    np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) * 1e-3,  # indefinite
    np.diag([0.05**2, np.nan, 0.001]),             # NaN
    np.diag([0.05**2, np.inf, 0.001]),             # infinite
    np.diag([0.05**2, 0.05**2]),                   # wrong shape
    np.eye(6) * 1e-3,                              # wrong shape
], ids=["negative", "zero", "indefinite", "nan", "inf", "2x2", "6x6"])
def test_invalid_prior_covariance_is_ignored(cov: np.ndarray) -> None:
    truth, _ = GEOMETRIES["far"]
    rng = np.random.default_rng(10)
    for _ in range(5):
        fs = draw_frame_set(truth, true_camera(SITE, CAMERA, rng), rng)
        prior = draw_prior(truth, P_GOOD, rng)
        a = estimate_pose(fs, SITE, prior, MAP, cov)
        b = estimate_pose(fs, SITE, prior, PLAIN, None)
        assert_same_result(a, b)
        assert a.estimate is not None
        assert "map_prior" not in a.estimate.flags
        assert "prior_rejected" not in a.estimate.flags
