"""Synthetic camera layouts on a ring around the origin. :func:`ring_cameras`: copies of one
calibrated camera, each looking at the robot's height above the origin (the pose benchmarks
``smartedge bench pose``, ``robust``, ``single-camera`` and the pose tests vary the camera count
with it). :func:`write_ring_site`: a whole site file of ring cameras, with
:func:`robot_pose` (a robot driving a slow circle) and :func:`detection_payloads` (what every
camera publishes of it): the scene of ``smartedge bench backend`` and its stage breakdown.

Frames: world (= map), z up, metres.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from core.camera import CameraModel
from core.geometry import invert_transform, rotation_z
from core.site import Site, load_site, look_at_T_world_cam
from protocol import encode, keys
from protocol.messages import Detection, RobotDetections


def ring_cameras(template: CameraModel, count: int, radius_m: float = 4.0,
                 height_m: float = 2.5) -> list[CameraModel]:
    """``count`` copies of ``template`` (same image size, ``K`` and distortion) named
    ``ring00``, ``ring01``, ... on a circle of ``radius_m`` around the origin at ``height_m``,
    evenly spaced from 0.3 rad, each looking at (0, 0, 0.3 m)."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count + 0.3
        pos = np.array([radius_m * math.cos(a), radius_m * math.sin(a), height_m])
        T_world_cam = look_at_T_world_cam(pos, np.array([0.0, 0.0, 0.3]))
        cams.append(CameraModel(f"ring{i:02d}", template.width, template.height,
                                template.K.copy(), template.dist.copy(),
                                invert_transform(T_world_cam)))
    return cams


RING_RADIUS_M = 4.0
CAMERA_HEIGHT_M = 2.5
ROBOT_CIRCLE_M = 0.5
ROBOT_SPEED_MPS = 0.2


def write_ring_site(path: Path, n_cameras: int) -> Site:
    """A site with ``n_cameras`` on a ring around the origin, all looking at it, and the HSR
    keypoint model of the paper site."""
    from simulation.scenario import load_scenario

    model = load_scenario().site.robot_model()
    cameras = []
    for i in range(n_cameras):
        a = 2 * math.pi * i / n_cameras
        cameras.append({
            "id": f"cam{i:02d}", "resolution": [848, 480],
            "intrinsics": {"fx": 428.0, "fy": 428.0, "cx": 424.0, "cy": 240.0},
            "distortion": [-0.055, 0.065, 0.0, 0.0, -0.02],
            "T_world_cam": {"position_m": [RING_RADIUS_M * math.cos(a),
                                           RING_RADIUS_M * math.sin(a), CAMERA_HEIGHT_M],
                            "look_at_m": [0.0, 0.0, 0.2]},
        })
    doc = {
        "site": "bench", "cameras": cameras,
        "robot_models": {"hsr": {
            "footprint_radius_m": model.footprint_radius_m, "height_m": model.height_m,
            "keypoints": [{"name": n, "xyz_m": [float(v) for v in p]}
                          for n, p in zip(model.keypoint_names, model.keypoints_base_m,
                                          strict=True)]}},
        "robots": [{"id": "hsr", "model": "hsr"}],
        "thresholds": {"sync_window_ms": 10.0, "sync_max_wait_ms": 50.0},
    }
    path.write_text(yaml.safe_dump(doc))
    return load_site(path)


def robot_pose(t_s: float) -> np.ndarray:
    w = ROBOT_SPEED_MPS / ROBOT_CIRCLE_M
    return np.array([ROBOT_CIRCLE_M * math.cos(w * t_s), ROBOT_CIRCLE_M * math.sin(w * t_s),
                     w * t_s + math.pi / 2])


def detection_payloads(site: Site, pose: np.ndarray, stamp_ns: int, seq: int,
                       rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """(key, encoded RobotDetections) of every camera seeing the robot at ``pose`` (x, y,
    theta), its keypoints with 1 px Gaussian noise."""
    model = site.robot_model()
    pts = model.keypoints_base_m @ rotation_z(pose[2]).T + [pose[0], pose[1], 0.0]
    out = []
    for cam in site.cameras.values():
        uv, _ = cam.project(pts)
        uv = uv + rng.normal(0.0, 1.0, uv.shape)
        lo, hi = uv.min(axis=0) - 5, uv.max(axis=0) + 5
        det = Detection(np.array([*lo, *hi]), 0.95, uv, np.full(len(uv), 0.9))
        msg = RobotDetections(cam.camera_id, stamp_ns, seq, cam.width, cam.height, "bench",
                              (det,))
        out.append((keys.detections_key(site.name, cam.camera_id), encode(msg)))
    return out


__all__ = ["detection_payloads", "ring_cameras", "robot_pose", "write_ring_site"]
