"""``smartedge evaluate paper --detections cnn``: the paper's experiment 1 with every camera frame
rendered and run through the shipped ONNX models, through the backend's one pipeline."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("moderngl", reason="rendering needs moderngl")

from lab.experiments import PaperConfig, run_paper, source_errors


@pytest.fixture(scope="module")
def cnn_report(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("paper_cnn")
    lines: list[str] = []
    # 2 Hz: 1636 frames (3 Hz: 2456), the same 12 multi-camera waypoint samples, 2.4 cm
    # mean at either rate
    cfg = PaperConfig(runs_per_direction=1, trajectories=("traj3",), stop_s=2.0,
                      experiments=(1,), detections="cnn", threads=1, use_fusion=False,
                      camera_rate_hz=2.0)
    report = run_paper(cfg, out, progress=lines.append)
    return report, lines, out


def test_cnn_mode_renders_and_infers_every_frame(cnn_report) -> None:
    _report, lines, out = cnn_report
    assert any("rendered images" in ln and "ONNX models hsr/models" in ln and "2 Hz" in ln
               for ln in lines), lines
    image_lines = [ln for ln in lines if ln.strip().startswith("images so far:")]
    assert len(image_lines) == 2  # one per run
    assert "renders" in image_lines[-1] and "static reuses" in image_lines[-1]
    assert (out / "table1.md").exists() and (out / "results.json").exists()
    assert json.loads((out / "results.json").read_text())["runs"] == 2


def test_cnn_keypoints_localize_the_robot_at_multi_camera_waypoints(cnn_report) -> None:
    report = cnn_report[0]
    err = source_errors(report.accuracy_runs, "one_frame")
    multi = err.num_cameras >= 2
    assert multi.sum() >= 6
    assert err.translation_m[multi].mean() < 0.05
    assert np.rad2deg(err.heading_rad[multi]).mean() < 6.0
    robot = source_errors(report.accuracy_runs, "robot")
    assert err.translation_m[multi].mean() < robot.translation_m.mean()


def test_unknown_detection_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="detections"):
        PaperConfig(detections="magic")
    with pytest.raises(ValueError, match="camera_rate_hz"):
        PaperConfig(camera_rate_hz=0.0)
