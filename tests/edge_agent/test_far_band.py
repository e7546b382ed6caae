"""The far band (edge_agent/far_band.py): the rows of a static camera's frame where robots 7 m and
more away appear, run through the detector at twice its scale. Its rows come from the camera's
calibration; its boxes map back to frame pixels, lose the robots it cuts and join the whole
frame's; the shipped detector runs it (a free input size); a rendered far robot that the whole
frame misses is found with it, and a near robot's detections do not change."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from core.camera import CameraModel
from core.site import load_site, look_at_T_world_cam
from edge_agent.boxes import box_iou
from edge_agent.far_band import FAR_BAND_CHOICES, FarBand, far_band_for_camera, far_rows
from edge_agent.model_cards import default_model_dir
from edge_agent.models import RobotKeypointPipeline
from edge_agent.networks import (
    FAR_BAND_EDGE_PX,
    MAX_BAND_SESSIONS,
    Detector,
    far_band_to_frame,
    merge_far_band_boxes,
)
from edge_agent.pipeline import EdgePipeline, camera_far_band, far_band_from_args

REPO_ROOT = Path(__file__).resolve().parents[2]
PAPER_SITE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"


def _camera(position_m: tuple[float, float, float], target_m: tuple[float, float, float],
            width: int = 848, height: int = 480) -> CameraModel:
    K = np.array([[425.0, 0.0, (width - 1) / 2], [0.0, 425.0, (height - 1) / 2], [0, 0, 1]])
    T_world_cam = look_at_T_world_cam(np.array(position_m), np.array(target_m))
    return CameraModel("cam", width, height, K, np.zeros(5), np.linalg.inv(T_world_cam))


def test_band_covers_the_rows_of_far_robots_and_only_those() -> None:
    """Robots standing 7 m deep and more, projected by the camera model itself, have their feet
    and heads inside the band; a robot 4 m away has its feet below the band's feet row."""
    site = load_site(PAPER_SITE)
    cam = site.camera("cam1")
    height_m = site.robot_model("hsr").height_m
    band = far_band_for_camera(cam, height_m, 424)
    assert band is not None
    assert band.scale == 1.0 and (band.input_w, band.input_h) == (848, band.v1 - band.v0)
    assert band.v0 % 8 == 0 and band.v1 % 8 == 0
    assert band.v1 - band.v0 <= 240, band  # at most half the frame
    # robots straight ahead and to the sides, 7.5-14 m deep
    c = cam.position_world
    axis = cam.optical_axis_world[:2] / np.linalg.norm(cam.optical_axis_world[:2])
    side = np.array([-axis[1], axis[0]])
    feet_rows, head_rows = [], []
    for depth in (7.5, 10.0, 14.0):
        for lateral in (-3.0, 0.0, 3.0):
            xy = c[:2] + axis * depth + side * lateral
            uv = cam.project_cam(cam.world_to_cam(np.array([[*xy, 0.0], [*xy, height_m]])))
            if 0 <= uv[0, 0] < cam.width:
                feet_rows.append(uv[0, 1])
                head_rows.append(uv[1, 1])
    assert len(feet_rows) >= 6
    assert band.v0 <= min(head_rows) and max(feet_rows) <= band.feet_max_v <= band.v1
    near = c[:2] + axis * 4.0
    near_feet = cam.project_cam(cam.world_to_cam(np.array([[*near, 0.0]])))[0, 1]
    assert near_feet > band.feet_max_v + 30


def test_cameras_without_a_far_band() -> None:
    # looking straight down from 3 m: no floor 7 m deep in view
    down = _camera((5.0, 5.0, 3.0), (5.01, 5.0, 0.0))
    assert far_rows(down, 1.0, 7.0, 20.0) is None
    assert far_band_for_camera(down, 1.0, 424) is None
    # a detector that already sees the frame at full resolution cannot zoom in twice
    oblique = _camera((0.0, 0.0, 2.5), (6.0, 0.0, 0.0), width=424, height=240)
    assert far_band_for_camera(oblique, 1.0, 424) is None
    assert far_band_for_camera(_camera((0.0, 0.0, 2.5), (6.0, 0.0, 0.0)), 1.0, 424) is not None
    with pytest.raises(ValueError, match="robot height"):
        far_band_for_camera(oblique, 0.0, 424)


