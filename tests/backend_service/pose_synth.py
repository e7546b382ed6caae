"""Synthetic frame-sets for the pose-estimation tests: the example site's keypoints projected
through the real CameraModel (with its lens distortion)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from backend_service.frame_set import CameraObservation, FrameSet
from core.camera import CameraModel
from core.geometry import angle_diff, invert_transform
from core.pose import PlanarPose
from core.site import Site, load_site, look_at_T_world_cam

REPO = Path(__file__).resolve().parents[2]
SITE_PATH = REPO / "deploy" / "site.example.yaml"
ROBOT = "hsr"


def example_site() -> Site:
    return load_site(SITE_PATH)


def random_pose(rng: np.random.Generator) -> PlanarPose:
    """A pose in the middle of the example room (seen by all four cameras)."""
    return PlanarPose(float(rng.uniform(8.8, 11.2)), float(rng.uniform(4.8, 7.2)),
                      float(rng.uniform(-math.pi, math.pi)))


def project_pose(site: Site, pose: PlanarPose, camera_id: str) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) pixels and (M,) bool in-image-and-in-front of the robot keypoints at ``pose``."""
    kp = site.robot_model(ROBOT).keypoints_base_m
    T = pose.T()
    pts = kp @ T[:3, :3].T + T[:3, 3]
    cam = site.camera(camera_id)
    uv, depth = cam.project(pts)
    ok = (depth > 0) & cam.in_image(uv)
    return uv, ok


def make_frame_set(site: Site, pose: PlanarPose, camera_ids: list[str] | tuple[str, ...],
                   sigma_px: float = 0.0, rng: np.random.Generator | None = None,
                   stamp_ns: int = 1_000_000_000, outlier_fraction: float = 0.0) -> FrameSet:
    """Frame-set of ``pose`` seen by ``camera_ids``: Gaussian pixel noise ``sigma_px``, a
    fraction of keypoints replaced by gross outliers (uniform in the image), score 1 for
    visible keypoints and 0 for the rest."""
    rng = rng or np.random.default_rng(0)
    obs = []
    for cid in camera_ids:
        uv, ok = project_pose(site, pose, cid)
        uv = np.where(ok[:, None], uv, 0.0)
        if sigma_px > 0:
            uv = uv + rng.normal(0.0, sigma_px, uv.shape)
        if outlier_fraction > 0:
            cam = site.camera(cid)
            n_out = round(outlier_fraction * len(uv))
            idx = rng.choice(len(uv), n_out, replace=False)
            uv[idx] = rng.uniform([0, 0], [cam.width, cam.height], (n_out, 2))
        scores = ok.astype(float)
        obs.append(CameraObservation(cid, stamp_ns, uv, scores))
    return FrameSet.from_observations(ROBOT, obs)


def pose_error(a: PlanarPose, b: PlanarPose) -> tuple[float, float]:
    """(position error m, |yaw error| rad)."""
    return (math.hypot(a.x - b.x, a.y - b.y),
            abs(angle_diff(a.theta, b.theta)))


def ring_camera(camera_id: str, position_m: list[float], target_m: list[float],
                template: CameraModel) -> CameraModel:
    """A camera like ``template`` at ``position_m`` looking at ``target_m``."""
    T_world_cam = look_at_T_world_cam(np.array(position_m), np.array(target_m))
    return CameraModel(camera_id, template.width, template.height, template.K.copy(),
                       template.dist.copy(), invert_transform(T_world_cam))


#: the error model both covariance tests draw from (``SolverConfig``'s error terms)
SIGMA_PX = 1.0
SHIFT_PX = 0.5
SCALE = 0.02
EXTRINSIC_M = 0.01
EXTRINSIC_DEG = 0.1
ERRORS = dict(detection_shift_sigma_px=SHIFT_PX, detection_scale_sigma=SCALE,
              extrinsic_sigma_m=EXTRINSIC_M, extrinsic_sigma_deg=EXTRINSIC_DEG)


def true_camera(site: Site, camera_id: str, rng: np.random.Generator) -> CameraModel:
    """The camera as it really is: the calibrated one rotated about its optical centre
    (rotation vector, world axes) and moved, each component with ``EXTRINSIC_DEG`` /
    ``EXTRINSIC_M`` (as :func:`simulation.detections.true_cameras` draws it)."""
    import dataclasses

    from core.geometry import rotation_from_rotvec

    cam = site.camera(camera_id)
    T_world_cam = cam.T_world_cam.copy()
    dR = rotation_from_rotvec(rng.normal(0.0, math.radians(EXTRINSIC_DEG), 3))
    T_world_cam[:3, :3] = dR @ T_world_cam[:3, :3]
    T_world_cam[:3, 3] += rng.normal(0.0, EXTRINSIC_M, 3)
    return dataclasses.replace(cam, T_cam_world=invert_transform(T_world_cam))


def detect_with_errors(truth: PlanarPose, cam: CameraModel, keypoints_base_m: np.ndarray,
                       rng: np.random.Generator, stamp_ns: int = 1_000_000_000
                       ) -> CameraObservation | None:
    """One detection of ``truth`` by the (true) camera ``cam`` under the error model: a common
    shift (``SHIFT_PX``), a scale about the in-image keypoints' centroid (``SCALE``) and
    independent pixel noise (``SIGMA_PX``); keypoints outside the image or behind the camera
    get score 0. ``None`` when no keypoint is in the image."""
    T = truth.T()
    pts = keypoints_base_m @ T[:3, :3].T + T[:3, 3]
    uv, depth = cam.project(pts)
    ok = (depth > 0) & cam.in_image(uv)
    if not ok.any():
        return None
    centroid = uv[ok].mean(axis=0)
    scale = 1.0 + rng.normal(0.0, SCALE)
    shift = rng.normal(0.0, SHIFT_PX, 2)
    uv = centroid + scale * (uv - centroid) + shift + rng.normal(0.0, SIGMA_PX, uv.shape)
    uv = np.where(ok[:, None], uv, 0.0)
    return CameraObservation(cam.camera_id, stamp_ns, uv, ok.astype(np.float64))
