"""Solve a robot's pose from your own keypoint detections with the Python API (no Zenoh).

Stands in for a detector by projecting the robot model's keypoints into every camera of the
site at a known pose and adding pixel noise; then solves the pose from those detections without
a prior (as for a kidnapped robot) and prints it, its uncertainty and its error to the truth.

    .venv/bin/python examples/solve_pose.py --x-m 10.0 --y-m 6.0 --theta-deg 30 --noise-px 1.0
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from backend_service import estimate_from_detections
from core.camera import CameraModel
from core.geometry import angle_diff
from core.pose import PlanarPose
from core.site import RobotModel, load_site
from protocol import Detection, RobotDetections

EXAMPLE_SITE = Path(__file__).resolve().parents[1] / "deploy" / "site.example.yaml"


def detect(camera: CameraModel, model: RobotModel, T_world_robot: np.ndarray,
           noise_px: float, rng: np.random.Generator) -> Detection | None:
    """What a keypoint detector would report for the robot at ``T_world_robot`` (4x4, robot base
    -> world): the model's keypoints projected into ``camera`` plus Gaussian pixel noise.
    ``None`` when the robot is not in the image."""
    keypoints_world = model.keypoints_base_m @ T_world_robot[:3, :3].T + T_world_robot[:3, 3]
    uv_px, depth_m = camera.project(keypoints_world)
    visible = camera.in_image(uv_px) & (depth_m > 0)
    if not visible.any():
        return None
    uv_px = np.where(visible[:, None], uv_px + rng.normal(0.0, noise_px, uv_px.shape), 0.0)
    seen = uv_px[visible]
    return Detection(
        bbox_xyxy=np.array([*seen.min(axis=0), *seen.max(axis=0)]),
        score=0.9,
        keypoints_px=uv_px,
        keypoint_scores=visible.astype(np.float64),  # 0: "not found", ignored by the solver
        keypoint_sigmas_px=np.full(len(uv_px), max(noise_px, 0.5)),  # how much to trust each
    )


def main(site_path: Path, truth: PlanarPose, noise_px: float, seed: int) -> None:
    site = load_site(site_path)
    robot_id = next(iter(site.robots))
    model = site.robot_model(robot_id)
    rng = np.random.default_rng(seed)
    stamp_ns = time.time_ns()

    # one message per camera, all taken at the same time (a "frame-set")
    messages = []
    for camera in site.cameras.values():
        detection = detect(camera, model, truth.T(), noise_px, rng)
        messages.append(RobotDetections(
            camera_id=camera.camera_id, stamp_ns=stamp_ns, seq=0, image_width=camera.width,
            image_height=camera.height, model_id="my-detector",
            detections=(detection,) if detection is not None else ()))

    result = estimate_from_detections(site, messages, prior=None)  # None: PnP initialization
    if not result.ok:
        raise SystemExit(f"no pose: {result.reason}")
    est = result.estimate
    std_x_m, std_y_m, std_theta_rad = np.sqrt(np.diag(est.covariance))  # covariance: SI units
    error_cm = 100 * math.hypot(est.x - truth.x, est.y - truth.y)
    error_deg = math.degrees(angle_diff(est.theta, truth.theta))

    print(f"cameras: {', '.join(est.camera_ids)}  (reprojection RMSE "
          f"{est.reprojection_rmse_px:.2f} px)")
    print(f"pose:  x={est.x:.3f} m  y={est.y:.3f} m  theta={math.degrees(est.theta):.2f} deg")
    print(f"std:   x={100 * std_x_m:.1f} cm  y={100 * std_y_m:.1f} cm  "
          f"theta={math.degrees(std_theta_rad):.2f} deg")
    print(f"error: {error_cm:.1f} cm  {error_deg:+.2f} deg")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, default=EXAMPLE_SITE, help="site file (YAML)")
    parser.add_argument("--x-m", type=float, default=10.0, help="true x in the world frame")
    parser.add_argument("--y-m", type=float, default=6.0, help="true y in the world frame")
    parser.add_argument("--theta-deg", type=float, default=30.0, help="true heading")
    parser.add_argument("--noise-px", type=float, default=1.0, help="keypoint noise (1 sigma)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the noise")
    args = parser.parse_args()
    main(args.site, PlanarPose(args.x_m, args.y_m, math.radians(args.theta_deg)),
         args.noise_px, args.seed)
