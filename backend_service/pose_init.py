"""Initialization of the pose solve, both of the paper's ways (Sec. III-B).

(i) From a prior (the robot's current pose estimate or odometry in the map frame):
:func:`init_from_prior`.

(ii) With no prior (kidnapped robot): :func:`init_without_prior` runs PnP per camera view with
at least ``min_keypoints`` keypoints (OpenCV SQPnP inside RANSAC, EPnP as fallback), transforms
each candidate to the world with ``T_world_cam``, rejects physically impossible candidates
(keypoints behind the camera, a robot that is not upright: the mirrored/flipped PnP solutions,
a base far above or below the floor), projects the rest onto the ground plane and combines the
candidates that agree with the best-supported one: weighted mean position, weighted circular
mean yaw, weights = inlier keypoints over *all* views.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Sequence
from typing import Final

import cv2
import numpy as np

from core.camera import CameraModel
from core.geometry import angle_diff, se2_from_matrix, wrap_angle
from core.pose import PlanarPose

log = logging.getLogger(__name__)

#: A candidate whose base z axis leans more than this from world up is not a ground robot
#: (PnP's mirrored / flipped solutions land here).
MAX_TILT_RAD: Final = math.radians(30.0)
#: A candidate base further than this from the floor (z = 0) is rejected.
MAX_HEIGHT_M: Final = 0.5
#: Candidates within these of the best one are averaged with it.
AGREE_XY_M: Final = 0.3
AGREE_YAW_RAD: Final = math.radians(20.0)


@dataclasses.dataclass(frozen=True, eq=False)
class View:
    """One camera's observation prepared for a solve: ``keypoints_px`` (M, 2) distorted pixels,
    ``weights`` (M,) >= 0 (0 = missing or below the score threshold)."""

    camera: CameraModel
    keypoints_px: np.ndarray
    weights: np.ndarray

    @functools.cached_property
    def valid(self) -> np.ndarray:
        """(M,) bool: usable keypoints (computed once per view)."""
        return (self.weights > 0) & np.all(np.isfinite(self.keypoints_px), axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class PoseCandidate:
    """A PnP candidate of one view: ``T_world_robot`` (4, 4), its ground projection ``pose``,
    ``inliers`` (keypoints over all views within the inlier threshold of the planar pose)."""

    camera_id: str
    T_world_robot: np.ndarray
    pose: PlanarPose
    inliers: int = 0
    median_error_px: float = math.inf


@dataclasses.dataclass(frozen=True, eq=False)
class InitResult:
    """Initialization outcome: ``pose`` (None on failure, with ``reason``), the best full
    ``T_world_robot`` (4, 4) for the 6-DoF variant, and every accepted candidate."""

    pose: PlanarPose | None
    T_world_robot: np.ndarray | None = None
    candidates: tuple[PoseCandidate, ...] = ()
    reason: str = ""


def init_from_prior(prior: PlanarPose) -> np.ndarray:
    """(3,) start vector (x, y, theta) from a prior pose in the world frame."""
    return np.array([prior.x, prior.y, wrap_angle(prior.theta)])


def circular_mean(angles_rad: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Weighted circular mean of angles (rad), in [-pi, pi)."""
    a = np.asarray(angles_rad, dtype=float)
    w = np.ones_like(a) if weights is None else np.asarray(weights, dtype=float)
    return wrap_angle(math.atan2(float(np.sum(w * np.sin(a))), float(np.sum(w * np.cos(a)))))


