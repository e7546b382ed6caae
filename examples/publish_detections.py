"""Publish one camera's robot detections onto the bus, as your own detector would.

The backend (``smartedge backend``) listens on ``smartedge/<site>/edge/<camera>/detections`` for
:class:`protocol.RobotDetections`; anything that puts them there is an edge agent. Here the
"detector" projects the robot model's keypoints at a fixed pose into the camera and adds pixel
noise; replace ``detect`` with your network.

    .venv/bin/python examples/publish_detections.py --camera cam_sw --rate-hz 10 --count 50
"""

from __future__ import annotations

import argparse
import contextlib
import math
import time
from pathlib import Path

import numpy as np
import zenoh

import protocol
from core.camera import CameraModel
from core.geometry import se3_from_planar
from core.session import add_session_arguments, make_config, options_from_args
from core.site import RobotModel, load_site
from protocol import keys

EXAMPLE_SITE = Path(__file__).resolve().parents[1] / "deploy" / "site.example.yaml"


def detect(camera: CameraModel, model: RobotModel, T_world_robot: np.ndarray,
           rng: np.random.Generator, noise_px: float = 1.0) -> tuple[protocol.Detection, ...]:
    """Your detector goes here: the robot's keypoints in pixels, (M, 2) in the robot model's
    order, with a score per keypoint (0 = not found). Empty when the robot is not seen."""
    uv_px, depth_m = camera.project(model.keypoints_base_m @ T_world_robot[:3, :3].T
                                    + T_world_robot[:3, 3])
    visible = camera.in_image(uv_px) & (depth_m > 0)
    if not visible.any():
        return ()
    uv_px = np.where(visible[:, None], uv_px + rng.normal(0.0, noise_px, uv_px.shape), 0.0)
    seen = uv_px[visible]
    return (protocol.Detection(
        bbox_xyxy=np.array([*seen.min(axis=0), *seen.max(axis=0)]), score=0.9,
        keypoints_px=uv_px, keypoint_scores=visible.astype(np.float64)),)


def main(conf: zenoh.Config, site_path: Path, camera_id: str, rate_hz: float, count: int,
         x_m: float, y_m: float, theta_rad: float) -> None:
    site = load_site(site_path)
    camera = site.camera(camera_id)
    model = site.robot_model(next(iter(site.robots)))
    T_world_robot = se3_from_planar(x_m, y_m, theta_rad)
    rng = np.random.default_rng(0)
    key = keys.detections_key(site.name, camera_id)

    with zenoh.open(conf) as session:
        publisher = session.declare_publisher(key)
        print(f"publishing on {key} at {rate_hz:g} Hz", flush=True)
        seq = 0
        next_s = time.monotonic()
        while count <= 0 or seq < count:  # count <= 0: until Ctrl-C
            msg = protocol.RobotDetections(
                camera_id=camera_id, stamp_ns=time.time_ns(),  # when the image was taken
                seq=seq, image_width=camera.width, image_height=camera.height,
                model_id="my-detector", detections=detect(camera, model, T_world_robot, rng))
            publisher.put(protocol.encode(msg))
            print(f"put seq={seq} detections={len(msg.detections)}", flush=True)
            seq += 1
            next_s += 1.0 / rate_hz
            time.sleep(max(0.0, next_s - time.monotonic()))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, default=EXAMPLE_SITE, help="site file (YAML)")
    parser.add_argument("--camera", default="cam_sw", help="camera id in the site file")
    parser.add_argument("--rate-hz", type=float, default=10.0, help="frames per second")
    parser.add_argument("--count", type=int, default=0, help="frames to send (0: until Ctrl-C)")
    parser.add_argument("--x-m", type=float, default=10.0, help="the robot's x (world frame)")
    parser.add_argument("--y-m", type=float, default=6.0, help="the robot's y (world frame)")
    parser.add_argument("--theta-deg", type=float, default=30.0, help="the robot's heading")
    add_session_arguments(parser)  # --mode, --connect, --listen, --config (as zenoh's examples)
    args = parser.parse_args()
    conf = make_config(options_from_args(args))  # default: a peer on tcp/127.0.0.1:7447
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: close the session and stop
        main(conf, args.site, args.camera, args.rate_hz, args.count, args.x_m, args.y_m,
             math.radians(args.theta_deg))
