"""Cramer-Rao bound and camera-placement planning."""

from __future__ import annotations

import numpy as np

from backend_service.projection import StackedCameras, numeric_jacobian
from core.pose import PlanarPose
from lab.evaluation.cramer_rao import (
    cramer_rao_bound,
    greedy_camera_selection,
    placement_report,
)
from tests.backend_service.pose_synth import ROBOT, example_site, project_pose

SITE = example_site()
MODEL = SITE.robot_model(ROBOT)
CAMS = sorted(SITE.cameras)
POSE = PlanarPose(10.0, 6.2, 0.4)


def test_bound_matches_numeric_jacobian_and_shrinks_with_cameras() -> None:
    crb4 = cramer_rao_bound(SITE, MODEL, POSE, CAMS, 2.0)
    crb2 = cramer_rao_bound(SITE, MODEL, POSE, CAMS[:2], 2.0)
    crb1 = cramer_rao_bound(SITE, MODEL, POSE, CAMS[:1], 2.0)
    assert np.all(np.diag(crb4) < np.diag(crb2)) and np.all(np.diag(crb2) < np.diag(crb1))
    # independent check: numpy central differences of the same projection
    cams = [SITE.camera(c) for c in CAMS]
    uv = np.stack([project_pose(SITE, POSE, c)[0] for c in CAMS])
    w = np.stack([project_pose(SITE, POSE, c)[1] for c in CAMS]).astype(float)
    _, J = numeric_jacobian(StackedCameras.from_cameras(cams), MODEL.keypoints_base_m,
                            POSE.as_array(), uv, w)
    assert np.allclose(np.linalg.inv(J.T @ J / 4.0), crb4, rtol=1e-5)
    # the bound scales with sigma^2
    assert np.allclose(cramer_rao_bound(SITE, MODEL, POSE, CAMS, 4.0), 4 * crb4)


def test_unobservable_pose_gives_infinite_bound() -> None:
    crb = cramer_rao_bound(SITE, MODEL, PlanarPose(30.0, 30.0, 0.0), CAMS[:1], 2.0)
    assert np.all(np.isinf(np.diag(crb)))


def test_placement_planning_prefers_spread_cameras() -> None:
    poses = [PlanarPose(x, y, t) for x in (9.5, 10.5) for y in (5.5, 6.5) for t in (0.0, 2.0)]
    cams = [SITE.camera(c) for c in CAMS]
    rep = placement_report(cams, MODEL, poses, 2.0)
    assert rep.std_position_m.shape == (8,) and np.all(rep.cameras_seeing == 4)
    assert rep.mean_std_position_m < 0.05
    chosen = greedy_camera_selection(cams, MODEL, poses, 2, 2.0)
    assert len(set(chosen)) == 2
    # the greedy pair is at least as good as any other pair
    best = placement_report([SITE.camera(c) for c in chosen], MODEL, poses).mean_std_position_m
    for i in range(4):
        for j in range(i + 1, 4):
            other = placement_report([cams[i], cams[j]], MODEL, poses).mean_std_position_m
            assert best <= other + 1e-12 or set(chosen) != {CAMS[i], CAMS[j]}