def pnp_candidate(view: View, keypoints_base_m: np.ndarray, min_keypoints: int = 4,
                  ransac_px: float = 8.0) -> PoseCandidate | None:
    """PnP on one view; ``None`` when there are too few keypoints, PnP fails, or the solution
    is impossible (behind the camera, not upright, off the floor)."""
    valid = view.valid
    if int(valid.sum()) < max(min_keypoints, 4):
        return None
    obj = np.ascontiguousarray(keypoints_base_m[valid], dtype=np.float64)
    img = np.ascontiguousarray(view.keypoints_px[valid], dtype=np.float64)
    K, dist = view.camera.K, view.camera.dist
    rvec = tvec = None
    try:
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, K, dist, iterationsCount=100, reprojectionError=ransac_px,
            confidence=0.999, flags=cv2.SOLVEPNP_SQPNP)
        if ok and inliers is not None and len(inliers) >= 4:
            idx = inliers.reshape(-1)
            rvec, tvec = cv2.solvePnPRefineLM(obj[idx], img[idx], K, dist, rvec, tvec)
        else:
            ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_EPNP)
    except cv2.error as exc:
        log.debug("PnP failed for %s: %s", view.camera.camera_id, exc)
        return None
    if not ok or rvec is None or not np.all(np.isfinite(rvec)) or not np.all(np.isfinite(tvec)):
        return None
    R_cr, _ = cv2.Rodrigues(rvec)
    T_cam_robot = np.eye(4)
    T_cam_robot[:3, :3] = R_cr
    T_cam_robot[:3, 3] = tvec.reshape(3)
    depths = obj @ R_cr.T[:, 2] + float(tvec.reshape(3)[2])
    if np.any(depths <= 0.0):
        return None  # behind the camera
    T_world_robot = view.camera.T_world_cam @ T_cam_robot
    up = T_world_robot[:3, 2]
    if up[2] < math.cos(MAX_TILT_RAD):
        return None  # mirrored / flipped / lying robot
    if abs(T_world_robot[2, 3]) > MAX_HEIGHT_M:
        return None
    # Ground projection: the heading is the base x axis projected onto the floor.
    pose = PlanarPose(*(float(v) for v in se2_from_matrix(T_world_robot)))
    return PoseCandidate(view.camera.camera_id, T_world_robot, pose)


def _support(pose: PlanarPose, views: Sequence[View], keypoints_base_m: np.ndarray,
             inlier_px: float) -> tuple[int, float]:
    pts_world = keypoints_base_m @ pose.T()[:3, :3].T + pose.T()[:3, 3]
    errors: list[np.ndarray] = []
    for view in views:
        uv, depth = view.camera.project(pts_world)
        ok = view.valid & (depth > 0)
        err = np.full(len(uv), np.inf)
        err[ok] = np.linalg.norm(uv[ok] - view.keypoints_px[ok], axis=1)
        errors.append(err[view.valid])
    all_err = np.concatenate(errors) if errors else np.zeros(0)
    if all_err.size == 0:
        return 0, math.inf
    return int(np.sum(all_err < inlier_px)), float(np.median(all_err))


def init_without_prior(views: Sequence[View], keypoints_base_m: np.ndarray,
                       min_keypoints: int = 4, inlier_px: float = 10.0) -> InitResult:
    """Kidnapped-robot initialization from per-view PnP candidates (see the module doc).

    ``views``: the frame-set's views; ``keypoints_base_m`` (M, 3) base frame, metres.
    """
    kp = np.asarray(keypoints_base_m, dtype=np.float64)
    candidates: list[PoseCandidate] = []
    for view in views:
        cand = pnp_candidate(view, kp, min_keypoints)
        if cand is None:
            continue
        inliers, med = _support(cand.pose, views, kp, inlier_px)
        candidates.append(dataclasses.replace(cand, inliers=inliers, median_error_px=med))
    if not candidates:
        return InitResult(None, reason=f"no view gave a valid PnP pose (needs >= {min_keypoints} "
                                       "keypoints in front of the camera, robot upright)")
    best = max(candidates, key=lambda c: (c.inliers, -c.median_error_px))
    agree = [c for c in candidates
             if math.hypot(c.pose.x - best.pose.x, c.pose.y - best.pose.y) < AGREE_XY_M
             and abs(angle_diff(c.pose.theta, best.pose.theta)) < AGREE_YAW_RAD]
    w = np.array([max(c.inliers, 1) for c in agree], dtype=float)
    x = float(np.sum(w * [c.pose.x for c in agree]) / w.sum())
    y = float(np.sum(w * [c.pose.y for c in agree]) / w.sum())
    theta = circular_mean(np.array([c.pose.theta for c in agree]), w)
    return InitResult(PlanarPose(x, y, theta), best.T_world_robot, tuple(candidates))
