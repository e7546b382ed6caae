"""Robot adapters behind one interface (:class:`RobotAdapter`).

Only the interface is imported here: ``robot_bridge.adapters.ros2`` needs ``rosbags`` (and
``zenoh`` for its transport class), so it is imported by name where it is used.
``robot_bridge.adapters.sim`` is written against a structural interface of a simulated robot
and imports no simulation code; which adapters the bridge offers is decided by
:mod:`robot_bridge.adapters.registry` (the simulated one is registered from the top floor).
"""

from __future__ import annotations

from robot_bridge.adapters.base import LocalizationPose, OdometrySample, RobotAdapter

__all__ = ["LocalizationPose", "OdometrySample", "RobotAdapter"]
