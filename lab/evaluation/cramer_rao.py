"""Cramer-Rao bound of the planar pose from multi-view keypoints, and camera-placement planning.

With i.i.d. Gaussian pixel noise of std ``sigma_px`` on every visible keypoint, the Fisher
information of (x, y, theta) is ``J^T J / sigma_px^2`` with ``J`` (2K, 3) the Jacobian of the
projections at the true pose (the same CasADi formulation the solver uses). Its inverse bounds
the covariance of any unbiased estimator; the Monte-Carlo test shows the solver attains it.

Visibility: a keypoint counts when it lies in front of the camera and inside its image
(self-occlusion of the robot body is not modelled).

Planning: :func:`placement_report` evaluates the bound over a grid of robot poses for a set of
cameras; :func:`greedy_camera_selection` picks, from candidate cameras, the ones that minimize
the mean position standard deviation over those poses.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from backend_service.pose_solver import get_problem
from core.camera import CameraModel
from core.pose import PlanarPose
from core.site import RobotModel, Site


def fisher_information(cameras: Sequence[CameraModel], keypoints_base_m: np.ndarray,
                       true_pose: PlanarPose, sigma_px: float) -> np.ndarray:
    """(3, 3) Fisher information of (x [m], y [m], theta [rad]) at ``true_pose`` (world frame)
    for keypoints visible in ``cameras`` with pixel noise ``sigma_px``."""
    kp = np.asarray(keypoints_base_m, dtype=np.float64)
    T = true_pose.T()
    pts = kp @ T[:3, :3].T + T[:3, 3]
    uv_all, w_all = [], []
    for cam in cameras:
        uv, depth = cam.project(pts)
        visible = (depth > 0) & cam.in_image(uv)
        uv_all.append(np.where(visible[:, None], uv, 0.0))
        w_all.append(visible.astype(float))
    if not cameras:
        return np.zeros((3, 3))
    problem = get_problem(list(cameras), kp, 3, "none")
    p = problem.pack(np.stack(uv_all), np.stack(w_all))
    _, J, _ = problem.evaluate(true_pose.as_array(), p)
    return J.T @ J / float(sigma_px) ** 2


def cramer_rao_bound(site: Site, robot_model: RobotModel, true_pose: PlanarPose,
                     camera_ids: Sequence[str], sigma_px: float) -> np.ndarray:
    """(3, 3) lower bound on the covariance of (x, y, theta) estimated from ``camera_ids`` of
    ``site`` at ``true_pose`` with ``sigma_px`` pixel noise; ``inf`` on the diagonal where the
    pose is not observable (too few visible keypoints)."""
    cams = [site.camera(c) for c in sorted(camera_ids)]
    F = fisher_information(cams, robot_model.keypoints_base_m, true_pose, sigma_px)
    if np.linalg.matrix_rank(F, tol=1e-12 * max(np.abs(F).max(), 1e-300)) < 3:
        return np.diag([np.inf, np.inf, np.inf])
    return np.linalg.inv(F)


@dataclasses.dataclass(frozen=True, eq=False)
class PlacementReport:
    """Bound over a set of poses: ``std_position_m`` (P,) = sqrt(trace of the xy block),
    ``std_theta_rad`` (P,), ``cameras_seeing`` (P,) number of cameras with >= 4 visible
    keypoints. Unobservable poses have ``inf`` std."""

    poses: tuple[PlanarPose, ...]
    std_position_m: np.ndarray
    std_theta_rad: np.ndarray
    cameras_seeing: np.ndarray

    @property
    def mean_std_position_m(self) -> float:
        finite = np.isfinite(self.std_position_m)
        return float(self.std_position_m[finite].mean()) if finite.all() else float("inf")


def placement_report(cameras: Sequence[CameraModel], robot_model: RobotModel,
                     poses: Sequence[PlanarPose], sigma_px: float = 2.0) -> PlacementReport:
    """Evaluate the Cramer-Rao bound of ``cameras`` at every pose of ``poses`` (world frame)."""
    kp = robot_model.keypoints_base_m
    std_p, std_t, seeing = [], [], []
    for pose in poses:
        T = pose.T()
        pts = kp @ T[:3, :3].T + T[:3, 3]
        vis_cams = []
        for cam in cameras:
            uv, depth = cam.project(pts)
            if int(np.sum((depth > 0) & cam.in_image(uv))) >= 4:
                vis_cams.append(cam)
        seeing.append(len(vis_cams))
        F = fisher_information(vis_cams, kp, pose, sigma_px) if vis_cams else np.zeros((3, 3))
        if np.linalg.matrix_rank(F, tol=1e-12 * max(np.abs(F).max(), 1e-300)) < 3:
            std_p.append(np.inf)
            std_t.append(np.inf)
            continue
        C = np.linalg.inv(F)
        std_p.append(float(np.sqrt(C[0, 0] + C[1, 1])))
        std_t.append(float(np.sqrt(C[2, 2])))
    return PlacementReport(tuple(poses), np.array(std_p), np.array(std_t), np.array(seeing))


def greedy_camera_selection(candidates: Sequence[CameraModel], robot_model: RobotModel,
                            poses: Sequence[PlanarPose], count: int,
                            sigma_px: float = 2.0) -> list[str]:
    """Ids of ``count`` cameras from ``candidates`` chosen greedily to minimize the mean
    position std of the bound over ``poses`` (unobservable poses count as 100 m)."""
    chosen: list[CameraModel] = []
    remaining = list(candidates)
    for _ in range(min(count, len(remaining))):
        def score(cam: CameraModel) -> float:
            rep = placement_report([*chosen, cam], robot_model, poses, sigma_px)
            return float(np.mean(np.minimum(rep.std_position_m, 100.0)))

        best = min(remaining, key=score)
        chosen.append(best)
        remaining.remove(best)
    return [c.camera_id for c in chosen]
