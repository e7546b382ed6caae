"""Rendered samples of the simulated site and randomized scenes: labels agree with the render,
generation is deterministic, the writer and the command produce what a user can inspect."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("moderngl")

from simulation.dataset import DatasetError, SampleGenerator, write_dataset
from simulation.mesh import CLASS_ID
from simulation.runner import SimulationRun
from simulation.scenario import load_scenario
from simulation.scenes import ROBOT_INSTANCE, look_at_camera, site_geometry, site_scene


@pytest.fixture(scope="module")
def scenario():
    return load_scenario()


@pytest.fixture(scope="module")
def site_gen(scenario):
    return SampleGenerator(scenario, "site", seed=3, width=424, height=240)


def _check_label_matches_render(sample) -> None:
    (robot,) = sample.robots
    assert robot.keypoints_px.shape == (len(robot.visible), 2)
    mask = sample.instance_id == ROBOT_INSTANCE
    if robot.visible.any():
        assert robot.bbox_xyxy is not None and mask.any()
        x0, y0, x1, y1 = robot.bbox_xyxy
        uv = robot.keypoints_px[robot.visible]
        # every visible keypoint lies inside the box of the robot's visible pixels (1 px slack)
        assert np.all((uv[:, 0] >= x0 - 1) & (uv[:, 0] <= x1 + 1))
        assert np.all((uv[:, 1] >= y0 - 1) & (uv[:, 1] <= y1 + 1))
        # and on (or right next to) a robot pixel
        for u, v in np.round(uv).astype(int):
            patch = mask[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3]
            assert patch.any()
    assert np.all(sample.class_id[mask] == CLASS_ID["robot"])


def test_site_samples_label_the_robot_where_it_is_rendered(site_gen) -> None:
    seen = 0
    for i in range(12):
        sample = site_gen(i)
        _check_label_matches_render(sample)
        seen += bool(sample.robots[0].visible.any())
    assert seen >= 3  # the site's cameras see the robot in a good part of the room


def test_randomized_samples_label_the_robot(scenario) -> None:
    gen = SampleGenerator(scenario, "randomized", seed=5, width=320, height=192)
    visible = 0
    for i in range(8):
        sample = gen(i)
        _check_label_matches_render(sample)
        visible += int(sample.robots[0].visible.sum())
    assert visible > 8 * 3


def test_same_seed_same_images_other_seed_other_images(scenario, site_gen) -> None:
    a, b = site_gen(4), SampleGenerator(scenario, "site", seed=3, width=424, height=240)(4)
    assert np.array_equal(a.image_rgb, b.image_rgb)
    assert np.array_equal(a.instance_id, b.instance_id)
    assert np.array_equal(a.robots[0].keypoints_px, b.robots[0].keypoints_px)
    c = SampleGenerator(scenario, "site", seed=4, width=424, height=240)(4)
    assert not np.array_equal(a.image_rgb, c.image_rgb)


def test_simulated_pose_seen_from_a_site_camera(scenario) -> None:
    """The closed loop: the robot at the simulation's pose, seen by the site's camera."""
    from simulation.render_gl import Renderer
    from simulation.robot_mesh import hsr_like_mesh
    from simulation.scenes import robot_keypoints_world

    run = SimulationRun(scenario, "traj3", seed=0)
    pose = run.plan.pose_at(3.0).reshape(-1, 3)[0]
    model = scenario.site.robot_model(scenario.robot_id)
    scene = site_scene(site_geometry(scenario), hsr_like_mesh(model), pose)
    seeing = run.detector.cameras_seeing(pose)
    assert seeing
    from simulation.labels import instance_bbox, keypoint_labels

    for cam_id in sorted(scenario.site.cameras):
        cam = scenario.site.cameras[cam_id]
        out = Renderer(cam.width, cam.height).render(scene, cam)
        kp = keypoint_labels(out, cam, robot_keypoints_world(model, pose))
        bbox = instance_bbox(out, ROBOT_INSTANCE)
        if cam_id in seeing:
            assert bbox is not None and kp.visible.sum() >= 3, cam_id
        # a camera that cannot see the robot: nothing of it rendered
        away = look_at_camera("away", cam.position_world, cam.position_world * 2 - [*pose[:2], 0],
                              cam.width, cam.height, 60.0)
        out_away = Renderer(cam.width, cam.height).render(scene, away)
        assert instance_bbox(out_away, ROBOT_INSTANCE) is None
        break


def test_writer_output_is_independent_of_workers(tmp_path: Path, scenario) -> None:
    gen = SampleGenerator(scenario, "randomized", seed=9, width=160, height=96)
    one = write_dataset(gen, tmp_path / "one", 4, workers=1)
    two = write_dataset(gen, tmp_path / "two", 4, workers=2)
    assert one.read_text() == two.read_text()
    for name in ("images", "depth", "class", "instance"):
        assert sorted(p.name for p in (tmp_path / "two" / name).iterdir()) == [
            f"{i:06d}.png" for i in range(4)]
    doc = json.loads(one.read_text().splitlines()[0])
    assert doc["image"] == "images/000000.png" and len(doc["robots"][0]["keypoints_px"]) == 12
    meta = json.loads((tmp_path / "one" / "dataset.json").read_text())
    assert meta["classes"][CLASS_ID["robot"]] == "robot"


def test_bad_requests_are_clear_errors(tmp_path: Path, scenario) -> None:
    with pytest.raises(DatasetError, match="mode"):
        SampleGenerator(scenario, "movie")
    with pytest.raises(DatasetError, match="size"):
        SampleGenerator(scenario, "site", width=640)
    with pytest.raises(DatasetError, match="count"):
        write_dataset(SampleGenerator(scenario, "site"), tmp_path, 0)


def test_render_command_writes_dataset_and_preview(tmp_path: Path) -> None:
    from smartedge.cli import main

    out = tmp_path / "r"
    assert main(["render", "--out", str(out), "--count", "3", "--preview", "2",
                 "--size", "212x120", "--randomize"]) == 0
    assert len((out / "labels.jsonl").read_text().splitlines()) == 3
    assert len(list((out / "preview").iterdir())) == 2
    assert main(["render", "--out", str(out), "--size", "big"]) == 1


def test_render_command_with_a_user_robot_from_a_registry_urdf(tmp_path: Path) -> None:
    """A real robot description (Clearpath Husky from pybullet_data, BSD) with a keypoint file
    renders and is labelled with its own keypoints."""
    pybullet_data = pytest.importorskip("pybullet_data")
    from smartedge.cli import main
    from tests.simulation.test_robot_mesh import HUSKY_KEYPOINTS

    urdf = Path(pybullet_data.getDataPath()) / "husky" / "husky.urdf"
    kp = tmp_path / "husky_kp.yaml"
    kp.write_text(HUSKY_KEYPOINTS)
    out = tmp_path / "husky"
    assert main(["render", "--out", str(out), "--count", "4", "--randomize", "--size",
                 "320x192", "--robot", str(urdf), "--keypoints", str(kp)]) == 0
    docs = [json.loads(line) for line in (out / "labels.jsonl").read_text().splitlines()]
    assert all(len(d["robots"][0]["keypoints_px"]) == 5 for d in docs)
    assert sum(any(d["robots"][0]["visible"]) for d in docs) >= 2
    assert main(["render", "--out", str(out), "--robot", str(urdf)]) == 1  # no --keypoints


def test_robot_head_views_from_inside_the_room_label_floor_and_furniture(scenario) -> None:
    """Robot mode: the head camera of the robot at a free pose looks into the room from about
    1 m above the floor; floor and walls or furniture are labelled, the robot itself is not in
    its own view, and a training row of such a view is a detector negative without crops (or
    labels the other robot instance when one stands in front)."""
    from simulation.world import World
    from training.data import Geometry, view_records

    gen = SampleGenerator(scenario, "robot", seed=2, width=160, height=120)
    world = World(scenario)
    r = scenario.site.robot_model(scenario.robot_id).footprint_radius_m
    furniture = [CLASS_ID[c] for c in ("table", "shelf", "cabinet", "box")]
    seen_furniture = seen_wall = 0
    for i in range(8):
        sample = gen(i)
        assert sample.mode == "robot" and sample.image_rgb.shape == (120, 160, 3)
        assert not world.footprint_collides(sample.robot_pose[:2], r)
        T_world_cam = np.linalg.inv(sample.camera.T_cam_world)
        assert 0.8 < T_world_cam[2, 3] < 1.3  # camera above the floor, at head height
        assert np.all(T_world_cam[:2, 3] > scenario.room_min_xy_m)
        assert np.all(T_world_cam[:2, 3] < scenario.room_max_xy_m)
        assert T_world_cam[2, 2] < 0.0  # optical axis tilted down
        assert np.mean(sample.class_id == CLASS_ID["floor"]) > 0.05
        seen_wall += bool(np.any(sample.class_id == CLASS_ID["wall"]))
        seen_furniture += bool(np.isin(sample.class_id, furniture).any())
        rows = view_records(sample, Geometry(det_w=64, det_h=48, seg_w=32, seg_h=24),
                            np.random.default_rng(0), num_keypoints=12)
        assert rows.seg_labels.shape == (1, 24, 32) and rows.crop_kp.shape[1:] == (12, 2)
        if not sample.robots:
            assert np.isnan(rows.boxes).all() and len(rows.crops) == 0
            assert not np.any(sample.class_id == CLASS_ID["robot"])
        else:
            _check_label_matches_render(sample)
    assert seen_wall >= 4 and seen_furniture >= 2
    np.testing.assert_array_equal(gen(3).class_id, gen(3).class_id)  # deterministic


def test_robot_mode_needs_a_head_camera(scenario) -> None:
    import dataclasses

    model = dataclasses.replace(scenario.site.robot_model(scenario.robot_id), head_camera=None)
    with pytest.raises(DatasetError, match="head_camera"):
        SampleGenerator(scenario, "robot", robot_model=model)
