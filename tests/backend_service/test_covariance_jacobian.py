"""The propagated covariance's extrinsic derivative in closed form, against finite differences.

The reference is the definition the error model uses (:mod:`backend_service.covariance`): the
camera's ``T_world_cam`` rotated about its optical centre by a rotation vector in world axes and
moved, then projected by :class:`core.camera.CameraModel` itself; central differences of
that, per camera, are what the vectorized closed form must reproduce.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from backend_service.covariance import (
    ErrorModel,
    project_with_extrinsic_jacobian,
    propagate_correlated,
)
from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rotvec
from tests.backend_service.pose_synth import ROBOT, example_site

SITE = example_site()
KP_BASE = np.asarray(SITE.robot_model(ROBOT).keypoints_base_m, dtype=np.float64)
STRONG_LENS = np.array([-0.28, 0.09, 0.002, -0.003, -0.015, 0.01, -0.004, 0.002])


def _moved(camera: CameraModel, rotvec: np.ndarray, dt_m: np.ndarray) -> CameraModel:
    T_world_cam = camera.T_world_cam.copy()
    T_world_cam[:3, :3] = rotation_from_rotvec(rotvec) @ T_world_cam[:3, :3]
    T_world_cam[:3, 3] += dt_m
    return dataclasses.replace(camera, T_cam_world=invert_transform(T_world_cam))


def _numeric_jacobian(camera: CameraModel, points_world: np.ndarray) -> np.ndarray:
    """(M, 2, 6) central differences of the projection over (rotation, position)."""
    eps = 1e-6
    cols = []
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        uv_plus, _ = _moved(camera, step[:3], step[3:]).project(points_world)
        uv_minus, _ = _moved(camera, -step[:3], -step[3:]).project(points_world)
        cols.append((uv_plus - uv_minus) / (2 * eps))
    return np.stack(cols, axis=-1)


def _cameras(with_strong_lens: bool) -> list[CameraModel]:
    cams = list(SITE.cameras.values())
    if with_strong_lens:
        cams = [dataclasses.replace(c, dist=STRONG_LENS) for c in cams]
    return cams


@pytest.mark.parametrize("with_strong_lens", [False, True])
def test_closed_form_matches_central_differences(with_strong_lens: bool) -> None:
    cams = _cameras(with_strong_lens)
    pts = KP_BASE + np.array([10.0, 6.0, 0.0])
    uv, G = project_with_extrinsic_jacobian(cams, pts)
    assert uv.shape == (len(cams), len(pts), 2) and G.shape == (len(cams), len(pts), 2, 6)
    for c, cam in enumerate(cams):
        uv_ref, depth = cam.project(pts)
        front = depth > 0
        np.testing.assert_allclose(uv[c][front], uv_ref[front], atol=1e-9)
        scale = np.abs(G[c][front]).max()
        np.testing.assert_allclose(G[c][front], _numeric_jacobian(cam, pts)[front],
                                   atol=1e-6 * scale)


def _loop_reference(A: np.ndarray, cams: list[CameraModel], pts: np.ndarray,
                    weights: np.ndarray, model: ErrorModel) -> tuple[np.ndarray, np.ndarray]:
    """The error model's propagation written camera by camera, with numeric Jacobians."""
    n, M = A.shape[0], len(pts)
    frame, systematic = np.zeros((n, n)), np.zeros((n, n))
    s_rot = math.radians(model.extrinsic_sigma_deg)
    for c, cam in enumerate(cams):
        used = weights[c] > 0
        if not used.any():
            continue
        Ac = A[:, 2 * M * c:2 * M * (c + 1)]
        uv, _ = cam.project(pts)
        AG = Ac @ np.tile(np.eye(2), (M, 1))
        frame += model.detection_shift_sigma_px ** 2 * AG @ AG.T
        g = np.where(used[:, None], uv - uv[used].mean(axis=0), 0.0).reshape(-1)
        frame += model.detection_scale_sigma ** 2 * np.outer(Ac @ g, Ac @ g)
        G = np.where(used[:, None, None], _numeric_jacobian(cam, pts), 0.0).reshape(2 * M, 6)
        S = np.diag([s_rot ** 2] * 3 + [model.extrinsic_sigma_m ** 2] * 3)
        systematic += Ac @ G @ S @ G.T @ Ac.T
    return frame, systematic


def test_propagation_equals_the_per_camera_definition() -> None:
    rng = np.random.default_rng(4)
    cams = _cameras(with_strong_lens=True)
    pts = KP_BASE + np.array([9.5, 6.5, 0.0])
    M = len(pts)
    weights = rng.uniform(0.2, 1.0, (len(cams), M))
    weights[1, ::3] = 0.0  # some keypoints unused
    weights[2] = 0.0  # a camera without a used keypoint
    A = rng.normal(0.0, 1e-3, (3, 2 * M * len(cams)))
    A[:, np.repeat(weights.reshape(-1) == 0, 2)] = 0.0  # as the solve builds it
    model = ErrorModel(detection_shift_sigma_px=1.5, detection_scale_sigma=0.02,
                       extrinsic_sigma_m=0.01, extrinsic_sigma_deg=0.3)
    frame, systematic = propagate_correlated(A, cams, pts, weights, model)
    frame_ref, systematic_ref = _loop_reference(A, cams, pts, weights, model)
    np.testing.assert_allclose(frame, frame_ref, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(systematic, systematic_ref, rtol=1e-6, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(systematic) > 0)


def test_nothing_to_propagate_gives_zeros() -> None:
    cams = _cameras(with_strong_lens=False)
    A = np.ones((3, 2 * len(KP_BASE) * len(cams)))
    w = np.ones((len(cams), len(KP_BASE)))
    pts = KP_BASE + np.array([10.0, 6.0, 0.0])
    frame, systematic = propagate_correlated(A, cams, pts, w, ErrorModel())
    assert not frame.any() and not systematic.any()
