"""Single-camera bearing-only heuristic and multi-frame averaging."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from backend_service.estimate import SolverConfig, estimate_pose
from backend_service.multi_frame import MultiFrameAverager
from backend_service.single_camera import apply_single_camera_heuristic, camera_ground_xy
from core.pose import PlanarPose
from tests.backend_service.pose_synth import example_site, make_frame_set, pose_error, project_pose

SITE = example_site()
FAR_CAM = "cam_sw"  # at (7, 3, 2.5)
FAR_POSE = PlanarPose(11.6, 7.4, 1.0)  # ~6.4 m away


def test_far_pose_is_seen_by_the_camera() -> None:
    _, ok = project_pose(SITE, FAR_POSE, FAR_CAM)
    assert ok.sum() >= 10


def test_heuristic_keeps_depth_and_orientation_and_updates_bearing() -> None:
    cam = SITE.camera(FAR_CAM)
    c = camera_ground_xy(cam)
    prior = FAR_POSE
    jumped = PlanarPose(prior.x + 0.8, prior.y + 0.5, prior.theta + 0.6)
    out = apply_single_camera_heuristic(cam, prior, jumped, math.radians(10), 0.15)
    assert out.applied
    assert out.pose.theta == prior.theta
    d_prior = math.hypot(prior.x - c[0], prior.y - c[1])
    assert math.hypot(out.pose.x - c[0], out.pose.y - c[1]) == np.float64(d_prior) or \
        abs(math.hypot(out.pose.x - c[0], out.pose.y - c[1]) - d_prior) < 1e-9
    bearing = math.atan2(jumped.y - c[1], jumped.x - c[0])
    assert abs(math.atan2(out.pose.y - c[1], out.pose.x - c[0]) - bearing) < 1e-12
    small = PlanarPose(prior.x + 0.02, prior.y, prior.theta + 0.01)
    assert not apply_single_camera_heuristic(cam, prior, small, math.radians(10), 0.15).applied


def test_single_far_camera_heuristic_limits_the_jump() -> None:
    rng = np.random.default_rng(5)
    with_h, without_h, applied = [], [], 0
    for _ in range(60):
        prior = PlanarPose(FAR_POSE.x + rng.normal(0, 0.03), FAR_POSE.y + rng.normal(0, 0.03),
                           FAR_POSE.theta + rng.normal(0, 0.02))
        fs = make_frame_set(SITE, FAR_POSE, [FAR_CAM], sigma_px=6.0, rng=rng)
        a = estimate_pose(fs, SITE, prior, SolverConfig(single_camera="paper"))
        b = estimate_pose(fs, SITE, prior, SolverConfig(single_camera="plain"))
        assert a.ok and b.ok, (a.reason, b.reason)
        assert "single_camera" in a.estimate.flags
        if "lateral_only" in a.estimate.flags:
            applied += 1
            # depth and orientation stayed at the prior's
            c = camera_ground_xy(SITE.camera(FAR_CAM))
            d = math.hypot(a.pose.x - c[0], a.pose.y - c[1])
            assert abs(d - math.hypot(prior.x - c[0], prior.y - c[1])) < 1e-9
            assert a.pose.theta == prior.theta
        with_h.append(pose_error(a.pose, FAR_POSE))
        without_h.append(pose_error(b.pose, FAR_POSE))
    w, wo = np.array(with_h), np.array(without_h)
    assert applied >= 10
    assert w[:, 0].mean() < 0.9 * wo[:, 0].mean(), (w[:, 0].mean(), wo[:, 0].mean())
    assert w[:, 1].mean() < 0.9 * wo[:, 1].mean(), (w[:, 1].mean(), wo[:, 1].mean())
    assert w[:, 0].max() < wo[:, 0].max()


def test_multi_frame_average_of_static_robot() -> None:
    rng = np.random.default_rng(9)
    truth = PlanarPose(10.0, 6.0, math.pi - 0.01)  # yaw near the wrap-around
    avg = MultiFrameAverager(5, frame_correlation=0.0)  # independent draws per frame
    singles, out = [], None
    for i in range(5):
        fs = make_frame_set(SITE, truth, ["cam_ne", "cam_sw"], 3.0, rng, stamp_ns=10**9 + i)
        res = estimate_pose(fs, SITE, truth, SolverConfig(robust_loss="none"))
        assert res.ok
        singles.append(res)
        out = avg.add(res)
        assert (out is None) == (i < 4)
    assert out is not None and "multi_frame" in out.estimate.flags
    assert abs(out.pose.theta) > 3.0  # circular mean, not the arithmetic one
    mean_x = np.mean([r.pose.x for r in singles])
    assert out.pose.x == np.float64(mean_x) or abs(out.pose.x - mean_x) < 1e-12
    assert np.trace(out.estimate.covariance) < np.trace(singles[-1].estimate.covariance)
    # a jump (robot moved) restarts the window
    moved = dataclasses.replace(singles[-1], pose=PlanarPose(11.0, 6.0, 0.0))
    assert avg.add(moved) is None and len(avg) == 1
    avg.reset()
    assert len(avg) == 0
