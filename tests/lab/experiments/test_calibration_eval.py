"""``smartedge evaluate calibration`` (lab.experiments.calibration) on the simulated paper
lab against the simulator's true cameras: a short version end to end, and experiment 1 run
with a site file other than the scenario's while the simulation keeps the true cameras."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from calibration.site_file import write_site_with_cameras
from lab.evaluate import main as evaluate_main
from lab.experiments import PaperConfig, run_once, source_errors
from lab.experiments.calibration import (
    CalibrationEvalConfig,
    common_offset,
    run_calibration_evaluation,
)
from simulation.detections import true_cameras
from simulation.scenario import load_scenario


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("calibration_eval")
    lines: list[str] = []
    config = CalibrationEvalConfig.quick(intrinsics_views=12, board_rounds=2, with_table=False)
    result = run_calibration_evaluation(config, out, progress=lines.append)
    return out, result, lines


def test_short_evaluation_measures_every_method_against_the_truth(short_run) -> None:
    out, result, lines = short_run
    n = result.numbers
    # intrinsics from rendered views: within 0.5 % and a lens model within 0.3 px
    intr = n["intrinsics"]["cam1"]
    assert max(abs(v) for v in intr["error_pct"].values()) < 0.5, intr["error_pct"]
    assert intr["model_diff_px"]["mean"] < 0.3
    # board poses per stamp: every camera within 1.5 cm / 0.2 deg
    per_stamp = n["board_extrinsics"]["anchors"]["per_stamp"]["cameras"]
    assert len(per_stamp) == 4
    assert all(v["position_cm"] < 1.5 and v["rotation_deg"] < 0.2 for v in per_stamp.values())
    robot = n["robot"]
    assert {k: v["exit_code"] for k, v in robot.items()} == {
        "robot_from_20cm": 0, "robot_site_frame": 0, "robot_bumped": 0}
    # (a) from 20 cm / 3 deg: the cameras agree with each other to < 1.5 cm once the common
    # planar offset is removed, and that offset is most of the remaining error
    a = robot["robot_from_20cm"]
    assert all(v["position_cm"] < 1.5 for v in a["offset_removed"].values())
    worst = max(v["position_cm"] for v in a["cameras"].values())
    assert abs(worst - a["common_offset"]["shift_cm"]) < 0.5 * worst + 1.0
    assert all(v["rotation_deg"] < 0.3 for v in a["cameras"].values())
    # (b) --frame site: better than the nominal file for the worst camera
    b = robot["robot_site_frame"]["cameras"]
    assert max(v["position_cm"] for v in b.values()) < 2.0
    assert max(v["position_cm"] for v in b.values()) < max(
        v["position_cm"] for v in n["nominal"].values())
    # (c) the bumped camera back within 3 cm / 0.2 deg of the truth (from 5 cm / 1 deg)
    c = robot["robot_bumped"]
    assert c["before"]["cam3"]["rotation_deg"] > 0.8
    assert c["cameras"]["cam3"]["position_cm"] < 3.0 and c["cameras"]["cam3"]["rotation_deg"] < 0.2
    # files: report, numbers, picture, the sites written and loadable
    md = (out / "calibration.md").read_text()
    assert "| robot (b): from nominal, --frame site |" in md and "fx %" in md
    assert json.loads((out / "calibration.json").read_text())["robot"]["robot_bumped"]
    assert (out / "calibration.png").stat().st_size > 10_000
    assert (out / "sites" / "robot_site_frame.yaml").exists()
    assert any("robot robot_bumped" in line for line in lines)


def test_common_offset_recovers_a_planar_motion() -> None:
    cams = true_cameras(load_scenario())
    true = {c: m.T_world_cam for c, m in cams.items()}
    yaw = np.radians(0.5)
    M = np.eye(4)
    M[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    M[:2, 3] = [0.07, -0.03]
    moved = {c: np.linalg.inv(M) @ T for c, T in true.items()}
    shift, yaw_deg, fit = common_offset(moved, true)
    assert yaw_deg == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_allclose(fit, M, atol=1e-9)
    assert shift > 0.05


def test_experiment1_runs_with_another_site_file_while_the_simulation_keeps_the_truth(
        tmp_path) -> None:
    sc = load_scenario()
    sc = sc.with_overrides(motion=dataclasses.replace(sc.motion, stop_s=2.0))
    truth = {c: m.T_world_cam for c, m in true_cameras(sc).items()}
    true_site = write_site_with_cameras(sc.site.source_path, tmp_path / "true.yaml", truth)
    cfg = PaperConfig(runs_per_direction=1, use_fusion=False)
    nominal = run_once(sc, "traj1", False, 0, cfg, None)
    exact = run_once(sc, "traj1", False, 0, cfg, None, service_site=true_site)
    # the same simulation (the robot's own localization is untouched) ...
    np.testing.assert_array_equal(nominal.robot, exact.robot)
    # ... and the backend with the true cameras is better where >= 2 cameras see the robot
    err = {name: source_errors([r], "five_frames") for name, r in
           (("nominal", nominal), ("exact", exact))}
    multi = err["exact"].num_cameras >= 2
    assert multi.sum() >= 3
    assert err["exact"].translation_m[multi].mean() < 0.5 * err["nominal"].translation_m[
        multi].mean()


def test_bad_options_are_refused(capsys) -> None:
    assert evaluate_main(["calibration", "--out", "x", "--runs", "0"]) == 1
    assert "--runs must be >= 1" in capsys.readouterr().err
    assert evaluate_main(["calibration", "--out", "x", "--drive-s", "-1"]) == 1
    assert "--drive-s" in capsys.readouterr().err
