"""The pose problem's projection in plain numpy, vectorized over cameras (and poses): the
same residuals as the CasADi formulation of :mod:`backend_service.pose_solver`, for
solver-independent evaluation (single-camera refinement, the benchmark's pyceres/scipy peers,
the Cramér-Rao bound, tests), and the cameras stacked once for it (also the propagated
covariance's closed-form Jacobian, :mod:`backend_service.covariance`).

Frames: world (= map), z up; camera optical frame (OpenCV: z forward). Pixels (u, v).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import numpy as np

from core.camera import CameraModel
from core.geometry import distort_normalized


@dataclasses.dataclass(frozen=True, eq=False)
class StackedCameras:
    """N cameras' calibration stacked for vectorized projection: ``R_cw`` (N, 3, 3), ``t_cw``
    (N, 3), ``K`` (N, 3, 3), ``dist`` (N, 8) (zero-padded OpenCV coefficients)."""

    R_cw: np.ndarray
    t_cw: np.ndarray
    K: np.ndarray
    dist: np.ndarray

    @functools.cached_property
    def centre_world(self) -> np.ndarray:
        """(N, 3) optical centres in world coordinates, metres."""
        return -np.einsum("nji,nj->ni", self.R_cw, self.t_cw)

    @classmethod
    def from_cameras(cls, cameras: Sequence[CameraModel]) -> StackedCameras:
        dist = np.zeros((len(cameras), 8))
        for i, cam in enumerate(cameras):
            dist[i, : cam.dist.size] = cam.dist
        return cls(
            np.stack([c.T_cam_world[:3, :3] for c in cameras]),
            np.stack([c.T_cam_world[:3, 3] for c in cameras]),
            np.stack([c.K for c in cameras]),
            dist,
        )


@functools.lru_cache(maxsize=64)
def stacked_cameras(cameras: tuple[CameraModel, ...]) -> StackedCameras:
    """:meth:`StackedCameras.from_cameras`, cached by the cameras themselves (a
    :class:`CameraModel` compares by identity: the site's cameras are the keys)."""
    return StackedCameras.from_cameras(cameras)


def project_planar(cams: StackedCameras, keypoints_base_m: np.ndarray,
                   q_batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project the robot keypoints for B planar poses.

    ``keypoints_base_m`` (M, 3) base frame; ``q_batch`` (B, 3) of (x, y, theta) in the world
    frame. Returns pixels (B, N, M, 2) and depths (B, N, M) in metres (the depth is clamped
    like the CasADi formulation only for the division, so points behind give finite pixels).
    """
    q = np.asarray(q_batch, dtype=np.float64).reshape(-1, 3)
    c, s = np.cos(q[:, 2]), np.sin(q[:, 2])
    kp = np.asarray(keypoints_base_m, dtype=np.float64)
    # world points (B, M, 3)
    xw = c[:, None] * kp[None, :, 0] - s[:, None] * kp[None, :, 1] + q[:, 0, None]
    yw = s[:, None] * kp[None, :, 0] + c[:, None] * kp[None, :, 1] + q[:, 1, None]
    zw = np.broadcast_to(kp[None, :, 2], xw.shape)
    pw = np.stack([xw, yw, zw], axis=-1)
    pc = np.einsum("nij,bmj->bnmi", cams.R_cw, pw) + cams.t_cw[None, :, None, :]
    return pixels_from_camera_frame(pc, cams.K[None, :, None], cams.dist[None, :, None, :])


def pixels_from_camera_frame(pc: np.ndarray, K: np.ndarray, dist: np.ndarray
                             ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (..., 2) and depths (...) of camera-frame points ``pc`` (..., 3): the pinhole
    with the lens distortion, ``K`` (..., 3, 3) and ``dist`` (..., k) broadcast against the
    points' leading axes (the depth is clamped at 1 mm only for the division, as the CasADi
    formulation does)."""
    z = pc[..., 2]
    zs = np.maximum(z, 1e-3)
    xy = pc[..., :2] / zs[..., None]
    xyd = distort_normalized(xy, dist)
    xd, yd = xyd[..., 0], xyd[..., 1]
    u = K[..., 0, 0] * xd + K[..., 0, 1] * yd + K[..., 0, 2]
    v = K[..., 1, 1] * yd + K[..., 1, 2]
    return np.stack([u, v], axis=-1), z


def weighted_residuals(cams: StackedCameras, keypoints_base_m: np.ndarray, q_batch: np.ndarray,
                       keypoints_px: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(B, 2*N*M) residuals sqrt(w_ij) * (Pi_i(.) - k_ij), ordered camera, keypoint, (u, v):
    the layout of the CasADi formulation. ``keypoints_px`` (N, M, 2) must be finite where
    ``weights`` (N, M) is non-zero."""
    uv_hat, _ = project_planar(cams, keypoints_base_m, q_batch)
    obs = np.where(np.isfinite(keypoints_px), keypoints_px, 0.0)
    err = (uv_hat - obs[None]) * np.sqrt(weights)[None, :, :, None]
    return err.reshape(err.shape[0], -1)


def numeric_jacobian(cams: StackedCameras, keypoints_base_m: np.ndarray, q: np.ndarray,
                     keypoints_px: np.ndarray, weights: np.ndarray,
                     step: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (2NM,) and their central-difference Jacobian (2NM, 3) at pose ``q`` (3,),
    evaluated in one batched call."""
    q = np.asarray(q, dtype=np.float64)
    batch = np.repeat(q[None], 7, axis=0)
    for k in range(3):
        batch[1 + 2 * k, k] += step
        batch[2 + 2 * k, k] -= step
    r = weighted_residuals(cams, keypoints_base_m, batch, keypoints_px, weights)
    J = np.stack([(r[1 + 2 * k] - r[2 + 2 * k]) / (2 * step) for k in range(3)], axis=1)
    return r[0], J
