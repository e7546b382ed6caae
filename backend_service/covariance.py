"""Honest covariances of camera pose estimates: the error model propagated through the solve.

The Gauss-Newton covariance s^2 (J^T W J)^-1 assumes every keypoint's pixel error is independent.
Two error sources are not, and they dominate what the solve gets wrong:

- **per detection** (``detection_shift_sigma_px``, ``detection_scale_sigma``): a top-down
  detector crops, resizes and locates every keypoint of one robot together, so a crop error
  shifts all keypoints by the same offset and scales them about their centroid. Seen by one
  camera, a 2.5 % scale error is a 2.5 % range error (12 cm at 5 m) the residuals never show;
- **per camera** (``extrinsic_sigma_m``, ``extrinsic_sigma_deg``): the calibrated camera pose
  differs from the true one. Every frame of that camera carries the same error, so averaging
  frames does not reduce it (it is the *systematic* part).

A solution q = argmin sum w e^2 moves, to first order, by dq = -(J^T W J)^-1 J^T W de for a pixel
perturbation de. With Cov(de) = G Sigma G^T for each correlated source (G: how that source moves
the predicted keypoints), Cov(q) = A G Sigma G^T A^T, A = (J^T W J)^-1 J^T W. The result
splits into the part that is new in every frame (independent + per detection) and the
systematic part (extrinsics); :class:`backend_service.multi_frame.MultiFrameAverager` averages
only the first down.

:func:`fuse_with_prior` is the single-camera MAP treatment built on it: the plain solve as a
Gaussian measurement with this covariance (weak along the viewing ray), the prior as a Gaussian
with its own, combined by information (the first-order MAP solution), with a consistency gate.
Pure numpy, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Final

import numpy as np

from backend_service.projection import stacked_cameras
from core.camera import CameraModel
from core.geometry import wrap_angle
from core.projection import project_world_points

__all__ = [
    "CovarianceParts",
    "ErrorModel",
    "fuse_with_prior",
    "project_with_extrinsic_jacobian",
    "propagate_correlated",
]

#: chi-square(3) 99.9 % quantile: a plain solve and a prior further apart (Mahalanobis, with
#: both covariances) than this contradict each other; the prior is then not used
PRIOR_GATE_CHI2: Final = 16.27


@dataclasses.dataclass(frozen=True)
class ErrorModel:
    """Correlated keypoint errors the covariance accounts for (see the module docstring)."""

    detection_shift_sigma_px: float = 0.0
    detection_scale_sigma: float = 0.0
    extrinsic_sigma_m: float = 0.0
    extrinsic_sigma_deg: float = 0.0

    @property
    def any(self) -> bool:
        return any(v > 0 for v in dataclasses.astuple(self))


@dataclasses.dataclass(frozen=True)
class CovarianceParts:
    """(n, n) covariances of the solution: ``frame`` (new in every frame: independent keypoint
    noise + per-detection errors) and ``systematic`` (the same in every frame of these cameras:
    extrinsic calibration). ``total`` = frame + systematic."""

    frame: np.ndarray
    systematic: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return self.frame + self.systematic

    def sub(self, idx: Sequence[int]) -> CovarianceParts:
        ix = np.ix_(list(idx), list(idx))
        return CovarianceParts(self.frame[ix], self.systematic[ix])


def project_with_extrinsic_jacobian(cameras: Sequence[CameraModel], points_world: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of ``points_world`` (M, 3) in every camera and their derivative with respect to
    each camera's pose, in closed form and vectorized over cameras.

    Returns ``uv`` (C, M, 2) distorted pixels (NaN behind a camera) and ``G`` (C, M, 2, 6):
    d(u, v)/d(rotation of the camera about its optical centre (rad, world axes), position of
    the camera (m, world axes)), from the one projection with Jacobians
    (:func:`core.projection.project_world_points`).
    """
    stack = stacked_cameras(tuple(cameras))
    P = np.asarray(points_world, dtype=np.float64).reshape(1, -1, 3)
    proj = project_world_points(np.swapaxes(stack.R_cw, 1, 2)[:, None], stack.centre_world[:, None],
                                stack.K[:, None], stack.dist[:, None], P)
    assert proj.d_uv_d_camera is not None
    return proj.uv, proj.d_uv_d_camera


