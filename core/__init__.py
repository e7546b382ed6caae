"""The shared core of the ground floor: what every floor uses that is not part of the wire
contract (that is :mod:`protocol`).

- ``runtime``: the shape every service shares: a transport-free service node and the Zenoh
  runner around it (one worker loop, bounded channels);
- ``session``: the Zenoh session configuration (a json5 file, the environment or the embedded
  default) and its command-line flags;
- ``site``: the site file: cameras, robot models, robots, thresholds and the one clock policy;
- ``config_file``: reading YAML configuration files with errors that name the file and the
  dotted key;
- ``camera``: the pinhole camera with OpenCV lens distortion, in plain numpy;
- ``projection``: the one projection of world points into cameras with its Jacobians (vs the
  camera's pose and vs the point), used by the covariances, camera health and calibration;
- ``geometry``: plain-numpy angles, SE(2), SE(3), quaternions, the lens distortion model and
  the static-robot detector;
- ``history``: the one stamped history: items in stamp order, looked up, interpolated, trimmed;
- ``tf_buffer``: a small TF buffer: the robot's frame tree from ``/tf`` and ``/tf_static``,
  looked up at a stamp;
- ``acl``: who may put what on the bus: the ``access_control`` block of the site's router;
- ``plugins``: named plug-ins chosen by a command-line option (``--source``, ``--adapter``);
- ``pose``: the one planar pose type, ``PlanarPose`` (x, y, theta in a frame);
- ``trajectory``: the one trajectory type (stamped 3D poses) and its TUM files;
- ``pose_labels``: a robot's keypoints, visibility, box and expected pixel error in a camera's
  image from its pose (the system labelling its own frames);
- ``coco``: the one format of labelled camera frames, COCO keypoints files: read (checked),
  written atomically, matched to a robot model, split by time, merged.

Imports only :mod:`protocol` of the project; of third parties numpy, PyYAML (``config_file``,
``site``) and zenoh (inside the functions of ``runtime`` and ``session`` that need it).
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
