"""``smartedge viewer``: watch a running system in Rerun.

The viewer is a sink: it subscribes to the keys the services publish (detections, odometry, the
robot's localization, camera-only and fused poses, corrections, statuses) and draws them. It
never sits inside a service's logic, so the same view works in-process for ``smartedge demo``,
as its own process beside a deployment, or on a laptop connected to the site's router.

- ``node``: the viewer node, wire messages in, Rerun calls out (transport-free);
- ``rerun_view``: live state in the Rerun viewer, the only module that imports ``rerun``.

Part of the app wing (:mod:`smartedge`): never imports the lab.
"""

from __future__ import annotations

from smartedge.viewer.node import ViewerNode, build_node, build_parser, main

__all__ = ["ViewerNode", "build_node", "build_parser", "main"]
