"""Robot adapters behind one interface (:class:`RobotAdapter`).

Only the interface is imported here: ``robot_bridge.adapters.ros2`` needs ``rosbags`` (and
``zenoh`` for its transport class) and ``robot_bridge.adapters.sim`` needs ``simulation``, so
each is imported by name where it is used.
"""

from __future__ import annotations

from robot_bridge.adapters.base import LocalizationPose, OdometrySample, RobotAdapter

__all__ = ["LocalizationPose", "OdometrySample", "RobotAdapter"]
