"""The one projection of world points into cameras with its Jacobians, in closed form.

The backend's covariances (:mod:`backend_service.covariance`: the extrinsic Jacobian), its
camera-health monitor and the robot-target calibration (:mod:`calibration.robot_problem`) all
use :func:`project_world_points`. Pure numpy, vectorized: every array broadcasts along its
leading axes, so one call projects M points into C cameras (camera arrays shaped (C, 1, ...),
points (1, M, 3)) or n observations each through its own camera (all arrays (n, ...)).

Conventions: a camera is ``R_wc`` (..., 3, 3), its rotation camera → world, and ``c_w``
(..., 3), its optical centre in the world (metres); ``K`` (..., 3, 3) the intrinsics,
``dist`` (..., D) OpenCV's distortion coefficients (D = 0, 4, 5 or 8). A camera's pose is
perturbed on the left, about its optical centre: R' = Exp(w) R, c' = c + dc, with ``w`` (rad)
and ``dc`` (m) in world axes. With a = p - c the camera-frame point p_cam = R^T a moves by
R^T [a]x dw - R^T dc; the chain rule through the perspective division, the lens distortion
(:func:`core.geometry.distort_normalized_jacobian`) and the focal lengths gives the derivative.
"""

from __future__ import annotations

import dataclasses
from typing import Final

import numpy as np

from core.geometry import distort_normalized, distort_normalized_jacobian

#: a point this close to the camera plane (m) or behind it has no pixel (NaN), unless the
#: caller clamps the depth (``min_depth_m``)
IN_FRONT_M: Final = 1e-9
#: the depth (m) the calibration solvers clamp to (``min_depth_m``): a point a bad step put at
#: or behind a camera keeps finite pixels and derivatives, and a large residual
SOLVER_MIN_DEPTH_M: Final = 1e-3


@dataclasses.dataclass(frozen=True, eq=False)
class PixelProjection:
    """Where points land in cameras, and how that moves.

    ``uv`` (..., 2): distorted pixels; ``depth_m`` (...): depth in the camera frame (negative
    behind it); ``d_uv_d_camera`` (..., 2, 6): d(u, v)/d(w, dc) of the camera's pose (module
    docstring); ``d_uv_d_point`` (..., 2, 3): d(u, v)/d(the world point). The derivatives are
    ``None`` when not asked for."""

    uv: np.ndarray
    depth_m: np.ndarray
    d_uv_d_camera: np.ndarray | None = None
    d_uv_d_point: np.ndarray | None = None


def project_world_points(R_wc: np.ndarray, c_w: np.ndarray, K: np.ndarray, dist: np.ndarray,
                         points_world: np.ndarray, *, jacobians: bool = True,
                         min_depth_m: float | None = None) -> PixelProjection:
    """Project ``points_world`` (..., 3) through the cameras (module docstring for the shapes).

    ``min_depth_m``: ``None`` (the default) gives NaN pixels and derivatives for points at or
    behind the camera plane; a value clamps the depth to it instead, so an optimizer always
    sees finite values (the true depth is still returned, to mask such points)."""
    R = np.asarray(R_wc, dtype=np.float64)
    a = np.asarray(points_world, dtype=np.float64) - np.asarray(c_w, dtype=np.float64)
    p_cam = np.einsum("...ji,...j->...i", R, a)  # R^T a
    z = p_cam[..., 2]
    if min_depth_m is None:
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.where(z > IN_FRONT_M, 1.0 / z, np.nan)
    else:
        inv_z = 1.0 / np.maximum(z, min_depth_m)
    xy = p_cam[..., :2] * inv_z[..., None]
    K = np.asarray(K, dtype=np.float64)
    focal, principal = K[..., :2, :2], K[..., :2, 2]
    xy_d = distort_normalized(xy, dist)
    uv = np.einsum("...ij,...j->...i", focal, xy_d) + principal
    if not jacobians:
        return PixelProjection(uv, z)
    # d(x, y)/d(p_cam): [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    d_xy = np.zeros((*xy.shape[:-1], 2, 3))
    d_xy[..., 0, 0] = inv_z
    d_xy[..., 1, 1] = inv_z
    d_xy[..., :, 2] = -xy * inv_z[..., None]
    d_uv_p = np.einsum("...ij,...jk,...kl->...il", focal,
                       distort_normalized_jacobian(xy, dist), d_xy)  # wrt the camera-frame point
    d_uv_a = np.einsum("...ij,...kj->...ik", d_uv_p, R)  # wrt a (world axes): d_uv_p @ R^T
    G = np.empty((*d_uv_a.shape[:-1], 6))
    G[..., 0:3] = np.cross(d_uv_a, a[..., None, :])  # row . (a x dw) = (row x a) . dw
    G[..., 3:] = -d_uv_a
    return PixelProjection(uv, z, G, d_uv_a)


__all__ = ["IN_FRONT_M", "SOLVER_MIN_DEPTH_M", "PixelProjection", "project_world_points"]
