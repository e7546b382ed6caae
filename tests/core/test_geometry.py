"""core.geometry: identities of angles, SE(2), quaternions and rotations; the distortion model
against OpenCV; the static detector."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.geometry import (
    MotionState,
    StaticDetector,
    angle_diff,
    distort_normalized,
    distort_normalized_jacobian,
    invert_transform,
    lens_fold_radius,
    quaternion_to_rotation,
    quaternion_to_yaw,
    rotation_from_rotvec,
    rotation_from_rpy,
    rotation_to_quaternion,
    rotation_z,
    rpy_from_rotation,
    se2_between,
    se2_compose,
    se2_from_matrix,
    se2_inverse,
    se2_matrix,
    se3_from_planar,
    wrap_angle,
    wrap_angle_array,
    yaw_from_rotation,
    yaw_to_quaternion,
    yaw_to_quaternion_array,
)
from core.site import Thresholds

ANGLES = st.floats(-1e4, 1e4, allow_nan=False)
SMALL_ANGLES = st.floats(-3.0 * math.pi, 3.0 * math.pi, allow_nan=False)
COORDS = st.floats(-100.0, 100.0, allow_nan=False)
POSES = st.tuples(COORDS, COORDS, SMALL_ANGLES).map(np.array)
S = 1_000_000_000


def _same_angle(a: float, b: float, tol: float = 1e-9) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) <= tol


# --------------------------------------------------------------------------------------------
# angles
# --------------------------------------------------------------------------------------------


@given(ANGLES)
def test_wrap_range_idempotence_and_equivalence(a: float) -> None:
    w = wrap_angle(a)
    assert -math.pi <= w < math.pi
    assert wrap_angle(w) == w  # exact: the remainder is computed without rounding
    assert _same_angle(w, a, 1e-12 * max(1.0, abs(a)))


@given(st.lists(ANGLES, min_size=0, max_size=20))
def test_wrap_array_is_the_scalar_bit_for_bit(angles: list[float]) -> None:
    out = wrap_angle_array(np.array(angles, dtype=np.float64))
    assert out.shape == (len(angles),)
    assert [float(v) for v in out] == [wrap_angle(a) for a in angles]


def test_wrap_convention_at_the_boundary() -> None:
    assert wrap_angle(math.pi) == -math.pi
    assert wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(3 * math.pi) == -math.pi
    assert wrap_angle(math.pi - 1e-12) == pytest.approx(math.pi - 1e-12)
    assert wrap_angle(-1e-300) == -1e-300  # no rounding up to 2 pi
    assert float(wrap_angle_array(math.pi)) == -math.pi
    assert math.isnan(wrap_angle(math.inf)) and math.isnan(wrap_angle(math.nan))
    assert np.isnan(wrap_angle_array([math.inf, math.nan])).all()


@given(SMALL_ANGLES, SMALL_ANGLES)
def test_angle_diff_is_the_signed_shortest_rotation(a: float, b: float) -> None:
    d = angle_diff(a, b)
    assert -math.pi <= d < math.pi
    assert _same_angle(b + d, a)
    assert abs(angle_diff(b, a) + d) < 1e-9 or abs(abs(d) - math.pi) < 1e-9


# --------------------------------------------------------------------------------------------
# rotations and quaternions
# --------------------------------------------------------------------------------------------


@given(SMALL_ANGLES)
def test_yaw_quaternion_round_trip(yaw: float) -> None:
    q = yaw_to_quaternion(yaw)
    assert math.isclose(math.hypot(*q), 1.0)
    assert _same_angle(quaternion_to_yaw(*q), yaw)
    assert -math.pi <= quaternion_to_yaw(*q) < math.pi
    np.testing.assert_allclose(yaw_to_quaternion_array(np.array([yaw]))[0], q)
    np.testing.assert_allclose(quaternion_to_rotation(np.array(q)), rotation_z(yaw), atol=1e-12)


@given(SMALL_ANGLES, st.floats(0.1, 10.0))
def test_quaternion_to_yaw_ignores_scale_and_sign(yaw: float, scale: float) -> None:
    q = np.array(yaw_to_quaternion(yaw))
    assert _same_angle(quaternion_to_yaw(*(scale * q)), yaw)
    assert _same_angle(quaternion_to_yaw(*(-q)), yaw)


def test_quaternion_to_yaw_rejects_zero_and_nan() -> None:
    with pytest.raises(ValueError):
        quaternion_to_yaw(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        quaternion_to_yaw(0.0, 0.0, math.nan, 1.0)


@given(st.floats(-3.0, 3.0), st.floats(-1.5, 1.5), SMALL_ANGLES)
def test_rotation_rpy_and_quaternion_round_trips(roll: float, pitch: float, yaw: float) -> None:
    R = rotation_from_rpy(roll, pitch, yaw)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    r2, p2, y2 = rpy_from_rotation(R)
    np.testing.assert_allclose(rotation_from_rpy(r2, p2, y2), R, atol=1e-9)
    q = rotation_to_quaternion(R)
    assert q[3] >= 0.0 and math.isclose(math.hypot(*q), 1.0)
    np.testing.assert_allclose(quaternion_to_rotation(np.array(q)), R, atol=1e-12)
    assert _same_angle(yaw_from_rotation(rotation_z(yaw)), yaw)


@given(st.tuples(*[st.floats(-2.0, 2.0)] * 3))
def test_rotvec_matches_opencv_rodrigues(v: tuple[float, float, float]) -> None:
    cv2 = pytest.importorskip("cv2")
    R_cv, _ = cv2.Rodrigues(np.array(v, dtype=np.float64))
    np.testing.assert_allclose(rotation_from_rotvec(np.array(v)), R_cv, atol=1e-12)


def test_quaternion_to_rotation_is_batched() -> None:
    yaws = np.linspace(-3, 3, 7)
    Rs = quaternion_to_rotation(yaw_to_quaternion_array(yaws))
    assert Rs.shape == (7, 3, 3)
    for R, yaw in zip(Rs, yaws, strict=True):
        np.testing.assert_allclose(R, rotation_z(yaw), atol=1e-12)


# --------------------------------------------------------------------------------------------
# SE(2) and SE(3)
# --------------------------------------------------------------------------------------------


def _close_pose(a: np.ndarray, b: np.ndarray, tol: float = 1e-8) -> bool:
    return bool(np.allclose(a[:2], b[:2], atol=tol) and _same_angle(a[2], b[2], tol))


@given(POSES)
def test_se2_compose_with_inverse_is_identity(a: np.ndarray) -> None:
    assert _close_pose(se2_compose(a, se2_inverse(a)), np.zeros(3))
    assert _close_pose(se2_compose(se2_inverse(a), a), np.zeros(3))
    assert _close_pose(se2_inverse(se2_inverse(a)), a)


@given(POSES, POSES, POSES)
def test_se2_compose_is_associative_and_matches_matrices(a, b, c) -> None:
    ab = se2_compose(a, b)
    assert _close_pose(se2_compose(ab, c), se2_compose(a, se2_compose(b, c)), 1e-7)
    np.testing.assert_allclose(se2_matrix(*ab), se2_matrix(*a) @ se2_matrix(*b), atol=1e-9)
    assert _close_pose(se2_from_matrix(se2_matrix(*a)), a)
    assert -math.pi <= ab[2] < math.pi


@given(POSES, POSES)
def test_se2_between_undoes_compose(a: np.ndarray, b: np.ndarray) -> None:
    assert _close_pose(se2_compose(a, se2_between(a, b)), b, 1e-7)
    assert _close_pose(se2_between(a, se2_compose(a, b)), b, 1e-7)


@given(POSES)
def test_planar_se3_agrees_with_se2(a: np.ndarray) -> None:
    T = se3_from_planar(*a)
    m = se2_matrix(*a)
    np.testing.assert_allclose(T[:2, :2], m[:2, :2])
    np.testing.assert_allclose(T[:2, 3], m[:2, 2])
    assert T[2, 2] == 1.0 and T[2, 3] == 0.0
    assert _close_pose(se2_from_matrix(T), a)
    np.testing.assert_allclose(invert_transform(T) @ T, np.eye(4), atol=1e-9)


@given(st.tuples(*[st.floats(-3.0, 3.0)] * 3), st.tuples(*[COORDS] * 3))
def test_invert_transform(rpy, t) -> None:
    T = np.eye(4)
    T[:3, :3] = rotation_from_rpy(*rpy)
    T[:3, 3] = t
    np.testing.assert_allclose(invert_transform(T), np.linalg.inv(T), atol=1e-9)


# --------------------------------------------------------------------------------------------
# distortion
# --------------------------------------------------------------------------------------------

DIST_COEFFS = st.tuples(
    st.floats(-0.5, 0.5), st.floats(-0.3, 0.3), st.floats(-0.01, 0.01), st.floats(-0.01, 0.01),
    st.floats(-0.1, 0.1),
)


@settings(max_examples=60, deadline=None)
@given(DIST_COEFFS, st.integers(0, 2**31), st.sampled_from([0, 4, 5, 8]))
def test_distortion_matches_opencv_project_points(coeffs, seed: int, n: int) -> None:
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(seed)
    dist = np.array([*coeffs, 0.02, -0.01, 0.005])[:n]
    pts = np.column_stack([rng.uniform(-0.6, 0.6, (40, 2)), np.ones(40)]) * rng.uniform(
        0.5, 10.0, (40, 1))
    K = np.eye(3)  # identity intrinsics: OpenCV returns the distorted normalized coordinates
    uv_cv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, dist)
    ours = distort_normalized(pts[:, :2] / pts[:, 2:], dist)
    np.testing.assert_allclose(ours, uv_cv.reshape(-1, 2), rtol=1e-9, atol=1e-12)


def test_distortion_broadcasts_one_row_per_camera() -> None:
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.5, 0.5, (3, 2, 6, 2))  # (batch, camera, keypoint, 2)
    dist = np.zeros((2, 8))
    dist[0, :5] = [0.1, -0.05, 0.001, -0.002, 0.01]
    dist[1, :8] = [-0.2, 0.04, 0.0, 0.003, 0.0, 0.01, 0.0, 0.002]
    out = distort_normalized(xy, dist[None, :, None, :])
    assert out.shape == xy.shape
    for c in range(2):
        np.testing.assert_array_equal(
            out[:, c].reshape(-1, 2), distort_normalized(xy[:, c].reshape(-1, 2), dist[c]))
    np.testing.assert_array_equal(distort_normalized(xy, np.zeros(0)), xy)


# --------------------------------------------------------------------------------------------
# static detection
# --------------------------------------------------------------------------------------------

STEPS = st.lists(
    st.tuples(st.floats(0.0, 0.2), st.floats(-0.1, 0.1), st.integers(1, 400)),
    min_size=1, max_size=80,
)


@given(STEPS)
def test_static_detector_invariants(steps) -> None:
    det = StaticDetector(max_speed_mps=0.05, max_yaw_rate_radps=0.02, dwell_s=1.0)
    t = 10 * S
    prev = det.state
    for speed, yaw_rate, dt_ms in steps:
        t += dt_ms * 1_000_000
        m = det.update(t, speed, 0.0, yaw_rate)
        still = speed <= 0.05 and abs(yaw_rate) <= 0.02
        assert m == det.state and m.stamp_ns == t
        if not still:  # any fast sample ends the stop
            assert m.still_since_ns is None and not m.is_static
        else:
            assert m.still_since_ns is not None
            assert m.is_static == (t - m.still_since_ns >= S)
        # a stop is counted once, when it starts
        assert m.stop_id == prev.stop_id + (1 if m.is_static and not prev.is_static else 0)
        prev = m


def test_static_detector_counts_stops_after_the_dwell() -> None:
    det = StaticDetector(0.05, 0.02, 0.5)
    assert det.state == MotionState()
    assert not det.update(0, 0.0, 0.0, 0.0).is_static
    assert not det.update(S // 2 - 1, 0.0, 0.03, 0.0).is_static
    m = det.update(S // 2, 0.0, 0.0, 0.0)
    assert m.is_static and m.stop_id == 1 and m.still_since_ns == 0
    assert not det.update(S, 0.0, 0.0, 0.5).is_static
    det.update(2 * S, 0.01, 0.0, 0.0)
    assert det.update(3 * S, 0.0, 0.0, 0.0).stop_id == 2


def test_static_detector_from_site_thresholds() -> None:
    th = Thresholds()
    det = StaticDetector.from_thresholds(th)
    assert (det.max_speed_mps, det.max_yaw_rate_radps, det.dwell_s) == (
        th.static_max_speed_mps, th.static_max_yaw_rate_radps, th.static_dwell_s)


@given(st.floats(-0.5, -0.01))
def test_lens_fold_radius_matches_the_analytic_fold_of_k1(k1: float) -> None:
    # r (1 + k1 r^2) stops growing where 1 + 3 k1 r^2 = 0
    expected = 1.0 / math.sqrt(-3.0 * k1)
    got = lens_fold_radius(np.array([k1, 0.0, 0.0, 0.0, 0.0]))
    assert abs(got - expected) <= 2e-3 * max(1.0, expected)


def test_lens_fold_radius_is_infinite_for_lenses_that_keep_growing() -> None:
    assert math.isinf(lens_fold_radius(np.zeros(5)))
    assert math.isinf(lens_fold_radius(np.array([0.1, 0.01, 0.0, 0.0, 0.0])))


@settings(max_examples=60, deadline=None)
@given(DIST_COEFFS, st.integers(0, 2**31), st.sampled_from([0, 4, 5, 8]))
def test_distortion_jacobian_matches_central_differences(coeffs, seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    dist = np.array([*coeffs, 0.02, -0.01, 0.005])[:n]
    xy = rng.uniform(-0.6, 0.6, (30, 2))
    eps = 1e-6
    cols = [(distort_normalized(xy + e, dist) - distort_normalized(xy - e, dist)) / (2 * eps)
            for e in (np.array([eps, 0.0]), np.array([0.0, eps]))]
    np.testing.assert_allclose(distort_normalized_jacobian(xy, dist), np.stack(cols, axis=-1),
                               rtol=1e-6, atol=1e-7)


def test_distortion_jacobian_broadcasts_one_row_per_camera() -> None:
    rng = np.random.default_rng(2)
    xy = rng.uniform(-0.5, 0.5, (2, 6, 2))  # (camera, keypoint, 2)
    dist = np.array([[-0.3, 0.1, 0.01, -0.01, 0.02, 0.0, 0.0, 0.0], [0.0] * 8])
    J = distort_normalized_jacobian(xy, dist[:, None, :])
    assert J.shape == (2, 6, 2, 2)
    np.testing.assert_allclose(J[1], np.broadcast_to(np.eye(2), (6, 2, 2)))
    np.testing.assert_allclose(J[0], distort_normalized_jacobian(xy[0], dist[0]))
