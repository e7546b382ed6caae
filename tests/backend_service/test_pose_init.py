"""Initialization (prior / PnP) and garbage inputs that must give "no estimate"."""

from __future__ import annotations

import math

import numpy as np
import pytest

from backend_service.estimate import estimate_pose
from backend_service.frame_set import CameraObservation, FrameSet
from backend_service.pose_init import View, circular_mean, init_without_prior, pnp_candidate
from core.pose import PlanarPose
from tests.backend_service.pose_synth import ROBOT, example_site, make_frame_set, pose_error

SITE = example_site()
CAMS = sorted(SITE.cameras)
KP = SITE.robot_model(ROBOT).keypoints_base_m
TRUTH = PlanarPose(10.3, 5.7, -2.5)


def _views(fs: FrameSet) -> list[View]:
    return [View(SITE.camera(o.camera_id), o.keypoints_px, o.keypoint_scores)
            for o in fs.observations]


def test_pnp_candidate_per_view_is_exact_without_noise() -> None:
    for view in _views(make_frame_set(SITE, TRUTH, CAMS)):
        cand = pnp_candidate(view, KP)
        assert cand is not None
        dp, dth = pose_error(cand.pose, TRUTH)
        assert dp < 1e-4 and dth < 1e-4


def test_init_without_prior_combines_candidates_and_ignores_a_corrupted_view() -> None:
    fs = make_frame_set(SITE, TRUTH, CAMS, sigma_px=1.0, rng=np.random.default_rng(1))
    views = _views(fs)
    # one view's keypoints shuffled: its PnP candidate (if any) disagrees with the others
    bad = views[0]
    views[0] = View(bad.camera, bad.keypoints_px[::-1].copy(), bad.weights)
    init = init_without_prior(views, KP)
    assert init.pose is not None
    dp, dth = pose_error(init.pose, TRUTH)
    assert dp < 0.05 and dth < math.radians(3)


def test_circular_mean_wraps() -> None:
    assert abs(abs(circular_mean(np.array([math.pi - 0.1, -math.pi + 0.1]))) - math.pi) < 1e-12
    assert circular_mean(np.array([0.0, 1.0]), np.array([3.0, 1.0])) == pytest.approx(
        math.atan2(math.sin(1.0), 3 + math.cos(1.0)))


def test_too_few_keypoints_for_pnp() -> None:
    fs = make_frame_set(SITE, TRUTH, CAMS[:1])
    o = fs.observations[0]
    scores = np.zeros(12)
    scores[:3] = 1.0
    view = View(SITE.camera(o.camera_id), o.keypoints_px, scores)
    assert pnp_candidate(view, KP) is None


def _fs_with(uv: np.ndarray, scores: np.ndarray, cam: str = "cam_sw") -> FrameSet:
    return FrameSet.from_observations(ROBOT, [CameraObservation(cam, 5, uv, scores)])


def _mirrored_frame_set() -> FrameSet:
    """Keypoints of a robot *behind* cam_sw, projected without the front check: the only
    consistent pose lies behind the camera."""
    cam = SITE.camera("cam_sw")
    behind = PlanarPose(5.0, 1.0, 0.3)  # cam_sw is at (7, 3) looking towards +x +y
    T = behind.T()
    pc = cam.world_to_cam(KP @ T[:3, :3].T + T[:3, 3])
    assert np.all(pc[:, 2] < 0)
    xy = pc[:, :2] / pc[:, 2:3]
    uv = xy @ cam.K[:2, :2].T + cam.K[:2, 2]
    return _fs_with(uv, np.ones(12))


GOOD = make_frame_set(SITE, TRUTH, ["cam_sw"]).observations[0]


@pytest.mark.parametrize(
    ("name", "frame_set", "prior"),
    [
        ("nan keypoints", _fs_with(np.full((12, 2), np.nan), np.ones(12)), None),
        ("zero confidences", _fs_with(GOOD.keypoints_px, np.zeros(12)), TRUTH),
        ("unknown camera", _fs_with(GOOD.keypoints_px, np.ones(12), cam="cam_xx"), TRUTH),
        ("one valid keypoint", _fs_with(GOOD.keypoints_px, np.eye(12)[0]), TRUTH),
        ("wrong keypoint count", _fs_with(GOOD.keypoints_px[:5], np.ones(5)), TRUTH),
        ("empty frame-set", FrameSet.from_observations(ROBOT, []), TRUTH),
        ("unknown robot", FrameSet("nobody", 0, (GOOD,)), TRUTH),
        ("behind camera, no prior", _mirrored_frame_set(), None),
        ("behind camera, prior there", _mirrored_frame_set(), PlanarPose(5.0, 1.0, 0.3)),
        ("no prior, three keypoints",
         _fs_with(GOOD.keypoints_px, np.r_[np.ones(3), np.zeros(9)]), None),
        ("inf keypoints", _fs_with(np.full((12, 2), np.inf), np.ones(12)), TRUTH),
        ("nan prior and nan keypoints", _fs_with(np.full((12, 2), np.nan), np.ones(12)),
         PlanarPose(math.nan, 0.0, 0.0)),
    ],
)
def test_garbage_gives_no_estimate_never_an_exception(name: str, frame_set: FrameSet,
                                                      prior: PlanarPose | None) -> None:
    res = estimate_pose(frame_set, SITE, prior)
    assert not res.ok and res.estimate is None
    assert res.reason and "internal error" not in res.reason, res.reason


def test_garbage_view_next_to_a_good_one_is_dropped() -> None:
    good = make_frame_set(SITE, TRUTH, ["cam_ne", "cam_se"])
    junk = CameraObservation("cam_unknown", 5, np.full((12, 2), np.nan), np.ones(12))
    fs = FrameSet.from_observations(ROBOT, [*good.observations, junk])
    res = estimate_pose(fs, SITE, None)
    assert res.ok, res.reason
    assert set(res.estimate.camera_ids) == {"cam_ne", "cam_se"}
