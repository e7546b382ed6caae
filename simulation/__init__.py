"""Simulated site: room, cameras, robot model and motion, odometry drift, detection noise.

A sensor and robot source that produces the same ``protocol`` messages real sensors do; a
plug-in of the services (registered into them from the top floor, :mod:`smartedge.simulated_site`).

- the site and what happens on it: ``scenario`` (scenario files: room, obstacles, waypoints,
  trajectories, noise, seeds), ``world`` (the room's obstacles, line-of-sight tests),
  ``robot`` (differential-drive motion, drifting wheel odometry, a localization that accepts
  corrections only when static), ``head`` (the robot's pan/tilt head and its TF tree),
  ``fleet`` (several robots on one site, as the cameras see them);
- simulated time and messages: ``runner`` (a scenario trajectory in simulated time, messages in
  arrival order), ``detections`` (the detection noise model: what an edge camera's detector
  would report), ``calibration_drive`` (a calibration drive's messages for ``smartedge
  calibrate robot``), ``synthetic_run`` (a looped run with drifting odometry for the pose-graph
  fusion), ``synthetic_room`` (a labelled synthetic room for the semantic map), ``camera_ring``
  (synthetic camera layouts on a ring);
- real time and the bus: ``live`` (the simulated site in real time for ``--source sim`` /
  ``--adapter sim``), ``publisher`` (a simulated run published over Zenoh, the only module
  here that imports zenoh), ``hostile`` (oversized payloads a simulated attacker sends);
- rendering: ``mesh`` (triangle meshes and scenes), ``scenes`` (the scenes the cameras see),
  ``robot_mesh`` (robot meshes, the built-in HSR-like robot), ``robot_files`` (a user's own
  robot: mesh, URDF, keypoint file; trimesh), ``render_gl`` (headless OpenGL rendering through a
  calibrated camera; moderngl), ``gl_resources`` (its GPU-side pieces), ``lens`` (OpenCV
  intrinsics as an OpenGL projection and the distorting lens map), ``render_stages`` (time per
  render stage), ``site_cameras`` (images from each camera's true pose), ``board_views``
  (rendered calibration-board views), ``labels`` (training labels from a rendered image),
  ``dataset`` (rendered, exactly labelled samples and a dataset writer), ``image_effects``
  (the camera's and the scene's image-space effects, the photometric augmentation).

Imports only the ground floor of the project (``protocol`` and ``core``), never a service.
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
