"""Extrinsics of the paper lab's four cameras from rendered board sightings, solved jointly,
against the simulator's true camera poses."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.board import BoardDetector, CalibrationError
from calibration.board_extrinsics import (
    BoardSighting,
    load_board_poses,
    site_header,
    solve_board_extrinsics,
)
from calibration.site_file import write_site_with_cameras
from core.geometry import pose_error
from core.site import load_site
from protocol.errors import ConfigFileError
from simulation.detections import true_cameras
from simulation.scenario import load_scenario
from tests.calibration.rendered import (
    EXTRINSICS_BOARD,
    PAPER_LAB,
    paper_lab_board_poses,
    render_sightings,
)


@pytest.fixture(scope="module")
def lab():
    cameras = true_cameras(load_scenario())
    poses = paper_lab_board_poses(cameras, rounds=6)
    images = render_sightings(cameras, poses)
    det = BoardDetector(EXTRINSICS_BOARD)
    sightings = [BoardSighting.from_detection(c, s, d)
                 for c, by_stamp in images.items() for s, img in by_stamp.items()
                 if (d := det.detect(img)).usable]
    return cameras, poses, sightings


def test_board_poses_from_the_robot_give_every_camera_within_1cm_01deg(lab) -> None:
    cameras, poses, sightings = lab
    result = solve_board_extrinsics(cameras, sightings, EXTRINSICS_BOARD, poses)
    assert set(result.cameras) == set(cameras)
    for cid, sol in result.cameras.items():
        dp, da = pose_error(sol.T_world_cam, cameras[cid].T_world_cam)
        assert dp < 0.01 and da < 0.1, (cid, dp, da)
        # the reported uncertainty is of the size of the error
        assert sol.std_position_m < 0.01 and dp < 4 * sol.std_position_m + 1e-3
        assert sol.rms_px < 1.0
    # the start (PnP chained through the sightings) was further off
    worst_start = max(pose_error(result.initial[c], cameras[c].T_world_cam)[0] for c in cameras)
    assert worst_start > 0.02


def test_one_fixed_board_ties_every_camera_jointly(lab, tmp_path) -> None:
    cameras, poses, sightings = lab
    result = solve_board_extrinsics(cameras, sightings, EXTRINSICS_BOARD,
                                    {"000": poses["000"]})
    assert result.fixed_stamps == ("000",)
    assert len(result.board_poses) > 10
    for cid, sol in result.cameras.items():
        dp, da = pose_error(sol.T_world_cam, cameras[cid].T_world_cam)
        # anchored on one sighting (two cameras, 6-8 corners each) of one board pose, the
        # whole solution shares that sighting's error: 1-2 cm / 0.04-0.13 deg here; the
        # covariance allows for it (std ~2.4 cm / 0.5 deg)
        assert dp < 0.04 and da < 0.3, (cid, dp, da)
        assert dp < 3 * sol.std_position_m + 0.005, (cid, dp, sol.std_position_m)
        assert da < 3 * sol.std_rotation_deg + 0.05, (cid, da, sol.std_rotation_deg)
    out = tmp_path / "site.yaml"
    written = write_site_with_cameras(
        PAPER_LAB, out, {c: r.T_world_cam for c, r in result.cameras.items()},
        site_header(result, PAPER_LAB))
    site = load_site(out)
    assert sorted(written.cameras) == sorted(site.cameras)
    nominal = load_site(PAPER_LAB)
    for cid, sol in result.cameras.items():
        np.testing.assert_allclose(site.cameras[cid].T_world_cam, sol.T_world_cam, atol=1e-6)
        np.testing.assert_array_equal(site.cameras[cid].K, nominal.cameras[cid].K)
        assert site.cameras[cid].clock_offset_ns == nominal.cameras[cid].clock_offset_ns
    assert "std" in out.read_text().splitlines()[2]


def test_unanchored_sightings_are_refused(lab) -> None:
    cameras, poses, sightings = lab
    with pytest.raises(CalibrationError, match="no camera saw the board at a fixed pose"):
        solve_board_extrinsics(cameras, sightings, EXTRINSICS_BOARD,
                               {"999": poses["000"]})


def test_board_poses_file_errors_name_the_key(tmp_path) -> None:
    path = tmp_path / "poses.yaml"
    path.write_text("board_poses:\n  '001': {translation_m: [1, 2], rpy_deg: [0, 0, 0]}\n")
    with pytest.raises(ConfigFileError, match=r"board_poses\.001\.translation_m"):
        load_board_poses(path)
    path.write_text("board_poses:\n  '001': {translation_m: [1, 2, 0], rpy_deg: [0, 0, 90]}\n")
    T = load_board_poses(path)["001"]
    np.testing.assert_allclose(T[:3, 0], [0, 1, 0], atol=1e-12)
