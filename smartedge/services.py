"""The composition root: how ``smartedge <service>`` starts each service of the system.

The services know only their own registries (frame sources, robot adapters) and never import
the simulation or each other; this module is the one place that knows them all. Each entry
point registers what the service may be offered from outside its package (the simulated site,
:mod:`smartedge.simulated_site`) and then hands its argv to the service's own ``main``:

- :func:`edge_agent_main`: ``smartedge edge-agent`` (``--source camera|ros|sim``);
- :func:`robot_bridge_main`: ``smartedge robot-bridge`` (``--adapter ros2|ros1|rmw_zenoh|sim``);
- :func:`robot_camera_main`: ``smartedge robot-camera``: the robot's head RGB-D camera as
  semantic clouds, from the real robot's ROS 2 topics (``--source ros``,
  :mod:`edge_agent.robot_camera`) or the simulated head (``--source sim``, the default,
  :mod:`smartedge.simulated_head_camera`).

The backend and the mapper have nothing to register: their commands point at their packages
directly (:data:`smartedge.cli.COMMANDS`). Everything is imported inside the functions, so an
edge board loads only what its own service needs.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence


def edge_agent_main(argv: Sequence[str]) -> int:
    """``smartedge edge-agent``: the edge agent with the simulated source offered."""
    from smartedge.simulated_site import register_sim_source

    register_sim_source()
    from edge_agent.service import main

    return main(argv)


def robot_bridge_main(argv: Sequence[str]) -> int:
    """``smartedge robot-bridge``: the robot bridge with the simulated robot offered."""
    from smartedge.simulated_site import register_sim_adapter

    register_sim_adapter()
    from robot_bridge.service import main

    return main(argv)


def robot_camera_source(argv: Sequence[str]) -> str:
    """The ``--source`` of a ``smartedge robot-camera`` command line (default ``sim``); the
    chosen service parses the whole line again, its ``--help`` included."""
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("--source", default="sim")  # the chosen service checks the value
    args, _ = parser.parse_known_args(list(argv))
    return str(args.source)


def robot_camera_main(argv: Sequence[str]) -> int:
    """``smartedge robot-camera``: the real head camera (``--source ros``) or the simulated one."""
    if robot_camera_source(argv) == "ros":
        from edge_agent.robot_camera import main as ros_main

        return ros_main(argv)
    from smartedge.simulated_head_camera import main as sim_main

    return sim_main(argv)


__all__ = ["edge_agent_main", "robot_bridge_main", "robot_camera_main", "robot_camera_source"]
