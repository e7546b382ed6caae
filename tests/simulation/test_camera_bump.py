"""A camera bumped during a simulated run: from the bump on, its detections are those of the moved
camera; before it and for the other cameras nothing changes."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from core.geometry import se3_from_planar
from simulation.detections import CameraBump, DetectionSimulator
from simulation.scenario import NoiseConfig, load_scenario

POSE = np.array([10.0, 6.0, 0.4])  # the middle of the paper lab, seen by all four cameras


@pytest.fixture(scope="module")
def exact_scenario():
    """The paper lab with an exact detector (no keypoint noise, no misses)."""
    sc = load_scenario()
    return sc.with_overrides(
        noise=NoiseConfig(sigma_px=0.0, sigma_shift_px=0.0, sigma_scale=0.0,
                          dropout_probability=0.0, outlier_probability=0.0),
        cameras=dataclasses.replace(sc.cameras, miss_probability=0.0))


def _keypoints(det: DetectionSimulator, camera_id: str, t_ns: int) -> np.ndarray:
    msg = det.detect(camera_id, t_ns, POSE, 0, np.random.default_rng(0))
    assert msg.detections, f"{camera_id} does not see the robot"
    return msg.detections[0].keypoints_px


def test_the_bumped_camera_sees_through_its_moved_pose(exact_scenario) -> None:
    at_ns = exact_scenario.start_stamp_ns + 30_000_000_000
    bump = CameraBump("cam3", at_ns, (0.03, 0.04, 0.0), (0.0, 0.6, 0.8))
    plain = DetectionSimulator(exact_scenario)
    bumped = DetectionSimulator(exact_scenario, bumps=[bump])
    before, after = at_ns - 1_000_000, at_ns + 1_000_000
    for cid in sorted(exact_scenario.site.cameras):
        np.testing.assert_array_equal(_keypoints(bumped, cid, before),
                                      _keypoints(plain, cid, before))
        if cid != "cam3":
            np.testing.assert_array_equal(_keypoints(bumped, cid, after),
                                          _keypoints(plain, cid, after))
    # after the bump: the projection through the moved true camera
    moved = bump.apply(plain.cameras["cam3"])
    index, true_after = bumped.true_camera("cam3", after)
    assert index == 0 and np.array_equal(true_after.T_cam_world, moved.T_cam_world)
    assert bumped.true_camera("cam3", before)[0] == -1
    T = se3_from_planar(*POSE)
    kp = exact_scenario.site.robot_model(exact_scenario.robot_id).keypoints_base_m
    expected, _ = moved.project(kp @ T[:3, :3].T + T[:3, 3])
    got = _keypoints(bumped, "cam3", after)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    # the bump moves every keypoint by pixels (this one partly cancels its own rotation)
    shift = np.linalg.norm(got - _keypoints(plain, "cam3", after), axis=1)
    assert shift.min() > 1.0
    # the moved pose is the calibrated one moved by exactly the bump
    dc = moved.position_world - plain.cameras["cam3"].position_world
    np.testing.assert_allclose(dc, bump.translation_m, atol=1e-12)
    dR = moved.T_world_cam[:3, :3] @ plain.cameras["cam3"].T_world_cam[:3, :3].T
    angle = math.degrees(math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    assert angle == pytest.approx(1.0, abs=1e-9)


def test_bad_bumps_are_clear_errors(exact_scenario) -> None:
    with pytest.raises(ValueError, match="unknown camera 'cam9'"):
        DetectionSimulator(exact_scenario, bumps=[CameraBump("cam9", 0)])
    with pytest.raises(ValueError, match="translation_m"):
        CameraBump("cam1", 0, (0.0, float("nan"), 0.0))
    with pytest.raises(ValueError, match="rotation_deg"):
        CameraBump("cam1", 0, rotation_deg=(1.0, 2.0))  # type: ignore[arg-type]
