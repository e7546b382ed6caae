"""Backend service: frame-set synchronization, multi-view pose estimation (CasADi), pose-graph
fusion (GTSAM), semantic map (Open3D), Rerun logging and the service loop.

The algorithmic modules (frame sets, solver, initialization, metrics, fusion) are pure: they take
messages and site data and never touch Zenoh. Only ``backend_service.service`` does.
"""

from __future__ import annotations

import logging

from backend_service.frame_set import CameraObservation, FrameSet, PlanarPose

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["CameraObservation", "FrameSet", "PlanarPose"]
