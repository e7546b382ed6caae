"""Robot adapters behind one interface (:class:`RobotAdapter`).

- ``base``: the small interface between the bridge and one robot, and the data that crosses it;
- ``registry``: the adapter plug-ins and the registry the ``--adapter`` option is built from;
- ``ros_plugin``: the ``--adapter ros2`` / ``ros1`` plug-in and the ROS options every ROS
  plug-in reads;
- ``ros2``: ROS 2 (and ROS 1) robots over the Zenoh bridges: odometry in, pose corrections
  out, as ROS messages;
- ``rmw_zenoh``: ROS 2 robots on rmw_zenoh, reached directly (no bridge process);
- ``rmw_zenoh_wire``: rmw_zenoh's wire conventions as pure functions (keys, attachments,
  liveliness tokens);
- ``sim``: the adapter of the simulated robot, written against a structural port.

Only the interface is imported here: ``robot_bridge.adapters.ros2`` needs ``rosbags`` (and
``zenoh`` for its transport class), so it is imported by name where it is used.
``robot_bridge.adapters.sim`` is written against a structural interface of a simulated robot
and imports no simulation code; which adapters the bridge offers is decided by
:mod:`robot_bridge.adapters.registry` (the simulated one is registered from the top floor).
Like the rest of the bridge, imports only the ground floor (``protocol`` and ``core``).
"""

from __future__ import annotations

from robot_bridge.adapters.base import LocalizationPose, OdometrySample, RobotAdapter

__all__ = ["LocalizationPose", "OdometrySample", "RobotAdapter"]
