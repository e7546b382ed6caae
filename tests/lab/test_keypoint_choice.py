"""The keypoint choice report: per-keypoint information, self-occlusion, the heading budget."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from backend_service.covariance import ErrorModel
from core.pose import PlanarPose
from lab.evaluate import main as evaluate_main
from lab.evaluation.cramer_rao import fisher_information
from lab.evaluation.keypoint_choice import (
    base_candidates,
    heading_budget,
    keypoint_choice,
    mirror_groups,
    point_information,
    stop_poses,
    visible_keypoints,
)
from simulation.scenario import load_scenario

SCENARIO = load_scenario()
SITE = SCENARIO.site
MODEL = SITE.robot_model(SCENARIO.robot_id)
CAMERAS = [SITE.camera(c) for c in sorted(SITE.cameras)]
POSES = stop_poses([(w.x, w.y, w.theta) for w in SCENARIO.waypoints.values()], headings=4)
KP = MODEL.keypoints_base_m
Z_TOP = float(KP[:, 2].max())


def test_summed_point_information_is_the_solvers_fisher_information() -> None:
    """Top-rim keypoints seen from above by every camera that sees them: the per-point sum is
    the CasADi formulation's J^T J / sigma^2 (an independent Jacobian)."""
    top = KP[KP[:, 2] >= Z_TOP - 1e-9]
    pose = POSES[0]
    seeing = [c for c in CAMERAS if visible_keypoints(c, pose.T(), top, MODEL.footprint_radius_m,
                                             Z_TOP).all()]
    assert len(seeing) >= 2
    ours = point_information(seeing, top, pose, 0.7, MODEL.footprint_radius_m, Z_TOP).sum(0)
    solver = fisher_information(seeing, top, pose, 0.7)
    assert np.allclose(ours, solver, rtol=1e-4, atol=1e-6 * np.abs(solver).max())


def test_the_base_hides_its_far_side() -> None:
    """A bottom keypoint faces away from a camera on the other side: hidden; the top rim stays
    visible from a ceiling camera."""
    cam = CAMERAS[0]
    c = cam.T_world_cam[:3, 3]
    # robot 3 m in front of the camera's foot point, facing the camera (front towards it)
    look = cam.T_world_cam[:3, 2][:2] / np.linalg.norm(cam.T_world_cam[:3, 2][:2])
    x, y = c[:2] + 3.0 * look
    facing = PlanarPose(float(x), float(y), math.atan2(-look[1], -look[0]))
    away = dataclasses.replace(facing, theta=facing.theta + math.pi)
    names = list(MODEL.keypoint_names)
    front_bottom, front_top = names.index("front_bottom"), names.index("front_top")
    radius = MODEL.footprint_radius_m
    vis_facing = visible_keypoints(cam, facing.T(), KP, radius, Z_TOP)
    vis_away = visible_keypoints(cam, away.T(), KP, radius, Z_TOP)
    assert vis_facing[front_bottom] and not vis_away[front_bottom]
    assert vis_facing[front_top] and vis_away[front_top]


def test_leave_one_out_and_greedy_additions_are_consistent() -> None:
    choice = keypoint_choice(CAMERAS, MODEL, POSES, sigma_px=0.5, add=3)
    assert choice.poses == len(POSES)
    # removing information never lowers the bound; adding never raises it
    assert all(theta >= choice.theta_deg - 1e-12 for _, theta in choice.leave_one_out)
    added = [theta for _, _, theta in choice.greedy]
    assert added[0] <= choice.theta_deg and all(b <= a for a, b in itertools.pairwise(added))
    # the bound scales with sigma
    double = keypoint_choice(CAMERAS, MODEL, POSES, sigma_px=1.0, add=0)
    assert double.theta_deg == pytest.approx(2 * choice.theta_deg, rel=1e-9)
    # candidates lie on the base's cylinder and never duplicate a model keypoint
    for cand in base_candidates(MODEL):
        p = np.array(cand.xyz_m)
        assert np.hypot(p[0], p[1]) == pytest.approx(MODEL.footprint_radius_m)
        assert np.min(np.linalg.norm(KP - p, axis=1)) >= 0.03


def test_pairs_add_each_candidate_with_its_mirror_image() -> None:
    """``pairs``: every greedy step adds a left/right mirror pair (what a network trained on
    mirrored crops needs); a pair lowers the bound at least as much as its better half alone."""
    cands = base_candidates(MODEL)
    groups = mirror_groups(cands)
    assert sorted(i for g in groups for i in g) == list(range(len(cands)))
    for g in groups:
        a = np.array(cands[g[0]].xyz_m)
        if len(g) == 1:  # on the x axis
            assert abs(a[1]) < 1e-9
        else:
            assert np.allclose(np.array(cands[g[1]].xyz_m), a * [1, -1, 1])
    single = keypoint_choice(CAMERAS, MODEL, POSES, sigma_px=0.5, add=1)
    paired = keypoint_choice(CAMERAS, MODEL, POSES, sigma_px=0.5, add=4, pairs=True)
    assert len(paired.greedy) == 4
    for (_, p, b1), (_, q, b2) in (paired.greedy[:2], paired.greedy[2:]):
        assert np.allclose(np.array(q), np.array(p) * [1, -1, 1]) and b1 == b2
    assert paired.greedy[1][2] <= single.greedy[0][2]
    assert paired.greedy[3][2] <= paired.greedy[1][2]


def test_heading_budget_scales_with_each_source() -> None:
    base = ErrorModel(0.3, 0.01, 0.01, 0.1)
    b1 = heading_budget(CAMERAS, MODEL, POSES, sigma_px=0.5, errors=base)
    b2 = heading_budget(CAMERAS, MODEL, POSES, sigma_px=1.0, errors=ErrorModel(0.6, 0.02,
                                                                                0.02, 0.2))
    assert b2.keypoint_noise_deg == pytest.approx(2 * b1.keypoint_noise_deg, rel=1e-6)
    assert b2.detection_shift_deg == pytest.approx(2 * b1.detection_shift_deg, rel=1e-6)
    assert b2.calibration_deg == pytest.approx(2 * b1.calibration_deg, rel=1e-6)
    none = heading_budget(CAMERAS, MODEL, POSES, sigma_px=0.5, errors=ErrorModel())
    assert none.calibration_deg == 0.0 and none.detection_scale_deg == 0.0
    # averaging removes the per-frame parts only
    assert b1.calibration_deg < b1.averaged_deg < b1.repeated_deg


def test_cli_prints_both_reports(capsys: pytest.CaptureFixture[str]) -> None:
    assert evaluate_main(["keypoint-choice", "--add", "2", "--sigma-px", "0.4", "--pairs"]) == 0
    out = capsys.readouterr().out
    assert "without one keypoint" in out and "heading error budget" in out
    assert evaluate_main(["keypoint-choice", "--sigma-px", "0"]) == 2