def propagate_correlated(A: np.ndarray, cameras: Sequence[CameraModel],
                         points_world: np.ndarray, weights: np.ndarray,
                         model: ErrorModel) -> tuple[np.ndarray, np.ndarray]:
    """Covariances (per frame, systematic) of the solution from the correlated error sources.

    ``A``: (n, 2CM) sensitivity of the solution to the raw pixel residuals (camera-major, u/v
    interleaved per keypoint, zero columns for unused keypoints); ``points_world``: (M, 3)
    keypoints at the solution; ``weights``: (C, M) > 0 where a keypoint was used. Vectorized
    over cameras: one pass of array operations whatever the number of cameras."""
    n = A.shape[0]
    C = len(cameras)
    frame = np.zeros((n, n))
    systematic = np.zeros((n, n))
    if C == 0 or not model.any:
        return frame, systematic
    M = points_world.shape[0]
    used = np.asarray(weights).reshape(C, M) > 0  # (C, M)
    A4 = A.reshape(n, C, M, 2)
    s_rot = math.radians(model.extrinsic_sigma_deg)
    need_extrinsic = model.extrinsic_sigma_m > 0 or s_rot > 0
    if model.detection_scale_sigma > 0 or need_extrinsic:
        uv, G = project_with_extrinsic_jacobian(cameras, points_world)
    if model.detection_shift_sigma_px > 0:
        AG = A4.sum(axis=2).reshape(n, 2 * C)  # every keypoint moves by the same offset
        frame += model.detection_shift_sigma_px ** 2 * AG @ AG.T
    if model.detection_scale_sigma > 0:
        count = np.maximum(used.sum(axis=1), 1)[:, None]
        centroid = np.where(used[..., None], uv, 0.0).sum(axis=1) / count  # (C, 2)
        g = np.where(used[..., None], uv - centroid[:, None, :], 0.0)  # (C, M, 2)
        ag = np.einsum("ncmk,cmk->nc", A4, g)
        frame += model.detection_scale_sigma ** 2 * ag @ ag.T
    if need_extrinsic:
        G = np.where(used[..., None, None], G, 0.0)  # unused keypoints may be behind (NaN)
        AG = np.einsum("ncmk,cmkj->ncj", A4, G).reshape(n, C * 6)
        S = np.tile([s_rot ** 2] * 3 + [model.extrinsic_sigma_m ** 2] * 3, C)
        systematic += (AG * S) @ AG.T
    return frame, systematic


@dataclasses.dataclass(frozen=True)
class PriorFusion:
    """Outcome of :func:`fuse_with_prior`: ``q`` (3,) and its ``parts``; ``used``: the prior
    was consistent with the solve and went in; ``mahalanobis2``: their squared distance."""

    q: np.ndarray
    parts: CovarianceParts
    used: bool
    mahalanobis2: float


def fuse_with_prior(q_solve: np.ndarray, parts: CovarianceParts, q_prior: np.ndarray,
                    cov_prior: np.ndarray, gate_chi2: float = PRIOR_GATE_CHI2) -> PriorFusion:
    """The MAP combination of a planar solve (x, y, theta) and an independent prior.

    q = (C^-1 + P^-1)^-1 (C^-1 q_solve + P^-1 q_prior) with C the solve's covariance and P the
    prior's. The result's systematic part keeps what
    does not average over frames: the solve's systematic part and the whole prior term (every
    frame of a stop uses the same prior). When the two disagree beyond ``gate_chi2`` the prior
    is not used (it is the one more likely wrong: the solve fit the image)."""
    C = parts.total
    d = np.asarray(q_solve, np.float64) - np.asarray(q_prior, np.float64)
    d[2] = wrap_angle(float(d[2]))
    try:
        m2 = float(d @ np.linalg.solve(C + cov_prior, d))
        Ci = np.linalg.inv(C)
        Pi = np.linalg.inv(cov_prior)
        Cm = np.linalg.inv(Ci + Pi)
    except np.linalg.LinAlgError:
        return PriorFusion(np.asarray(q_solve, np.float64), parts, False, math.inf)
    if not (math.isfinite(m2) and m2 <= gate_chi2):
        return PriorFusion(np.asarray(q_solve, np.float64), parts, False, m2)
    Kc, Kp = Cm @ Ci, Cm @ Pi
    q = np.asarray(q_prior, np.float64) + Kc @ d
    q[2] = wrap_angle(float(q[2]))
    frame = Kc @ parts.frame @ Kc.T
    systematic = Kc @ parts.systematic @ Kc.T + Kp @ cov_prior @ Kp.T
    return PriorFusion(q, CovarianceParts(frame, systematic), True, m2)


def valid_covariance(cov: object, n: int = 3) -> np.ndarray | None:
    """``cov`` as a finite, symmetric positive-definite (n, n) array, else ``None``."""
    if cov is None:
        return None
    try:
        arr = np.asarray(cov, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if arr.shape != (n, n) or not np.all(np.isfinite(arr)):
        return None
    arr = 0.5 * (arr + arr.T)
    try:
        np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        return None
    return arr
