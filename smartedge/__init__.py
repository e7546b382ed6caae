"""smartedge: marker-less mobile robot localization from static smart edge cameras.

This package is the app wing: the ``smartedge`` command line and what joins the services
together. The system itself lives in ``protocol`` and ``core`` (the ground floor), the services
``edge_agent``, ``backend_service``, ``mapper`` and ``robot_bridge``, ``calibration`` and the
``simulation`` plug-in.

- ``cli``: the ``smartedge`` command, one entry point, subcommands imported lazily;
- ``services``: the composition root: how ``smartedge <service>`` starts each service;
- ``simulated_site``: the simulated site as plug-ins of the services (a frame source and a
  robot adapter);
- ``simulated_head_camera``: ``smartedge robot-camera`` for the simulated robot's head RGB-D
  camera, as semantic clouds;
- ``record_ros``: ROS 2 schemas and CDR payloads for ``smartedge record`` (the definitions are
  in ``ros_msgs/``);
- ``config_reference``: the configuration reference, generated from the site-file dataclasses;
- ``commands``: the operator's commands, one module per command, and the lazy command registry;
- ``viewer``: ``smartedge viewer``, the running system in Rerun.

Imports the floors below it (the ground floor, the services, ``calibration`` and
``simulation``) and never the lab: the lab's commands reach the CLI through the
``smartedge.commands`` entry point.
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
