"""The benchmarks' ring site: N cameras on a ring around the origin, all looking at a robot that
drives a slow circle, and the detections every camera publishes of it (the scene of
``smartedge bench backend`` and its stage breakdown)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from protocol import encode, keys
from protocol.geometry import rotation_z
from protocol.messages import Detection, RobotDetections
from protocol.site import Site, load_site

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
