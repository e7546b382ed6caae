"""Your own robot behind the robot bridge: a ``RobotAdapter`` around the robot's own API,
offered as ``--adapter wheels`` next to the adapters the bridge ships (ros2, ros1, rmw_zenoh,
sim).

The bridge needs three things from a robot: its odometry (``read_odometry``), its own
localization in the map frame (``read_localization``: ``None`` or ``lost`` while it does not
know where it is) and a way to set its pose (``apply_correction``: an initial pose, or a
correction while it stands still). It publishes the odometry and localization on
``smartedge/<site>/robot/<robot>/{odom,localization}`` and decides on corrections from the
backend's fused pose. Adapters never block and never raise on the robot's bad data: they drop
it and count it in ``self.counters``.

Here the "robot API" is :class:`WheelRobot`, a base that integrates its wheel speeds and starts
lost (a kidnapped robot); replace its calls with your robot's SDK, serial protocol or topics.

    .venv/bin/python examples/robot_adapter.py --site deploy/site.example.yaml --robot hsr \\
        --adapter wheels --wheels-start 10.5 5.5 90
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence

from core.site import Site
from protocol.messages import PoseCorrection
from robot_bridge.adapters.base import (
    AdapterSetup,
    LocalizationPose,
    OdometrySample,
    RobotAdapter,
)
from robot_bridge.adapters.registry import register_adapter


class WheelRobot:
    """The robot's own API (a stand-in): wheel odometry integrated in ``odom``, and a pose in
    ``map`` it knows only once it was given one (``set_pose``)."""

    def __init__(self, x_m: float, y_m: float, theta_rad: float, speed_mps: float) -> None:
        self.true_pose = [x_m, y_m, theta_rad]  # where it is (the robot cannot know this)
        self.odom = [0.0, 0.0, 0.0]  # odom frame: where it started
        self.speed_mps = speed_mps
        self.map_from_odom: tuple[float, float, float] | None = None  # set_pose's answer
        self.last_ns: int | None = None

    def step(self, now_ns: int) -> None:
        """Drive straight at ``speed_mps`` (0: stand still) until ``now_ns``."""
        dt = 0.0 if self.last_ns is None else (now_ns - self.last_ns) * 1e-9
        self.last_ns = now_ns
        d = self.speed_mps * dt
        for pose in (self.true_pose, self.odom):
            pose[0] += d * math.cos(pose[2])
            pose[1] += d * math.sin(pose[2])

    def set_pose(self, x_m: float, y_m: float, theta_rad: float) -> None:
        """Where the robot is in the map now: remember map -> odom (like AMCL's initialpose)."""
        ox, oy, oth = self.odom
        theta = theta_rad - oth
        self.map_from_odom = (x_m - (ox * math.cos(theta) - oy * math.sin(theta)),
                              y_m - (ox * math.sin(theta) + oy * math.cos(theta)), theta)

    def map_pose(self) -> tuple[float, float, float] | None:
        if self.map_from_odom is None:
            return None
        mx, my, mth = self.map_from_odom
        ox, oy, oth = self.odom
        return (mx + ox * math.cos(mth) - oy * math.sin(mth),
                my + ox * math.sin(mth) + oy * math.cos(mth), oth + mth)


class WheelRobotAdapter(RobotAdapter):
    """The bridge's view of a :class:`WheelRobot`."""

    name = "wheels"

    def __init__(self, robot: WheelRobot) -> None:
        super().__init__()
        self.robot = robot

    def read_odometry(self) -> list[OdometrySample]:
        if self.robot.last_ns is None:
            return []
        x, y, theta = self.robot.odom
        return [OdometrySample(self.robot.last_ns, x, y, theta, vx=self.robot.speed_mps)]

    def read_localization(self) -> LocalizationPose | None:
        if self.robot.last_ns is None:
            return None
        pose = self.robot.map_pose()
        if pose is None:  # never given a pose: lost, the bridge initializes it
            return LocalizationPose(self.robot.last_ns, 0.0, 0.0, 0.0, lost=True)
        return LocalizationPose(self.robot.last_ns, *pose)

    def apply_correction(self, correction: PoseCorrection) -> bool:
        self.robot.set_pose(correction.x, correction.y, correction.theta)
        self._count(f"applied_{correction.kind}")
        print(f"{correction.kind}: pose set to x={correction.x:.3f} m y={correction.y:.3f} m "
              f"theta={math.degrees(correction.theta):.1f} deg", flush=True)
        return True


class WheelsPlugin:
    """``--adapter wheels``: its own options, and the adapter built from them."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group("wheel robot (--adapter wheels)")
        group.add_argument("--wheels-start", type=float, nargs=3, default=(10.5, 5.5, 90.0),
                           metavar=("X_M", "Y_M", "THETA_DEG"),
                           help="where the robot really is at start (it does not know it)")
        group.add_argument("--wheels-speed", type=float, default=0.0, metavar="M_PER_S",
                           help="driving speed (default 0: it stands still)")

    def build(self, args: argparse.Namespace, site: Site | None) -> AdapterSetup:
        x, y, theta_deg = args.wheels_start
        robot = WheelRobot(x, y, math.radians(theta_deg), args.wheels_speed)
        adapter = WheelRobotAdapter(robot)
        # advance: called with the wall clock before every pump of the bridge (a real robot's
        # SDK would run on its own and need none)
        return AdapterSetup(factory=lambda session: adapter, advance=robot.step)


def main(argv: Sequence[str]) -> int:
    """The robot bridge (``smartedge robot-bridge``) with ``--adapter wheels`` offered."""
    register_adapter("wheels", WheelsPlugin())
    from robot_bridge.service import main as robot_bridge_main

    return robot_bridge_main(argv)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
