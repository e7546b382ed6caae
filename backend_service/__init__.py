"""Backend service: the robots' allocentric poses from the edge cameras' keypoint detections.

The per-robot pipeline (:mod:`backend_service.pipeline`): frame-set synchronization and
association of detections to robots, multi-view pose estimation (CasADi), initialization,
the single-camera rule, averaging while the robot is static and pose-graph fusion with odometry
(GTSAM); and the service node (``smartedge backend``). The semantic map is the mapper's
(package ``mapper``), a service of its own.

- ``pipeline``: the per-robot pipeline, messages in, estimates out (transport-free);
- ``pipeline_config``: the pipeline's parameters from the site file, what it needs of a pose graph;
- ``robot_track``: the pipeline's state for one robot: prior sources, predictions, averager, graph;
- ``sync``: the frame-set synchronizer: per-camera detections grouped into frame-sets;
- ``frame_set``: frame-sets, the synchronized multi-view observations one pose solve uses;
- ``association``: detections to robots: which robot of the site each detection is;
- ``assignment``: the optimal one-to-one assignment (Hungarian) the association runs;
- ``detection_router``: the association applied to camera messages, with its counters;
- ``estimate``: the public entry point of the multi-view pose estimation;
- ``pose_init``: initialization of the solve, from a prior or by per-view PnP;
- ``pose_solver``: the multi-view pose solve (the paper's Eq. 2) with CasADi: one cached problem
  per camera set and its methods;
- ``pose_symbolic``: Eq. 2 as CasADi expressions and the per-camera kernels compiled from them;
- ``gauss_newton``: the damped Gauss-Newton loop of the default method;
- ``compiled_functions``: CasADi functions compiled to C once per machine, kept on disk;
- ``projection``: the pose problem's projection in plain numpy, vectorized over cameras;
- ``covariance``: honest covariances of the estimates: the error model propagated through
  the solve;
- ``single_camera``: the paper's bearing-only heuristic for single-camera estimates;
- ``multi_frame``: averaging of camera estimates while the robot is static;
- ``fusion``: pose-graph fusion of camera estimates with odometry (GTSAM ISAM2): what enters the
  graph and when, the fused poses out;
- ``keyframe_graph``: the sliding-window keyframe graph the fusion fills: factor records, ISAM2,
  marginalization;
- ``camera_health``: a bumped camera noticed from its residuals;
- ``areas``: areas of a site: which cameras a backend serves, which area a robot is in;
- ``ownership``: which backend publishes which robot when several share a site (the rules,
  pure);
- ``ownership_tokens``: the same on the bus: the owner and area tokens, liveliness gets;
- ``service``: ``smartedge backend``, the node and its ``main``.

The algorithmic modules are pure: they take messages and site data and never touch Zenoh. Two
modules do, and neither imports ``zenoh`` itself (the sessions come from ``core``):
``service`` runs the node on Zenoh, and ``ownership_tokens`` declares and undeclares the
backend's owner and area tokens on the session and runs its liveliness gets. Imports only the
ground floor of the project (``protocol`` and ``core``). Heavy dependencies are imported
lazily by the modules that need them, so ``import backend_service`` stays cheap.
"""

from __future__ import annotations

import logging
from typing import Any

from backend_service.frame_set import CameraObservation, FrameSet

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

__all__ = ["CameraObservation", "FrameSet", *_LAZY]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'backend_service' has no attribute {name!r}")
