"""The pose solver weights keypoints by the detector's per-keypoint pixel sigmas when a camera
sends them: w = (floor / max(sigma, floor))^2 with ``SolverConfig.sigma_floor_px``.

Frame-sets are exact projections of the example site's robot keypoints (through the real
camera model, :mod:`tests.backend_service.pose_synth`) for two cameras, with three keypoints of
one camera pushed ~18 px off: weighted by scores alone they bias the pose by centimetres; with
sigmas that flag them (50 px against 1 px) the pose is back within a millimetre or so."""

from __future__ import annotations

import math

import numpy as np
import pytest

from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.frame_set import CameraObservation, FrameSet
from core.pose import PlanarPose
from protocol.messages import Detection
from tests.backend_service.pose_synth import ROBOT, example_site, make_frame_set, pose_error

SITE = example_site()
CAMS = ("cam_ne", "cam_sw")
M = SITE.robot_model(ROBOT).keypoints_base_m.shape[0]
BAD = np.array([1, 4, 7])  # corrupted keypoints of the first camera
SHIFT_PX = np.array([15.0, -10.0])
GOOD_SIGMA, BAD_SIGMA = 1.0, 50.0
TRUTHS = (PlanarPose(10.3, 5.4, -2.88), PlanarPose(9.2, 6.6, 0.7), PlanarPose(10.9, 5.1, 2.1))


def _observations(truth: PlanarPose) -> tuple[np.ndarray, np.ndarray]:
    """(2, M, 2) exact keypoints of :data:`CAMS` at ``truth``, with :data:`BAD` of the first
    camera shifted by :data:`SHIFT_PX`, and (2, M) visibility."""
    fs = make_frame_set(SITE, truth, list(CAMS))
    uv = np.stack([np.array(o.keypoints_px, dtype=np.float64) for o in fs.observations])
    seen = np.stack([np.asarray(o.keypoint_scores) > 0 for o in fs.observations])
    assert [o.camera_id for o in fs.observations] == list(CAMS)
    assert seen.all(), "every keypoint must be visible in both cameras for this test"
    uv[0, BAD] += SHIFT_PX
    return uv, seen


def _frame_set(uv: np.ndarray, sigmas: list[np.ndarray | None],
               scores: tuple[float, float] = (0.9, 0.9)) -> FrameSet:
    obs = [CameraObservation(cid, 1_000_000_000, uv[i], np.full(M, scores[i]),
                             keypoint_sigmas_px=sigmas[i])
           for i, cid in enumerate(CAMS)]
    return FrameSet.from_observations(ROBOT, obs)


def _flag_sigmas() -> list[np.ndarray]:
    """1 px for good keypoints, 50 px for the corrupted ones."""
    first = np.full(M, GOOD_SIGMA)
    first[BAD] = BAD_SIGMA
    return [first, np.full(M, GOOD_SIGMA)]


def _solve(fs: FrameSet, truth: PlanarPose, config: SolverConfig | None = None,
           with_prior: bool = True) -> tuple[float, float, PlanarPose]:
    prior = PlanarPose(truth.x + 0.2, truth.y - 0.15, truth.theta + 0.2) if with_prior else None
    # least squares (no robust loss): the weighting alone must handle the corruption
    res = estimate_pose(fs, SITE, prior, config or SolverConfig(robust_loss="none"))
    assert res.ok, res.reason
    dp, dth = pose_error(res.pose, truth)
    return dp, math.degrees(dth), res.pose


@pytest.mark.parametrize("with_prior", [True, False], ids=["prior", "pnp"])
@pytest.mark.parametrize("truth", TRUTHS, ids=[f"pose{i}" for i in range(len(TRUTHS))])
def test_sigmas_down_weight_corrupted_keypoints(truth: PlanarPose, with_prior: bool) -> None:
    uv, _ = _observations(truth)
    dp_score, dth_score, _ = _solve(_frame_set(uv, [None, None]), truth, with_prior=with_prior)
    dp_sig, dth_sig, _ = _solve(_frame_set(uv, _flag_sigmas()), truth, with_prior=with_prior)
    # the corruption matters when weighting by score ...
    assert dp_score > 0.01 or dth_score > 0.2, (dp_score, dth_score)
    # ... and hardly at all when the sigmas flag it
    assert dp_sig < 0.01 and dth_sig < 0.2, (dp_sig, dth_sig)
    assert dp_sig < 0.25 * dp_score
    assert dth_sig < dth_score


def test_exact_keypoints_with_sigmas_give_the_exact_pose() -> None:
    truth = TRUTHS[0]
    uv, _ = _observations(truth)
    uv[0, BAD] -= SHIFT_PX  # undo the corruption
    dp, dth, _ = _solve(_frame_set(uv, _flag_sigmas()), truth)
    assert dp < 1e-4 and dth < 1e-3


def test_uniform_sigmas_weigh_like_uniform_scores() -> None:
    """Every keypoint with the same sigma: the same (uniform) weighting as equal scores, so
    the same pose, corruption included."""
    truth = TRUTHS[1]
    uv, _ = _observations(truth)
    _, _, by_score = _solve(_frame_set(uv, [None, None]), truth)
    _, _, by_sigma = _solve(_frame_set(uv, [np.full(M, 7.0), np.full(M, 7.0)]), truth)
    assert pose_error(by_score, by_sigma)[0] < 1e-6
    assert pose_error(by_score, by_sigma)[1] < 1e-6


