"""Edge agent: runs on a smart edge sensor (Jetson), turns camera frames into robot keypoint
detections and semantic clouds and publishes them; a service (``smartedge edge-agent``).

- ``service``: one camera's edge service;
- ``sources``: the frame sources and the registry the ``--source`` option is built from;
- ``frames``: grabbers (devices, streams, files, folders) behind one interface and the reader
  thread that always hands over the newest frame;
- ``capture``: the processed frames saved for a lab's own dataset (``--capture``), bounded disk;
- ``capture_stamps``: the driver's capture stamps (V4L2, RealSense) in the sensor clock;
- ``ros_source``: ``--source ros``: camera images from ROS 2 topics on the Zenoh bus;
- ``ros_tf``: ``/tf`` and ``/tf_static`` from the bus into a :class:`core.tf_buffer.TfBuffer`;
- ``robot_camera``: ``smartedge robot-camera --source ros``: the real robot's head RGB-D
  camera as semantic clouds;
- ``models``: the robot keypoint pipelines (detector → crop → keypoints, per robot type);
- ``networks``: the detector, keypoint and segmentation networks on onnxruntime, decoding;
- ``model_cards``: each ONNX model's card and the export check (the shipped models are in
  ``edge_agent/models/``);
- ``providers``: where the networks run: execution providers, fallbacks, sessions;
- ``flip``: test-time flip, the mirrored frame's answer fused with the frame's;
- ``boxes``: box overlap and IoU, and whether two boxes are one robot (the one place);
- ``crop``: image geometry shared by training and inference (detector input, keypoint crops);
- ``far_band``: the rows of a static camera's frame where far robots appear, which the
  detector runs again at twice its scale;
- ``pipeline``: the per-frame pipeline, a frame through the ONNX models to ``RobotDetections``;
- ``semantic_cloud``: semantic point clouds from an RGB-D frame and its segmentation;
- ``preview``: JPEG preview images for the viewer;
- ``metrics``: held-out metrics of the detector, keypoint and segmentation networks (numpy).

Imports only the ground floor of the project (``protocol`` and ``core``); of third parties
numpy, OpenCV and onnxruntime (pyrealsense2 only for a RealSense, ``zenoh.ext`` in
``ros_tf``): never casadi, gtsam, open3d, rerun or torch.
"""

from __future__ import annotations

import logging

logging.getLogger(__name__).addHandler(logging.NullHandler())
