"""Scenario loading: the paper site is valid, has 1/2/4-camera waypoints, errors name file/key."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import yaml

from simulation.detections import DetectionSimulator
from simulation.scenario import PAPER_SCENARIO, ScenarioError, load_scenario, parse_scenario
from simulation.world import World


def test_paper_site_has_waypoints_seen_by_1_2_and_4_cameras() -> None:
    sc = load_scenario()
    assert len(sc.waypoints) == 7 and len(sc.trajectories) == 3
    assert len(sc.site.cameras) == 4
    area = np.prod(sc.room_max_xy_m - sc.room_min_xy_m)
    assert 200 <= area <= 280
    for cam in sc.site.cameras.values():
        assert (cam.width, cam.height) == (848, 480)
        assert cam.position_world[2] == pytest.approx(2.5, abs=0.3)
        assert np.any(cam.dist != 0)
    det = DetectionSimulator(sc)
    counts = {n: len(det.cameras_seeing(np.array([w.x, w.y, w.theta])))
              for n, w in sc.waypoints.items()}
    assert {1, 2, 4} <= set(counts.values())
    # Traj. 3 avoids the single-camera waypoints (like the paper's shorter trajectory)
    assert all(counts[w] >= 2 for w in sc.trajectories["traj3"])


def test_robot_model_matches_the_example_site() -> None:
    example = yaml.safe_load((Path(__file__).parents[2] / "deploy/site.example.yaml").read_text())
    ours = yaml.safe_load((PAPER_SCENARIO.parent / "paper_lab.yaml").read_text())
    assert ours["robot_models"]["hsr"] == example["robot_models"]["hsr"]


def test_trajectory_legs_do_not_cross_obstacles() -> None:
    sc = load_scenario()
    world = World(sc)
    r = sc.site.robot_model(sc.robot_id).footprint_radius_m
    for seq in sc.trajectories.values():
        for a, b in itertools.pairwise(seq):
            pa = np.array([sc.waypoints[a].x, sc.waypoints[a].y])
            pb = np.array([sc.waypoints[b].x, sc.waypoints[b].y])
            for f in np.linspace(0, 1, 100):
                assert not world.footprint_collides(pa + f * (pb - pa), r), (a, b, f)


def _doc() -> dict:
    return yaml.safe_load(PAPER_SCENARIO.read_text())


@pytest.mark.parametrize(
    "mutate,key",
    [
        (lambda d: d["noise"].update(sigma_pix=1.0), "noise.sigma_pix"),
        (lambda d: d["trajectories"]["traj1"].append("WP9"), "trajectories.traj1[7]"),
        (lambda d: d["waypoints"]["WP1"].update(xy_m=[5.2, 8.8]), "waypoints.WP1.xy_m"),
        (lambda d: d["waypoints"]["WP1"].update(xy_m=[30.0, 1.0]), "waypoints.WP1.xy_m"),
        (lambda d: d["noise"].update(dropout_probability=1.5), "noise.dropout_probability"),
        (lambda d: d["obstacles"][0].update(size_m=[1, 2]), "obstacles[0].size_m"),
        (lambda d: d.update(robot_id="nobody"), "robot_id"),
        (lambda d: d.update(site_file="missing.yaml"), "site_file"),
    ],
)
def test_errors_name_file_and_key(mutate, key: str) -> None:
    doc = _doc()
    mutate(doc)
    with pytest.raises(ScenarioError) as info:
        parse_scenario(doc, "scen.yaml", PAPER_SCENARIO.parent)
    assert info.value.key == key
    assert str(info.value).startswith(f"scen.yaml: {key}")


def test_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match=r"nope\.yaml"):
        load_scenario(tmp_path / "nope.yaml")