def test_sigmas_below_the_floor_weigh_one() -> None:
    """Sigmas of 0.1 px and 1 px are both below the 2 px floor: the same weights, the same
    pose; raising the floor above the bad sigma makes all weights 1 (as uniform scores)."""
    truth = TRUTHS[2]
    uv, _ = _observations(truth)
    tiny = [np.where(s == GOOD_SIGMA, 0.1, s) for s in _flag_sigmas()]
    _, _, a = _solve(_frame_set(uv, _flag_sigmas()), truth)
    _, _, b = _solve(_frame_set(uv, tiny), truth)
    assert max(pose_error(a, b)) < 1e-6
    _, _, by_score = _solve(_frame_set(uv, [None, None]), truth)
    _, _, floored = _solve(_frame_set(uv, _flag_sigmas()), truth,
                           SolverConfig(sigma_floor_px=100.0, robust_loss="none"))
    assert max(pose_error(by_score, floored)) < 1e-6
    assert pose_error(a, floored)[0] > 0.01  # and that is the biased, score-like pose


def test_one_camera_with_sigmas_and_one_without() -> None:
    """Mixing senders: the camera without sigmas is weighted by score (0.9), the other by
    sigma; the corrupted camera's sigmas still flag its bad keypoints."""
    truth = TRUTHS[0]
    uv, _ = _observations(truth)
    dp_score, _, _ = _solve(_frame_set(uv, [None, None]), truth)
    dp, dth, _ = _solve(_frame_set(uv, [_flag_sigmas()[0], None]), truth)
    assert dp < 0.01 and dth < 0.2 and dp < 0.25 * dp_score


@pytest.mark.parametrize("bad_shape", [(M - 1,), (M + 1,), (M, 1), (0,)])
def test_sigmas_of_the_wrong_shape_fall_back_to_scores(bad_shape: tuple[int, ...]) -> None:
    truth = TRUTHS[0]
    uv, _ = _observations(truth)
    _, _, by_score = _solve(_frame_set(uv, [None, None]), truth)
    dp, dth, pose = _solve(_frame_set(uv, [np.ones(bad_shape), np.ones(bad_shape)]), truth)
    assert max(pose_error(by_score, pose)) < 1e-6
    assert dp < 0.1 and dth < 2.0  # still a sensible (score-weighted) estimate


def test_wrong_shape_on_one_camera_only_keeps_the_other_cameras_sigmas() -> None:
    truth = TRUTHS[1]
    uv, _ = _observations(truth)
    # the corrupted camera's sigmas are unusable: it falls back to its scores (weight 0.9),
    # the other camera keeps its sigmas (1 px, under the floor: weight 1)
    _, _, reference = _solve(_frame_set(uv, [None, None], scores=(0.9, 1.0)), truth)
    dp, _, mixed = _solve(_frame_set(uv, [np.ones(M - 2), np.full(M, GOOD_SIGMA)]), truth)
    assert max(pose_error(reference, mixed)) < 1e-6
    assert dp > 0.01  # the corrupted keypoints are not down-weighted: the bias is back


def test_non_finite_sigma_drops_that_keypoint() -> None:
    """A NaN sigma makes the weight non-finite: that keypoint is ignored like a missing one,
    so NaN on the corrupted keypoints removes them."""
    truth = TRUTHS[2]
    uv, _ = _observations(truth)
    first = np.full(M, GOOD_SIGMA)
    first[BAD] = np.nan
    dp, dth, _ = _solve(_frame_set(uv, [first, np.full(M, GOOD_SIGMA)]), truth)
    assert dp < 1e-3 and dth < 0.02


def test_scores_below_the_threshold_still_drop_keypoints_with_sigmas() -> None:
    """Sigmas replace the score as the weight, not as the gate: a keypoint below the site's
    min score is dropped even with a small sigma."""
    truth = TRUTHS[0]
    uv, _ = _observations(truth)
    fs = _frame_set(uv, [np.full(M, GOOD_SIGMA), np.full(M, GOOD_SIGMA)])
    low = np.full(M, 0.9)
    low[BAD] = 0.05  # below min_keypoint_score 0.3
    first = fs.observations[0]
    fs = FrameSet.from_observations(ROBOT, [
        CameraObservation(first.camera_id, first.stamp_ns, first.keypoints_px, low,
                          keypoint_sigmas_px=first.keypoint_sigmas_px),
        fs.observations[1]])
    dp, dth, _ = _solve(fs, truth)
    assert dp < 1e-3 and dth < 0.02


def test_sigmas_travel_from_the_detection_to_the_observation() -> None:
    sig = np.linspace(0.5, 6.0, M)
    det = Detection(np.array([0.0, 0.0, 10.0, 10.0]), 0.9, np.zeros((M, 2)), np.full(M, 0.9),
                    "", sig)
    obs = CameraObservation.from_detection("cam_ne", 5, det)
    assert obs.keypoint_sigmas_px is not None
    np.testing.assert_array_equal(obs.keypoint_sigmas_px, sig)
    plain = Detection(np.array([0.0, 0.0, 10.0, 10.0]), 0.9, np.zeros((M, 2)),
                      np.full(M, 0.9))
    assert CameraObservation.from_detection("cam_ne", 5, plain).keypoint_sigmas_px is None


def test_default_floor_is_one_and_a_half_pixels() -> None:
    assert SolverConfig().sigma_floor_px == 1.5


@pytest.mark.parametrize("floor", [0.0, -1.0, math.nan, math.inf])
def test_bad_sigma_floor_is_a_value_error(floor: float) -> None:
    with pytest.raises(ValueError, match="sigma_floor_px"):
        SolverConfig(sigma_floor_px=floor)
