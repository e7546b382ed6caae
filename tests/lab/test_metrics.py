"""Alignment recovers known transforms exactly; APE matches evo on generated trajectories."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from core.geometry import rotation_z, wrap_angle_array
from lab.evaluation.metrics import (
    MetricsError,
    Trajectory,
    align_planar,
    ape,
    error_stats,
    group_by_camera_count,
    match_stamps,
    travelled_distance,
    umeyama_alignment,
)


def _random_rotation(rng: np.random.Generator, d: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(d, d)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    return q


@pytest.mark.parametrize("d,with_scale", [(2, False), (3, False), (3, True), (2, True)])
def test_umeyama_recovers_known_transform(d: int, with_scale: bool) -> None:
    rng = np.random.default_rng(d * 10 + with_scale)
    R = _random_rotation(rng, d)
    t = rng.normal(size=d) * 5
    s = 1.7 if with_scale else 1.0
    est = rng.normal(size=(50, d)) * 3
    ref = s * est @ R.T + t
    al = umeyama_alignment(est, ref, with_scale=with_scale)
    np.testing.assert_allclose(al.R, R, atol=1e-12)
    np.testing.assert_allclose(al.t, t, atol=1e-10)
    assert al.scale == pytest.approx(s, abs=1e-12)
    np.testing.assert_allclose(al.apply_points(est), ref, atol=1e-10)


def test_se2_planar_alignment_recovers_yaw_and_headings() -> None:
    rng = np.random.default_rng(3)
    est = np.column_stack([rng.uniform(0, 10, 40), rng.uniform(0, 6, 40),
                           rng.uniform(-3, 3, 40)])
    yaw, t = 0.7, np.array([2.0, -1.0])
    ref = est.copy()
    ref[:, :2] = est[:, :2] @ rotation_z(yaw)[:2, :2].T + t
    ref[:, 2] = wrap_angle_array(est[:, 2] + yaw)
    aligned, al = align_planar(est, ref)
    assert al.yaw_rad == pytest.approx(yaw, abs=1e-12)
    np.testing.assert_allclose(aligned[:, :2], ref[:, :2], atol=1e-10)
    np.testing.assert_allclose(wrap_angle_array(aligned[:, 2] - ref[:, 2]), 0, atol=1e-10)


def test_reflection_is_not_returned() -> None:
    est = np.array([[0, 0], [1, 0], [0, 1], [1, 1.0]])
    ref = est * np.array([-1, 1])  # mirror image: the best proper rotation is not a reflection
    al = umeyama_alignment(est, ref)
    assert np.linalg.det(al.R) == pytest.approx(1.0)


def test_degenerate_inputs_raise_clear_errors() -> None:
    with pytest.raises(MetricsError, match="identical"):
        umeyama_alignment(np.ones((5, 3)), np.zeros((5, 3)))
    with pytest.raises(MetricsError):
        umeyama_alignment(np.ones((1, 3)), np.zeros((1, 3)))


def _generated_pair(seed: int, n_ref: int = 400, n_est: int = 380):
    rng = np.random.default_rng(seed)
    t_ref = np.arange(n_ref) * 0.05
    # est sampled on a slightly different clock so association matters
    t_est = np.sort(rng.choice(t_ref, n_est, replace=False)) + rng.normal(0, 0.002, n_est)
    def path(t: np.ndarray) -> np.ndarray:
        return np.column_stack([3 * np.sin(0.3 * t), 2 * np.cos(0.2 * t), 0.1 * np.sin(t)])
    def quat(t: np.ndarray) -> np.ndarray:
        yaw, roll = 0.4 * t, 0.05 * np.sin(t)
        cr, sr, cy, sy = np.cos(roll / 2), np.sin(roll / 2), np.cos(yaw / 2), np.sin(yaw / 2)
        return np.column_stack([sr * cy, sr * sy, cr * sy, cr * cy])
    ref = Trajectory(t_ref, path(t_ref), quat(t_ref))
    R = _random_rotation(rng, 3)
    pos = (path(t_est) + rng.normal(0, 0.03, (n_est, 3))) @ R.T + rng.normal(size=3)
    q_noise = quat(t_est) + rng.normal(0, 0.01, (n_est, 4))
    # rotate the orientations by R as well (via evo below we only need them consistent)
    from scipy.spatial.transform import Rotation

    rots = Rotation.from_matrix(R) * Rotation.from_quat(q_noise / np.linalg.norm(q_noise, axis=1,
                                                                                   keepdims=True))
    est = Trajectory(t_est, pos, rots.as_quat())
    return ref, est


@pytest.mark.parametrize("seed,correct_scale", [(0, False), (1, False), (2, True)])
def test_ape_matches_evo(seed: int, correct_scale: bool) -> None:
    from evo.core import metrics as evo_metrics
    from evo.core import sync
    from evo.core.trajectory import PoseTrajectory3D

    ref, est = _generated_pair(seed)
    mine = ape(ref, est, align=True, correct_scale=correct_scale)

    def to_evo(tr: Trajectory) -> PoseTrajectory3D:
        return PoseTrajectory3D(tr.positions_m.copy(), np.roll(tr.quat_xyzw, 1, axis=1).copy(),
                                tr.stamps_s.copy())

    traj_ref, traj_est = sync.associate_trajectories(to_evo(ref), to_evo(est), max_diff=0.01)
    traj_est = copy.deepcopy(traj_est)
    traj_est.align(traj_ref, correct_scale=correct_scale)
    for relation, values in (
        (evo_metrics.PoseRelation.translation_part, mine.translation_m),
        (evo_metrics.PoseRelation.rotation_angle_deg, np.rad2deg(mine.rotation_rad)),
    ):
        metric = evo_metrics.APE(relation)
        metric.process_data((traj_ref, traj_est))
        assert len(metric.error) == len(values)
        np.testing.assert_allclose(values, metric.error, atol=1e-6)
        evo_stats = metric.get_all_statistics()
        for key, value in error_stats(values).as_dict().items():
            assert value == pytest.approx(evo_stats[key], abs=1e-6), key


def test_match_stamps_nearest_within_window() -> None:
    a = np.array([0.0, 1.0, 2.0, 3.0])
    b = np.array([0.004, 1.02, 2.0, 2.995, 9.0])
    ia, ib = match_stamps(a, b, 0.01)
    assert ia.tolist() == [0, 2, 3] and ib.tolist() == [0, 2, 3]


def test_group_by_camera_count_and_distance() -> None:
    g = group_by_camera_count(np.array([1.0, 3.0, 2.0, 2.0, 9.0]), np.array([1, 1, 2, 4, 0]))
    assert g[1].mean == pytest.approx(2.0) and g[1].std == pytest.approx(1.0)
    assert g[2].count == 1 and g[4].mean == pytest.approx(2.0)
    assert g["average"].count == 4 and g["average"].mean == pytest.approx(2.0)
    d = travelled_distance(np.array([[0, 0], [3, 4], [3, 5.0]]))
    np.testing.assert_allclose(d, [0, 5, 6])
