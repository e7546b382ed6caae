"""The paper's bearing-only heuristic for single-camera estimates (Sec. III-B).

Seen by one camera, and far from it, the robot's narrow body (~35 cm) gives a good bearing but a
weak depth and orientation. When a single-camera solve changes the orientation by more than
``d_theta`` or the distance to the camera by more than ``d_depth`` relative to the prior, the
heuristic keeps the prior's orientation and its distance to the camera, and updates only the
translation orthogonal to the viewing direction: the robot is moved along the circle of constant
distance around the camera to the bearing that best explains the keypoints (a 1-D fit), so the
well-observed bearing is used and the poorly observed depth/orientation are not.

Distances and bearings are horizontal (measured on the floor plane from the point below the
camera's optical centre).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from core.camera import CameraModel
from core.geometry import angle_diff, wrap_angle
from core.pose import PlanarPose

#: (B, 3) poses -> (B, K) weighted residuals in px (e.g. projection.weighted_residuals).
ResidualFn = Callable[[np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class HeuristicOutcome:
    """``pose``: the pose to report; ``applied``: the heuristic replaced depth and orientation;
    ``d_theta_rad`` / ``d_depth_m``: the solve's change relative to the prior."""

    pose: PlanarPose
    applied: bool
    d_theta_rad: float
    d_depth_m: float


def camera_ground_xy(camera: CameraModel) -> np.ndarray:
    """(2,) the optical centre projected onto the floor, world frame, metres."""
    return camera.position_world[:2].copy()


def apply_single_camera_heuristic(
    camera: CameraModel,
    prior: PlanarPose,
    estimate: PlanarPose,
    max_dtheta_rad: float,
    max_ddepth_m: float,
    residual_fn: ResidualFn | None = None,
) -> HeuristicOutcome:
    """Bearing-only check of a single-camera ``estimate`` against ``prior`` (both world frame).

    When ``|d_theta| > max_dtheta_rad`` or ``|d_depth| > max_ddepth_m`` the result keeps the
    prior's orientation and distance to the camera; the bearing comes from ``estimate`` and, if
    ``residual_fn`` is given, is refined by a 1-D Gauss-Newton fit of the reprojection errors.
    """
    c_xy = camera_ground_xy(camera)
    d_prior = float(np.hypot(prior.x - c_xy[0], prior.y - c_xy[1]))
    d_est = float(np.hypot(estimate.x - c_xy[0], estimate.y - c_xy[1]))
    d_theta = angle_diff(estimate.theta, prior.theta)
    d_depth = d_est - d_prior
    if abs(d_theta) <= max_dtheta_rad and abs(d_depth) <= max_ddepth_m:
        return HeuristicOutcome(estimate, False, d_theta, d_depth)
    bearing = math.atan2(estimate.y - c_xy[1], estimate.x - c_xy[0])
    if residual_fn is not None:
        bearing = _refine_bearing(residual_fn, c_xy, d_prior, prior.theta, bearing)
    pose = PlanarPose(float(c_xy[0] + d_prior * math.cos(bearing)),
                      float(c_xy[1] + d_prior * math.sin(bearing)), wrap_angle(prior.theta))
    return HeuristicOutcome(pose, True, d_theta, d_depth)


def _refine_bearing(residual_fn: ResidualFn, c_xy: np.ndarray, distance_m: float,
                    theta_rad: float, bearing0: float, iterations: int = 8) -> float:
    def poses(b: np.ndarray) -> np.ndarray:
        return np.stack([c_xy[0] + distance_m * np.cos(b), c_xy[1] + distance_m * np.sin(b),
                         np.full_like(b, theta_rad)], axis=1)

    def cost(b: float) -> float:
        return float(np.sum(residual_fn(poses(np.array([b])))[0] ** 2))

    b = bearing0
    h = 1e-6
    current = cost(b)
    for _ in range(iterations):
        r = residual_fn(poses(np.array([b, b + h, b - h])))
        J = (r[1] - r[2]) / (2 * h)
        jtj = float(J @ J)
        if jtj <= 0.0 or not np.isfinite(jtj):
            break
        step = -float(J @ r[0]) / jtj
        # Halve the step until the cost does not grow (the clamped depth makes far steps odd).
        for _ in range(10):
            trial = cost(b + step)
            if np.isfinite(trial) and trial <= current:
                break
            step *= 0.5
        else:
            break
        b, current = b + step, trial
        if abs(step) < 1e-10:
            break
    return b
