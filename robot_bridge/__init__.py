"""Robot bridge: odometry from the robot's navigation stack in, pose corrections out while the
robot is static. Adapters per robot (simulated robot, ROS 2 over Zenoh)."""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
