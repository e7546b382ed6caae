"""Mapper: the collaborative 3D semantic map (the paper's Sec. III-C), a service of its own.

Semantic point clouds of the static edge sensors (world frame) and of the robots (base frame,
placed with the backend's fused pose at the cloud's stamp) are fused into one sparse semantic
voxel map of the site, world frame, metres. Robot clouds pass an ICP gate first: aligned to the
map, fused only when the alignment agrees with the pose.

- :mod:`mapper.semantic_map`: the voxel map (Bayesian class fusion, occupancy, geometry), numpy;
- :mod:`mapper.alignment`: the ICP gate (Open3D, imported here only);
- :mod:`mapper.mapping`: placing, gating and fusing clouds (:class:`SemanticMapping`, one
  transport-free object driven by the service, experiments and tests alike);
- :mod:`mapper.map_io`: map files (the ``.npz`` snapshot, PLY export, PLY prior models);
- :mod:`mapper.service`: ``smartedge mapper``, the node, and the only module that touches Zenoh.

Imports only the ground floor of the project (``protocol`` and ``core``): never the backend,
the other services, the simulation or the top floor. ``import mapper`` is cheap: nothing heavy
is loaded until a module that needs it is imported.
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