def test_far_band_validates_its_rows_and_scale() -> None:
    with pytest.raises(ValueError, match=r"rows 100\.\.90"):
        FarBand(100, 90, 848, 480, 1.0)
    with pytest.raises(ValueError, match="scale"):
        FarBand(0, 100, 848, 480, 1.5)
    assert FarBand(0, 100, 848, 480, 1.0).feet_max_v == 100.0
    assert FarBand(32, 200, 848, 480, 1.0).applies_to(848, 480)
    assert not FarBand(32, 200, 848, 480, 1.0).applies_to(640, 480)


def test_band_boxes_map_to_the_frame_and_cut_robots_are_dropped() -> None:
    band = FarBand(40, 200, 848, 480, 0.5, feet_max_v=180.0)  # input 424x80, 2 px per input px
    assert (band.input_w, band.input_h) == (424, 80)
    boxes = np.array([
        [99.5, 19.5, 109.5, 39.5, 0.9],   # frame (199.5..219.5, 79.5..119.5): kept
        [9.5, -0.5, 19.5, 20.0, 0.8],     # top at the band's upper edge: cut
        [49.5, 40.0, 69.5, 79.5, 0.7],    # bottom below the feet row: a nearer robot, cut
    ])
    out = far_band_to_frame(boxes, band)
    np.testing.assert_allclose(out, [[199.5, 79.5, 219.5, 119.5, 0.9]])
    # a band at the frame's top keeps boxes touching its upper edge
    top = FarBand(0, 160, 848, 480, 0.5)
    assert len(far_band_to_frame(boxes[1:2], top)) == 1
    # the lower limit is the feet row plus the tolerance
    edge = np.array([[10.0, 10.0, 20.0, (180.0 + FAR_BAND_EDGE_PX - 40 + 0.5) / 2 - 0.5, 0.5]])
    assert len(far_band_to_frame(edge, band)) == 1
    edge[0, 3] += 1.0
    assert len(far_band_to_frame(edge, band)) == 0


def test_merge_fuses_a_robot_both_see_and_adds_the_far_one() -> None:
    whole = np.array([[100.0, 100.0, 140.0, 200.0, 0.9], [600.0, 80.0, 620.0, 120.0, 0.3]])
    band = np.array([[601.0, 81.0, 621.0, 121.0, 0.9],   # the far robot, seen better
                     [400.0, 70.0, 416.0, 104.0, 0.6]])  # one the whole frame missed
    out, added = merge_far_band_boxes(whole, band, max_detections=8)
    assert added == 1 and len(out) == 3
    np.testing.assert_allclose(out[:, 4], [0.9, 0.9, 0.6])
    far = out[np.argmin(np.abs(out[:, 0] - 600.5))]
    np.testing.assert_allclose(far[:4], [600.75, 80.75, 620.75, 120.75])  # weights 0.3 / 0.9
    assert box_iou(out[0, :4], whole[0, :4]) == 1.0 or box_iou(out[1, :4], whole[0, :4]) == 1.0
    same, none_added = merge_far_band_boxes(whole, np.zeros((0, 5)), 8)
    assert none_added == 0
    np.testing.assert_array_equal(same, whole)
    capped, _ = merge_far_band_boxes(whole, band, max_detections=2)
    assert len(capped) == 2


def test_shipped_detector_runs_a_far_band_and_keeps_its_whole_frame_size() -> None:
    det = Detector(default_model_dir() / "detector.onnx", threads=1)
    assert det.runs_far_band and det.spatial_dims == ("height", "width")
    assert list(det.session.get_inputs()[0].shape[1:]) == [3, 240, 424]
    image = np.zeros((480, 848, 3), np.uint8)
    band = FarBand(32, 200, 848, 480, 1.0)
    assert det.detect_many([image, image], 0.3, 8, [band, None])[0].shape[1] == 5
    with pytest.raises(ValueError, match="2 far bands for 1 frames"):
        det.detect_many([image], 0.3, 8, [band, band])


