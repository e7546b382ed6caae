"""Edge agent: runs on a smart edge sensor (Jetson), turns camera frames into robot keypoint
detections and semantic clouds and publishes them. Imports only ``protocol``, numpy, OpenCV and
onnxruntime: never casadi, gtsam, open3d or rerun."""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
