"""The one projection with Jacobians: pixels as OpenCV computes them, derivatives as finite
differences say, the same figures in both batch layouts, and points behind a camera."""

from __future__ import annotations

import numpy as np
import pytest

from core.geometry import rotation_from_rotvec
from core.projection import project_world_points

cv2 = pytest.importorskip("cv2")

DIST = np.array([-0.21, 0.08, 0.001, -0.002, -0.015])


def _cameras(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n cameras 3-5 m above the origin looking down, slightly tilted: R_wc, c_w, K (no skew:
    OpenCV's projectPoints ignores it)."""
    down = np.diag([1.0, -1.0, -1.0])  # camera z along world -z
    R = np.stack([rotation_from_rotvec(rng.normal(0, 0.2, 3)) @ down for _ in range(n)])
    c = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(3, 5, n)])
    K = np.tile(np.array([[610.0, 0.0, 322.0], [0.0, 605.0, 241.0], [0.0, 0.0, 1.0]]), (n, 1, 1))
    return R, c, K


def test_pixels_are_opencvs() -> None:
    rng = np.random.default_rng(1)
    R, c, K = _cameras(rng, 3)
    P = rng.uniform(-1, 1, (7, 3)) * [1, 1, 0.5]
    proj = project_world_points(R[:, None], c[:, None], K[:, None], DIST, P[None])
    for i in range(3):
        R_cw = R[i].T
        rvec, _ = cv2.Rodrigues(R_cw)
        ref, _ = cv2.projectPoints(P, rvec, -R_cw @ c[i], K[i], DIST)
        np.testing.assert_allclose(proj.uv[i], ref.reshape(-1, 2), atol=1e-9)
        np.testing.assert_allclose(proj.depth_m[i], (P - c[i]) @ R[i][:, 2], atol=1e-12)


def test_derivatives_are_the_finite_differences() -> None:
    rng = np.random.default_rng(2)
    R, c, K = _cameras(rng, 1)
    P = rng.uniform(-1, 1, (5, 3))
    base = project_world_points(R[0], c[0], K[0], DIST, P)
    h = 1e-6
    for k in range(6):
        step = np.zeros(6)
        step[k] = h

        def moved(s: np.ndarray) -> np.ndarray:
            return project_world_points(rotation_from_rotvec(s[:3]) @ R[0], c[0] + s[3:], K[0],
                                        DIST, P, jacobians=False).uv

        fd = (moved(step) - moved(-step)) / (2 * h)
        np.testing.assert_allclose(base.d_uv_d_camera[:, :, k], fd, rtol=1e-5, atol=1e-4)
    for k in range(3):
        dp = np.zeros(3)
        dp[k] = h
        fd = (project_world_points(R[0], c[0], K[0], DIST, P + dp, jacobians=False).uv
              - project_world_points(R[0], c[0], K[0], DIST, P - dp, jacobians=False).uv) / (2 * h)
        np.testing.assert_allclose(base.d_uv_d_point[:, :, k], fd, rtol=1e-5, atol=1e-4)


def test_cameras_by_points_equals_one_camera_per_observation() -> None:
    rng = np.random.default_rng(3)
    R, c, K = _cameras(rng, 4)
    P = rng.uniform(-1, 1, (6, 3))
    grid = project_world_points(R[:, None], c[:, None], K[:, None], DIST, P[None])
    cam, pt = np.divmod(np.arange(24), 6)
    flat = project_world_points(R[cam], c[cam], K[cam], DIST, P[pt])
    np.testing.assert_allclose(grid.uv.reshape(-1, 2), flat.uv, atol=1e-9)
    np.testing.assert_allclose(grid.d_uv_d_camera.reshape(-1, 2, 6), flat.d_uv_d_camera,
                               atol=1e-9)


def test_a_point_behind_the_camera_has_no_pixel_unless_the_depth_is_clamped() -> None:
    rng = np.random.default_rng(4)
    R, c, K = _cameras(rng, 1)
    behind = c[0] + 2.0 * R[0][:, 2] * -1.0  # 2 m behind the camera
    P = np.stack([np.zeros(3), behind])
    free = project_world_points(R[0], c[0], K[0], DIST, P)
    assert np.isfinite(free.uv[0]).all() and np.isnan(free.uv[1]).all()
    assert free.depth_m[1] == pytest.approx(-2.0)
    clamped = project_world_points(R[0], c[0], K[0], DIST, P, min_depth_m=1e-3)
    assert np.isfinite(clamped.uv).all() and np.isfinite(clamped.d_uv_d_camera).all()
    assert clamped.depth_m[1] == pytest.approx(-2.0)  # the true depth, to mask it
