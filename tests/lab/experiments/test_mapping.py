"""Experiment 4 (semantic mapping) on the simulated lab: the scores, the ground truth, and a
short run through the real renderer, segmentation network, cloud builder and mapping."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from lab.experiments.mapping import (
    MappingExperimentConfig,
    ground_truth,
    map_scores,
    run_mapping,
    write_prior_model,
)
from mapper.map_io import load_map_npz, read_ply_points
from mapper.semantic_map import SemanticMapConfig, SemanticVoxelMap
from protocol.semantic_classes import SEMANTIC_CLASS_ID
from simulation.scenario import load_scenario


@pytest.fixture(scope="module")
def scenario():
    sc = load_scenario()
    return sc.with_overrides(motion=dataclasses.replace(sc.motion, stop_s=2.0))


@pytest.fixture(scope="module")
def truth(scenario):
    return ground_truth(scenario, 0.05)


def test_ground_truth_leaves_out_what_nobody_sees_and_the_prior_is_the_empty_room(
        scenario, truth) -> None:
    floor = truth.labels == SEMANTIC_CLASS_ID["floor"]
    for box in scenario.obstacles:  # no floor under (the middle of) any piece of furniture
        c = np.asarray(box.center_xy_m)
        near = np.linalg.norm(truth.points[:, :2] - c, axis=1) < 0.2
        assert not np.any(near & floor & (truth.points[:, 2] < 0.05)), box.name
    assert {"table", "shelf", "cabinet", "box"} <= {
        name for name, cid in SEMANTIC_CLASS_ID.items() if np.any(truth.labels == cid)}
    assert np.all(truth.prior_points[:, 2] >= -1e-9)  # floor and walls only
    heights = truth.prior_points[:, 2]
    lo, hi = np.asarray(scenario.room_min_xy_m), np.asarray(scenario.room_max_xy_m)
    on_wall = (np.isclose(truth.prior_points[:, 0], lo[0])
               | np.isclose(truth.prior_points[:, 0], hi[0])
               | np.isclose(truth.prior_points[:, 1], lo[1])
               | np.isclose(truth.prior_points[:, 1], hi[1]))
    assert np.all(on_wall | (heights < 1e-9))  # nothing of the furniture


def test_scores_of_a_perfect_and_of_a_wrongly_labelled_map(truth) -> None:
    cfg = SemanticMapConfig()
    perfect = SemanticVoxelMap(cfg)
    n = len(truth.points)
    perfect.integrate(truth.points, truth.labels, np.full(n, 0.9))
    s = map_scores(perfect, truth)
    assert s.coverage > 0.99 and s.accuracy > 0.99 and s.off_surface_share < 0.01
    wrong = SemanticVoxelMap(cfg)
    wrong.integrate(truth.points, (truth.labels + 1) % 13, np.full(n, 0.9))
    assert map_scores(wrong, truth).accuracy < 0.01
    half = SemanticVoxelMap(cfg)
    keep = truth.points[:, 0] < 10.0  # the west half of the room
    half.integrate(truth.points[keep], truth.labels[keep], np.full(int(keep.sum()), 0.9))
    assert map_scores(half, truth).coverage == pytest.approx(keep.mean(), abs=0.01)
    lifted = SemanticVoxelMap(cfg)
    lifted.integrate(truth.points + np.array([0.0, 0.0, 0.3]), truth.labels, np.full(n, 0.9))
    assert map_scores(lifted, truth).off_surface_share > 0.5
    empty = map_scores(SemanticVoxelMap(cfg), truth)
    assert empty.coverage == 0.0 and math.isnan(empty.accuracy)


def test_prior_model_file_is_the_empty_room(scenario, tmp_path: Path) -> None:
    path = write_prior_model(scenario, tmp_path / "room.ply")
    points, normals = read_ply_points(path)
    assert normals is not None and len(points) > 100_000
    assert points[:, 2].max() <= scenario.room_height_m + 0.05


@pytest.fixture(scope="module")
def report(scenario, tmp_path_factory: pytest.TempPathFactory):
    """traj3 with feedback (its ground truth, localization and published fused poses), one
    frame per static camera, a head-camera cloud every 4 s, through the shipped segmentation
    network (every 4 s rather than 2: 23 clouds, 18 fused, coverage 0.072 static -> 0.240 with
    the robot, accuracy 0.97; every 2 s: 46, 39, 0.261, 0.97; at twice the time)."""
    from lab.experiments import (
        default_fusion_factory,
        paper_pipeline_config,
        run_feedback,
    )
    from simulation.runner import run_seed

    run = run_feedback(scenario, "traj3", True, run_seed(scenario, "traj3", False, 0, 0),
                       fusion_factory=default_fusion_factory(),
                       pipeline_config=paper_pipeline_config(scenario.site, scenario=scenario))
    out = tmp_path_factory.mktemp("mapping")
    cfg = MappingExperimentConfig(route="traj3", frames_per_camera=1, robot_cloud_rate_hz=0.25,
                                  consistency_rate_hz=0.1, threads=1)
    return run_mapping(scenario, cfg, out, runs=(run, run)), out


def test_the_robots_route_adds_coverage_to_the_static_cameras(report) -> None:
    rep, _ = report
    assert rep.static.coverage > 0.02
    assert rep.with_robot.coverage > rep.static.coverage + 0.02, (rep.static.coverage,
                                                                  rep.with_robot.coverage)
    assert rep.robot_clouds_fused >= 0.5 * rep.robot_clouds
    assert rep.with_robot.accuracy > 0.8
    assert rep.with_robot.labelled_voxels > rep.static.labelled_voxels


def test_consistency_rows_and_outputs(report) -> None:
    rep, out = report
    names = [r.placement for r in rep.consistency]
    assert names[-1] == "true pose (reference)" and len(names) == 4
    for row in rep.consistency:
        assert row.clouds >= 3 and 0.0 < row.fitness <= 1.0, row
    for png in ("semantic_map_topdown.png", "semantic_map_static_topdown.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    saved = load_map_npz(out / "semantic_map.npz")
    assert int(saved.has_semantics().sum()) == rep.with_robot.labelled_voxels
    text = (out / "mapping.md").read_text()
    assert "static sensors alone" in text and "true pose (reference)" in text
    assert set(rep.placements) == {"fused", "icp"}  # the other rule, on the same clouds
    assert "| icp |" in text