def test_a_detector_file_with_a_fixed_input_size_runs_without_its_band(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    onnx = pytest.importorskip("onnx")
    import shutil

    model = onnx.load(str(default_model_dir() / "detector.onnx"))
    dims = model.graph.input[0].type.tensor_type.shape.dim
    dims[2].dim_value, dims[3].dim_value = 240, 424
    onnx.save(model, str(tmp_path / "detector.onnx"))
    shutil.copy(default_model_dir() / "detector.json", tmp_path / "detector.json")
    det = Detector(tmp_path / "detector.onnx", threads=1)
    assert not det.runs_far_band
    image = np.zeros((480, 848, 3), np.uint8)
    with caplog.at_level("WARNING"):
        det.detect_many([image], 0.3, 8, [FarBand(32, 200, 848, 480, 1.0)])
        det.detect_many([image], 0.3, 8, [FarBand(32, 200, 848, 480, 1.0)])
    assert sum("fixed input size" in r.getMessage() for r in caplog.records) == 1


def test_far_band_option_auto_is_off_on_the_cpu_and_on_runs_it() -> None:
    site = load_site(PAPER_SITE)
    models = RobotKeypointPipeline.for_robot(site.robot_model("hsr"), threads=1)
    args = argparse.Namespace(camera="cam2", far_band="auto")
    assert far_band_from_args(args, site, models) is None  # CPU provider
    args.far_band = "on"
    band = far_band_from_args(args, site, models)
    assert band == camera_far_band(site, "cam2", models) and band is not None
    args.far_band = "off"
    assert far_band_from_args(args, site, models) is None
    assert FAR_BAND_CHOICES == ("auto", "on", "off")


@pytest.fixture(scope="module")
def lab_views():  # type: ignore[no-untyped-def]
    """Two views of the paper lab's site cameras (held-out seed 4242): a robot 11.7 m away
    whose box the whole frame misses (its best box there overlaps it by IoU 0.29 at 0.24),
    and a robot 5.6 m away."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    gen = SampleGenerator(scenario, "site", seed=4242)
    return scenario, gen(180), gen(0)


def _hits(found, box) -> list[float]:  # type: ignore[no-untyped-def]
    return [o.score for o in found if o.score >= 0.3 and box_iou(o.bbox_xyxy, box) >= 0.5]


def test_a_far_robot_the_whole_frame_misses_is_found_with_the_band(lab_views) -> None:  # type: ignore[no-untyped-def]
    scenario, far, near = lab_views
    site = scenario.site
    models = RobotKeypointPipeline.for_robot(site.robot_model(scenario.robot_id), threads=2)
    band = camera_far_band(site, far.camera.camera_id, models)
    assert band is not None and band.applies_to(far.camera.width, far.camera.height)
    box = far.robots[0].bbox_xyxy
    assert not _hits(models(far.image_rgb), box)
    assert len(_hits(models(far.image_rgb, far_band=band), box)) == 1
    assert models.far_band_added == 1
    # through the edge's per-frame pipeline, as the agent runs it, counted in its status
    from core.runtime import Stats
    from edge_agent.frames import Frame
    from edge_agent.sources import PipelineSource

    edge = EdgePipeline(far.camera.camera_id, models, far_band=band,
                        expected_size=(far.camera.width, far.camera.height))
    source = PipelineSource(edge)
    stats = Stats()
    source.bind_stats(stats)
    before = models.far_band_added
    msg = source.process(Frame(far.image_rgb, 1, 1), 1, 0)
    assert any(box_iou(d.bbox_xyxy, box) >= 0.5 for d in msg.detections)
    assert models.far_band_added == before + 1
    assert stats.snapshot_counters().get("far_band_boxes", 0) == before + 1
    # a near robot: the band changes nothing
    without = [(o.score, *o.bbox_xyxy) for o in models(near.image_rgb)]
    with_band = [(o.score, *o.bbox_xyxy) for o in models(near.image_rgb, far_band=band)]
    np.testing.assert_allclose(with_band, without)


def test_a_detector_keeps_a_bounded_number_of_band_sessions() -> None:
    """Cameras of many poses (the randomized evaluation) give bands of many sizes; the detector
    keeps the sessions of the most recent few only (each holds its own memory arena)."""
    det = Detector(default_model_dir() / "detector.onnx", threads=1)
    image = np.zeros((480, 848, 3), np.uint8)
    for k in range(MAX_BAND_SESSIONS + 2):
        det.detect(image, far_band=FarBand(0, 32 + 8 * k, 848, 480, 1.0))
    assert len(det._band_sessions) == MAX_BAND_SESSIONS
    assert (32 + 8 * (MAX_BAND_SESSIONS + 1), 848) in det._band_sessions
