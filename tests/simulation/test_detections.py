"""Detections: geometry is exact without noise, noise is seeded, messages are valid."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from core.geometry import se3_from_planar
from protocol.codec import decode, encode
from protocol.messages import RobotDetections
from simulation.detections import DetectionSimulator, true_cameras
from simulation.scenario import load_scenario


@pytest.fixture(scope="module")
def scenario():
    return load_scenario()


def _quiet(sc):
    noise = dataclasses.replace(sc.noise, sigma_px=0.0, sigma_shift_px=0.0, sigma_scale=0.0,
                                dropout_probability=0.0, outlier_probability=0.0)
    cams = dataclasses.replace(sc.cameras, miss_probability=0.0)
    return sc.with_overrides(noise=noise, cameras=cams)


def test_noise_free_keypoints_are_true_projections(scenario) -> None:
    sc = _quiet(scenario)
    det = DetectionSimulator(sc)
    wp = sc.waypoints["WP3"]
    pose = np.array([wp.x, wp.y, wp.theta])
    msg = det.detect("cam1", sc.start_stamp_ns, pose, 0, np.random.default_rng(0))
    assert len(msg.detections) == 1
    d = msg.detections[0]
    model = sc.site.robot_model("hsr")
    T_world_robot = se3_from_planar(*pose)
    kps_w = model.keypoints_base_m @ T_world_robot[:3, :3].T + T_world_robot[:3, 3]
    uv, _ = det.cameras["cam1"].project(kps_w)
    used = d.keypoint_scores > 0.3
    np.testing.assert_allclose(d.keypoints_px[used], uv[used], atol=1e-9)
    # the true camera differs from the calibrated one (calibration error is modelled)
    uv_cal, _ = sc.site.cameras["cam1"].project(kps_w)
    assert 0.01 < np.abs(uv_cal - uv).max() < 10.0


def test_calibration_error_is_fixed_per_site(scenario) -> None:
    a, b = true_cameras(scenario), true_cameras(scenario)
    np.testing.assert_array_equal(a["cam2"].T_cam_world, b["cam2"].T_cam_world)


def test_same_seed_same_noise_different_seed_different_noise(scenario) -> None:
    det = DetectionSimulator(scenario)
    wp = scenario.waypoints["WP2"]
    pose = np.array([wp.x, wp.y, wp.theta])
    m1 = det.detect("cam3", scenario.start_stamp_ns, pose, 0, np.random.default_rng(5))
    m2 = det.detect("cam3", scenario.start_stamp_ns, pose, 0, np.random.default_rng(5))
    m3 = det.detect("cam3", scenario.start_stamp_ns, pose, 0, np.random.default_rng(6))
    assert m1 == m2
    assert not np.allclose(m1.detections[0].keypoints_px, m3.detections[0].keypoints_px)


def test_robot_out_of_view_gives_empty_detections(scenario) -> None:
    det = DetectionSimulator(scenario)
    wp = scenario.waypoints["WP1"]  # behind cam1
    msg = det.detect("cam1", scenario.start_stamp_ns, np.array([wp.x, wp.y, 0.0]), 3,
                     np.random.default_rng(0))
    assert msg.detections == () and msg.seq == 3


def test_stamps_carry_clock_offsets_and_messages_round_trip(scenario) -> None:
    det = DetectionSimulator(scenario)
    t = scenario.start_stamp_ns + 123_456_789
    for cam_id, cam in scenario.site.cameras.items():
        stamp = det.capture_stamp_ns(cam_id, t)
        # corrected by the site's offset, only the small residual clock error remains
        assert abs(stamp + cam.clock_offset_ns - t) < 10_000_000
    wp = scenario.waypoints["WP3"]
    msg = det.detect("cam2", t, np.array([wp.x, wp.y, wp.theta]), 0, np.random.default_rng(1))
    assert decode(encode(msg), RobotDetections) == msg
    assert msg.image_width == 848 and msg.image_height == 480


def test_noise_has_outliers_and_dropouts_at_configured_rates(scenario) -> None:
    noise = dataclasses.replace(scenario.noise, dropout_probability=0.2,
                                outlier_probability=0.0)
    sc = scenario.with_overrides(
        noise=noise, cameras=dataclasses.replace(scenario.cameras, miss_probability=0.0))
    det = DetectionSimulator(sc)
    wp = sc.waypoints["WP3"]
    rng = np.random.default_rng(0)
    zeros = [np.mean(det.detect("cam1", sc.start_stamp_ns, np.array([wp.x, wp.y, wp.theta]), 0,
                                rng).detections[0].keypoint_scores == 0) for _ in range(300)]
    assert np.mean(zeros) == pytest.approx(0.2, abs=0.03)


def _run_poses(sc, n: int = 400) -> np.ndarray:
    """(n, 3) poses along traj1 at 15 Hz, stops (repeated poses) included."""
    from simulation.runner import SimulationRun

    run = SimulationRun(sc, "traj1", False, seed=3)
    return np.array([run.plan.state_at(k / 15.0)[0] for k in range(n)])


def test_frame_geometry_cache_hit_equals_a_recompute(scenario, monkeypatch) -> None:
    import simulation.detections as detections

    poses = _run_poses(scenario)
    assert len({p.tobytes() for p in poses}) < len(poses)  # a static robot repeats its pose
    cached = DetectionSimulator(scenario)
    monkeypatch.setattr(detections, "GEOMETRY_CHUNK", 97)  # several chunks
    for cam in ("cam1", "cam3"):
        cached.prepare_frames(cam, poses)  # all frames at once, vectorized
        for pose in poses[::7]:
            hit = cached.frame_geometry(cam, pose)
            fresh = DetectionSimulator(scenario).frame_geometry(cam, pose)  # one frame alone
            for name in ("uv", "in_view", "occluded", "self_occluded"):
                np.testing.assert_array_equal(getattr(hit.visibility, name),
                                              getattr(fresh.visibility, name))
            assert hit.visibility.distance_m == fresh.visibility.distance_m
            assert hit.visibility.detectable == fresh.visibility.detectable
            np.testing.assert_array_equal(hit.hull_uv, fresh.hull_uv)
            assert not hit.visibility.uv.flags.writeable and not hit.hull_uv.flags.writeable


def test_frame_geometry_is_the_projection_of_the_keypoints(scenario) -> None:
    det = DetectionSimulator(scenario)
    model = scenario.site.robot_model("hsr")
    poses = _run_poses(scenario, 120)
    det.prepare_frames("cam2", poses)
    for pose in poses[::11]:
        T = se3_from_planar(*pose)
        kps_w = (np.column_stack([model.keypoints_base_m, np.ones(len(model.keypoints_base_m))])
                 @ T.T)[:, :3]
        uv, _ = det.cameras["cam2"].project(kps_w)
        np.testing.assert_array_equal(det.visibility("cam2", pose).uv, uv)


def test_a_static_robot_shares_one_geometry_and_the_caches_are_bounded(scenario,
                                                                      monkeypatch) -> None:
    import simulation.detections as detections

    det = DetectionSimulator(scenario)
    wp = scenario.waypoints["WP3"]
    pose = np.array([wp.x, wp.y, wp.theta])
    # on demand: the last frame per camera is kept (a static robot repeats its pose)
    first = det.frame_geometry("cam1", pose)
    assert det.frame_geometry("cam1", pose.copy()) is first
    det.frame_geometry("cam1", pose + np.array([0.01, 0.0, 0.0]))
    again = det.frame_geometry("cam1", pose)
    assert again is not first
    np.testing.assert_array_equal(again.visibility.uv, first.visibility.uv)
    # prepared: at most MAX_PREPARED_FRAMES distinct poses; later ones come on demand
    monkeypatch.setattr(detections, "MAX_PREPARED_FRAMES", 5)
    monkeypatch.setattr(detections, "GEOMETRY_CHUNK", 2)
    poses = pose + np.outer(np.arange(12), [0.01, 0.0, 0.0])
    det.prepare_frames("cam1", np.repeat(poses, 2, axis=0))
    held = [det.frame_geometry("cam1", p) for p in poses]
    for k, p in enumerate(poses):
        g = det.frame_geometry("cam1", p)
        assert (g is held[k]) == (k < 5), k
        np.testing.assert_array_equal(g.visibility.uv,
                                      DetectionSimulator(scenario).visibility("cam1", p).uv)


def test_detect_many_is_detect_per_frame(scenario) -> None:
    from simulation.detections import FrameRequest

    det = DetectionSimulator(scenario)
    wp = scenario.waypoints["WP3"]
    pose = np.array([wp.x, wp.y, wp.theta])
    frames = [FrameRequest(c, scenario.start_stamp_ns, pose, 4, np.random.default_rng(i))
              for i, c in enumerate(("cam1", "cam2", "cam3"))]
    many = det.detect_many(frames)
    one = [det.detect(c, scenario.start_stamp_ns, pose, 4, np.random.default_rng(i))
           for i, c in enumerate(("cam1", "cam2", "cam3"))]
    assert many == one
