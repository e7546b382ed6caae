"""Intrinsics from rendered ChArUco views: the truth recovered, bad views skipped with their
reason, too few views refused, calibration files read back by the site loader."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.board import BoardDetector, CalibrationError
from calibration.intrinsics import (
    calibrate_intrinsics,
    coverage_image,
    model_difference_px,
    write_camera_info_yaml,
    write_opencv_yaml,
)
from core.site import load_camera_calibration
from tests.calibration.rendered import (
    INTRINSICS_BOARD,
    boardless_view,
    partial_view,
    sweep_views,
)


@pytest.fixture(scope="module")
def calibrated():
    cam, views = sweep_views()
    det = BoardDetector(INTRINSICS_BOARD)
    detections = [(f"view{i:02d}", det.detect(v.image_rgb)) for i, v in enumerate(views)]
    return cam, views, detections, calibrate_intrinsics(detections, INTRINSICS_BOARD, "cam1")


def test_detected_corners_match_the_rendered_truth(calibrated) -> None:
    _, views, detections, _ = calibrated
    errors = np.concatenate([d.corners_px - v.corners_px[d.corner_ids]
                             for v, (_, d) in zip(views, detections, strict=True) if d.usable])
    assert len(errors) > 600
    rms = float(np.sqrt((errors ** 2).sum(axis=1).mean()))
    assert rms < 0.15, rms
    assert np.all(np.abs(errors.mean(axis=0)) < 0.02), errors.mean(axis=0)


def test_intrinsics_recover_the_true_camera(calibrated) -> None:
    cam, _, _, result = calibrated
    truth = np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]])
    est = np.array([result.K[0, 0], result.K[1, 1], result.K[0, 2], result.K[1, 2]])
    assert np.all(np.abs(est / truth - 1.0) < 0.005), est / truth - 1.0
    assert result.rms_px < 0.3
    assert len(result.views) >= 20 and result.coverage_fraction > 0.7
    # the lens model: the same rays through the true and the estimated model, over the image
    # region the views covered
    diff = model_difference_px(cam.K, cam.dist, result.K, result.dist,
                               (cam.width, cam.height), coverage=result.coverage)
    assert float(diff.mean()) < 0.2, (diff.mean(), diff.max())
    assert float(np.percentile(diff, 95)) < 0.3
    # and it can fail: the nominal model without distortion is far off
    off = model_difference_px(cam.K, cam.dist, cam.K, np.zeros(5), (cam.width, cam.height),
                              coverage=result.coverage)
    assert float(off.mean()) > 1.0
    picture = coverage_image(result)
    assert picture.shape == (cam.height, cam.width, 3)


def test_bad_views_are_skipped_with_their_reason(calibrated) -> None:
    _, views, detections, _ = calibrated
    det = BoardDetector(INTRINSICS_BOARD)
    blurred = cv2.GaussianBlur(views[0].image_rgb, (0, 0), 2.5)
    extra = [("blurred", det.detect(blurred)), ("partial", det.detect(partial_view().image_rgb)),
             ("empty", det.detect(boardless_view().image_rgb))]
    result = calibrate_intrinsics(detections + extra, INTRINSICS_BOARD, "cam1")
    assert "blurred" in result.skipped["blurred"]
    assert result.skipped["partial"].startswith("too few corners (4 < 6")
    assert result.skipped["empty"].startswith("no board found")
    used = {v.name for v in result.views}
    assert not used & {"blurred", "partial", "empty"}


def test_too_few_views_fail_naming_how_many_and_why(calibrated) -> None:
    _, _, detections, _ = calibrated
    det = BoardDetector(INTRINSICS_BOARD)
    few = [d for d in detections if d[1].usable][:5]
    few += [("empty", det.detect(boardless_view().image_rgb)),
            ("partial", det.detect(partial_view().image_rgb))]
    with pytest.raises(CalibrationError) as err:
        calibrate_intrinsics(few, INTRINSICS_BOARD, "cam1")
    text = str(err.value)
    assert "only 5 usable views of 7 images (need at least 8)" in text
    assert "empty: no board found" in text and "partial: too few corners" in text


def test_calibration_files_round_trip_through_the_site_loader(calibrated, tmp_path) -> None:
    _, _, _, result = calibrated
    for path in (write_camera_info_yaml(result, tmp_path / "cam1.yaml"),
                 write_opencv_yaml(result, tmp_path / "cam1_opencv.yaml")):
        calib = load_camera_calibration(path)
        assert (calib.width, calib.height) == (result.width, result.height)
        np.testing.assert_allclose(calib.K, result.K, rtol=1e-12)
        np.testing.assert_allclose(calib.dist, result.dist, rtol=1e-12, atol=1e-15)
    assert "!!opencv-matrix" in (tmp_path / "cam1_opencv.yaml").read_text()  # FileStorage
    assert "plumb_bob" in (tmp_path / "cam1.yaml").read_text()
