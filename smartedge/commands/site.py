"""``smartedge site check FILE`` / ``smartedge site calib FILE``: validate a site file or a
camera calibration file and print what was understood. ``smartedge site reference``: print the
configuration reference (every section, key and default; docs/configuration.md)."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence

import numpy as np

from core.site import load_camera_calibration, load_site
from protocol.errors import SiteConfigError


def check_sections(site: object) -> None:
    """Parse the package-owned sections too (each package's own parser), where the package is
    installed, so ``site check`` reports a bad ``fusion.window_s`` before a service starts."""
    try:
        from backend_service.areas import parse_areas
        from backend_service.fusion import fusion_config_from_site
        from backend_service.pipeline_config import PipelineConfig
    except ImportError:  # an edge board has no backend packages
        return
    PipelineConfig.from_site(site)  # type: ignore[arg-type]
    fusion_config_from_site(site)  # type: ignore[arg-type]
    parse_areas(site)  # type: ignore[arg-type]
    try:
        from robot_bridge.bridge import BridgeConfig
    except ImportError:
        return
    from core import acl
    from robot_bridge.adapters.ros2 import RosConfig

    for robot_id in site.robots:  # type: ignore[attr-defined]
        BridgeConfig.from_site(site, robot_id)  # type: ignore[arg-type]
        RosConfig.from_site(site, robot_id)
    # two robots on the same ROS topics: each bridge would correct the other's robot
    conflicts = acl.ros_conflicts(acl.site_ros_keys(site))  # type: ignore[arg-type]
    if conflicts:
        raise SiteConfigError(site.source_path, "robots",  # type: ignore[attr-defined]
                              "; ".join(conflicts))


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge site", description=__doc__)
    sub = parser.add_subparsers(dest="action", required=True)
    check = sub.add_parser("check", help="validate a site file and summarize it")
    check.add_argument("path")
    calib = sub.add_parser("calib", help="read an OpenCV/ROS camera calibration YAML")
    calib.add_argument("path")
    sub.add_parser("reference", help="print the configuration reference (Markdown)")
    args = parser.parse_args(list(argv))
    if args.action == "reference":
        from smartedge.config_reference import render

        print(render(), end="")
        return 0
    try:
        if args.action == "calib":
            c = load_camera_calibration(args.path)
            print(f"{args.path}: {c.width}x{c.height}\nK=\n{c.K}\ndist={c.dist.tolist()}")
            return 0
        site = load_site(args.path)
        check_sections(site)
    except SiteConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"site {site.name!r} ({args.path}), world frame {site.world_frame!r}")
    for cam in site.cameras.values():
        pos = cam.position_world
        axis = cam.optical_axis_world
        tilt = math.degrees(math.asin(-axis[2]))
        yaw = math.degrees(math.atan2(axis[1], axis[0]))
        hfov = math.degrees(2 * math.atan(cam.width / (2 * cam.K[0, 0])))
        print(
            f"  camera {cam.camera_id}: {cam.width}x{cam.height}, hfov {hfov:.0f} deg, at "
            f"({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}) m, looking yaw {yaw:.0f} deg, "
            f"down {tilt:.0f} deg"
        )
    for rid, model_name in site.robots.items():
        model = site.robot_models[model_name]
        span = np.ptp(model.keypoints_base_m, axis=0)
        ros = site.ros_section(rid)
        ns = f", ROS namespace {ros['namespace']!r}" if ros.get("namespace") else ""
        print(
            f"  robot {rid}: model {model_name}, {model.num_keypoints} keypoints spanning "
            f"{span[0]:.2f} x {span[1]:.2f} x {span[2]:.2f} m{ns}"
        )
    print("ok")
    return 0
