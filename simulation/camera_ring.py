"""A synthetic camera layout: copies of one calibrated camera on a ring around the origin,
each looking at the robot's height above it. Used by the pose benchmarks (``smartedge bench
pose``, ``robust``, ``single-camera``) and the pose tests to vary the camera count.

Frames: world (= map), z up, metres.
"""

from __future__ import annotations

import math

import numpy as np

from protocol.camera import CameraModel
from protocol.geometry import invert_transform
from protocol.site import look_at_T_world_cam


def ring_cameras(template: CameraModel, count: int, radius_m: float = 4.0,
                 height_m: float = 2.5) -> list[CameraModel]:
    """``count`` copies of ``template`` (same image size, ``K`` and distortion) named
    ``ring00``, ``ring01``, ... on a circle of ``radius_m`` around the origin at ``height_m``,
    evenly spaced from 0.3 rad, each looking at (0, 0, 0.3 m)."""
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count + 0.3
        pos = np.array([radius_m * math.cos(a), radius_m * math.sin(a), height_m])
        T_world_cam = look_at_T_world_cam(pos, np.array([0.0, 0.0, 0.3]))
        cams.append(CameraModel(f"ring{i:02d}", template.width, template.height,
                                template.K.copy(), template.dist.copy(),
                                invert_transform(T_world_cam)))
    return cams


__all__ = ["ring_cameras"]
