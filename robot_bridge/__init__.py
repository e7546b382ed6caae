"""Robot bridge: odometry from the robot's navigation stack in, pose corrections out while the
robot is static; a service (``smartedge robot-bridge``).

- ``bridge``: the transport-free core: robot odometry in, ``Odometry`` to the backend out,
  pose corrections to the robot when it is static;
- ``policy``: when to push a pose to the robot's localization: static detection and the
  correction rule;
- ``pose_output``: the continuous pose output: the backend's estimates as a pose topic the
  robot can fuse (and ``map -> odom``);
- ``map_output``: the semantic map for ROS: ``PointCloud2`` and an obstacle ``OccupancyGrid``;
- ``service``: ``smartedge robot-bridge``, the node between one robot and the network;
- ``adapters``: the robots behind one interface (ROS 2 / ROS 1 over Zenoh, rmw_zenoh, the
  simulated robot's port).

Imports only the ground floor of the project (``protocol`` and ``core``).
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
