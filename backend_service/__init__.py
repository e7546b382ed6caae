"""Backend service: the robots' allocentric poses from the edge cameras' keypoint detections.

The per-robot pipeline (:mod:`backend_service.pipeline`): frame-set synchronization and
association of detections to robots, multi-view pose estimation (CasADi), initialization,
the single-camera rule, averaging while the robot is static and pose-graph fusion with odometry
(GTSAM); and the service node (``smartedge backend``). The semantic map is the mapper's
(package ``mapper``), a service of its own.

The algorithmic modules are pure: they take messages and site data and never touch Zenoh. Only
``backend_service.service`` does. Heavy dependencies are imported lazily by the modules that
need them, so ``import backend_service`` stays cheap.
"""

from __future__ import annotations

import logging
from typing import Any

from backend_service.frame_set import CameraObservation, FrameSet, PlanarPose

logging.getLogger(__name__).addHandler(logging.NullHandler())

_LAZY = {
    "PoseResult": "backend_service.estimate",
    "SolverConfig": "backend_service.estimate",
    "estimate_pose": "backend_service.estimate",
    "estimate_from_detections": "backend_service.estimate",
    "FrameSetSynchronizer": "backend_service.sync",
    "MultiFrameAverager": "backend_service.multi_frame",
    "FusionConfig": "backend_service.fusion",
    "PoseGraphFusion": "backend_service.fusion",
}

__all__ = ["CameraObservation", "FrameSet", "PlanarPose", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'backend_service' has no attribute {name!r}")
