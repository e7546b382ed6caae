"""Consistency (NEES) of the reported covariance under exactly the error model it claims.

Every trial draws frame-sets the way :class:`SolverConfig`'s error model describes them: the
true cameras are the calibrated ones rotated about their optical centre (rotation vector, world
axes) and moved, each component with ``extrinsic_sigma_deg`` / ``extrinsic_sigma_m``; every
detection is shifted as a whole (``detection_shift_sigma_px``), scaled about the centroid of its
in-image keypoints (``detection_scale_sigma``) and gets independent pixel noise. If the
covariance is right, NEES = e^T C^-1 e (e = estimate - truth, 3 DoF) averages 3.

The example site's room is seen by at least two cameras everywhere (a pose seen by one camera
only lies >= 10 m from it, outside the room), so the 1- and 2-camera frame-sets are poses in the
room whose other cameras are occluded; the tests check how many cameras each frame-set holds.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from backend_service.estimate import PoseResult, SolverConfig, estimate_pose
from backend_service.frame_set import FrameSet
from backend_service.multi_frame import MultiFrameAverager
from core.camera import CameraModel
from core.geometry import wrap_angle
from core.pose import PlanarPose
from tests.backend_service.pose_synth import (
    ERRORS,
    ROBOT,
    detect_with_errors,
    example_site,
    project_pose,
    true_camera,
)

SITE = example_site()
KP_BASE = np.asarray(SITE.robot_model(ROBOT).keypoints_base_m, dtype=np.float64)

CONFIG = SolverConfig(robust_loss="none", **ERRORS)

#: mean NEES of a consistent 3-DoF covariance is 3; accepted band
NEES_LOW, NEES_HIGH = 0.7 * 3, 1.5 * 3

ALL_CAMERAS = ("cam_ne", "cam_nw", "cam_se", "cam_sw")
CENTRE = PlanarPose(10.0, 6.0, 0.4)
NEAR = PlanarPose(9.1, 5.1, 0.4)   # ~3.0 m (ground distance) from cam_sw at (7, 3)
FAR = PlanarPose(11.3, 7.1, 1.0)   # ~5.9 m from cam_sw

#: (id, truth, cameras of the frame-set, trials)
CASES = [
    ("1 camera near", NEAR, ("cam_sw",), 300),
    ("1 camera far", FAR, ("cam_sw",), 300),
    ("2 cameras", CENTRE, ("cam_ne", "cam_sw"), 300),
    ("4 cameras", CENTRE, ALL_CAMERAS, 300),
]


def true_cameras(camera_ids: tuple[str, ...], rng: np.random.Generator) -> dict[str, CameraModel]:
    """The cameras as they really are: the calibrated ones with a fresh extrinsic error."""
    return {cid: true_camera(SITE, cid, rng) for cid in camera_ids}


def draw_frame_set(truth: PlanarPose, cameras: dict[str, CameraModel], rng: np.random.Generator,
                   stamp_ns: int = 1_000_000_000) -> FrameSet:
    """One frame-set of ``truth`` seen by the (true) ``cameras`` with fresh detection errors
    (:func:`pose_synth.detect_with_errors`)."""
    obs = [detect_with_errors(truth, cam, KP_BASE, rng, stamp_ns) for cam in cameras.values()]
    return FrameSet.from_observations(ROBOT, [o for o in obs if o is not None])


def seen_by(frame_set: FrameSet) -> int:
    return sum(1 for o in frame_set.observations if np.any(np.asarray(o.keypoint_scores) > 0))


def nees(result: PoseResult, truth: PlanarPose) -> float:
    assert result.ok and result.pose is not None and result.estimate is not None, result.reason
    e = result.pose.as_array() - truth.as_array()
    e[2] = wrap_angle(float(e[2]))
    return float(e @ np.linalg.solve(result.estimate.covariance, e))


def mean_nees(truth: PlanarPose, camera_ids: tuple[str, ...], trials: int, config: SolverConfig,
              seed: int) -> float:
    rng = np.random.default_rng(seed)
    values = []
    for _ in range(trials):
        fs = draw_frame_set(truth, true_cameras(camera_ids, rng), rng)
        assert seen_by(fs) == len(camera_ids)
        values.append(nees(estimate_pose(fs, SITE, None, config), truth))
    return float(np.mean(values))


@pytest.mark.parametrize(("truth", "camera_ids"), [c[1:3] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_chosen_cameras_see_the_whole_robot(truth: PlanarPose,
                                            camera_ids: tuple[str, ...]) -> None:
    for cid in camera_ids:
        _, ok = project_pose(SITE, truth, cid)
        assert ok.all(), cid


@pytest.mark.parametrize(("truth", "camera_ids", "trials"), [c[1:] for c in CASES],
                         ids=[c[0] for c in CASES])
def test_propagated_covariance_is_consistent(truth: PlanarPose, camera_ids: tuple[str, ...],
                                             trials: int) -> None:
    m = mean_nees(truth, camera_ids, trials, CONFIG, seed=11)
    assert NEES_LOW <= m <= NEES_HIGH, m


def test_residual_covariance_alone_is_overconfident_for_one_camera() -> None:
    """The Gauss-Newton covariance alone ignores the correlated errors: far too small."""
    m = mean_nees(FAR, ("cam_sw",), 150, dataclasses.replace(CONFIG, covariance_model="residual"),
                  seed=11)
    assert m > 4.5, m


def test_five_frame_average_of_independent_frames_is_consistent() -> None:
    """Five frame-sets that share one extrinsic draw (the same cameras) and have independent
    detection errors, averaged with ``frame_correlation=0``: the average keeps the systematic
    part and divides the per-frame part by 5 -- and is consistent. Dividing everything by 5
    (treating the calibration error as averaging out too) is overconfident."""
    rng = np.random.default_rng(21)
    camera_ids = ("cam_ne", "cam_sw")
    kept, naive = [], []
    for _ in range(200):
        cameras = true_cameras(camera_ids, rng)
        # wide jump gates: this test is about the covariance, not about detecting motion
        avg = MultiFrameAverager(5, max_jump_m=1.0, max_jump_rad=math.radians(30.0),
                                 frame_correlation=0.0)
        out, singles = None, []
        for i in range(5):
            fs = draw_frame_set(CENTRE, cameras, rng, stamp_ns=1_000_000_000 + i * 100_000_000)
            res = estimate_pose(fs, SITE, None, CONFIG)
            assert res.ok, res.reason
            singles.append(res)
            out = avg.add(res)
        assert out is not None and "multi_frame" in out.estimate.flags
        kept.append(nees(out, CENTRE))
        all_down = np.mean([r.estimate.covariance for r in singles], axis=0) / 5
        naive.append(nees(dataclasses.replace(
            out, estimate=dataclasses.replace(out.estimate, covariance=all_down)), CENTRE))
    assert NEES_LOW <= np.mean(kept) <= NEES_HIGH, np.mean(kept)
    assert np.mean(naive) > NEES_HIGH, np.mean(naive)
