"""Detections are checked against the camera's calibrated image size: an exact scale (a binned or
resized stream) is converted to calibrated pixels, anything else is dropped and counted."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from backend_service.estimate import estimate_pose
from backend_service.frame_set import image_scale, scale_detection
from backend_service.sync import FrameSetSynchronizer
from core.pose import PlanarPose
from protocol.messages import Detection, RobotDetections
from tests.backend_service.pose_synth import ROBOT, example_site, pose_error, project_pose

SITE = example_site()
CAMS = ("cam_ne", "cam_sw")
TRUTH = PlanarPose(10.3, 5.4, -2.88)
T0 = 1_000_000_000_000


def _message(cam_id: str, stamp_ns: int, scale: float, size: tuple[int, int] | None = None,
             with_sigmas: bool = True) -> RobotDetections:
    """The exact detections of :data:`TRUTH` as a camera streaming at 1/``scale`` of its
    calibrated resolution would send them (pixel centres at integers)."""
    cam = SITE.camera(cam_id)
    uv, ok = project_pose(SITE, TRUTH, cam_id)
    uv = np.where(ok[:, None], uv, 0.0)
    small = (uv + 0.5) / scale - 0.5
    lo, hi = small[ok].min(axis=0) - 2, small[ok].max(axis=0) + 2
    w, h = size or (round(cam.width / scale), round(cam.height / scale))
    det = Detection(np.array([*lo, *hi]), 0.9, small, ok.astype(float), "",
                    np.full(len(uv), 0.8 / scale) if with_sigmas else None)
    return RobotDetections(cam_id, stamp_ns, 0, w, h, "m", (det,))


def _frame_sets(scale: float, size: tuple[int, int] | None = None):
    sync = FrameSetSynchronizer(SITE, ROBOT)
    out = []
    for i, cam_id in enumerate(CAMS):
        out += sync.push(_message(cam_id, T0 + i * 1000, scale, size), T0 + 10**6)
    out += sync.flush()
    return sync, [fs for fs in out if fs.observations]


def test_image_scale() -> None:
    assert image_scale(848, 480, 848, 480) == 1.0
    assert image_scale(424, 240, 848, 480) == 2.0
    assert image_scale(1280, 720, 1920, 1080) == 1.5
    assert image_scale(1696, 960, 848, 480) == 0.5
    assert image_scale(640, 360, 848, 480) is None  # 16:9 against 53:30
    assert image_scale(848, 479, 848, 480) is None
    assert image_scale(0, 0, 848, 480) is None


def test_scale_detection_maps_pixel_centres() -> None:
    det = Detection(np.array([0.0, 0.0, 10.0, 5.0]), 0.5, np.array([[0.0, 0.0], [1.0, 2.0]]),
                    np.array([1.0, 0.5]), "", np.array([1.0, 2.0]))
    full = scale_detection(det, 2.0)
    # half-resolution pixel 0 covers full-resolution pixels 0 and 1: centre 0.5
    np.testing.assert_allclose(full.keypoints_px, [[0.5, 0.5], [2.5, 4.5]])
    np.testing.assert_allclose(full.bbox_xyxy, [0.5, 0.5, 20.5, 10.5])
    np.testing.assert_allclose(full.keypoint_sigmas_px, [2.0, 4.0])
    np.testing.assert_array_equal(full.keypoint_scores, det.keypoint_scores)


@pytest.mark.parametrize("scale", [2.0, 0.5], ids=["half", "double"])
def test_scaled_streams_give_the_full_resolution_pose(scale: float) -> None:
    _, full = _frame_sets(1.0)
    sync, scaled = _frame_sets(scale)
    assert len(full) == len(scaled) == 1
    assert sync.counters["image_size"] == 0
    np.testing.assert_allclose(
        np.stack([o.keypoints_px for o in scaled[0].observations]),
        np.stack([o.keypoints_px for o in full[0].observations]), atol=1e-9)
    prior = PlanarPose(TRUTH.x + 0.2, TRUTH.y - 0.1, TRUTH.theta + 0.1)
    a = estimate_pose(full[0], SITE, prior)
    b = estimate_pose(scaled[0], SITE, prior)
    assert a.ok and b.ok
    assert pose_error(a.pose, b.pose)[0] < 1e-6 and pose_error(a.pose, b.pose)[1] < 1e-6
    assert pose_error(b.pose, TRUTH)[0] < 1e-4


def test_another_image_size_is_dropped_counted_and_logged_once(caplog) -> None:
    caplog.set_level(logging.WARNING, logger="backend_service.sync")
    sync = FrameSetSynchronizer(SITE, ROBOT)
    out = []
    for k in range(3):
        out += sync.push(_message("cam_ne", T0 + k * 10**8, 1.0, size=(640, 360)),
                         T0 + k * 10**8 + 10**6)
    out += sync.flush()
    assert sync.counters["image_size"] == 3
    assert not any(fs.observations for fs in out)
    warnings = [r for r in caplog.records if "image_size" in r.getMessage()]
    assert len(warnings) == 1 and "640x360" in warnings[0].getMessage()
    assert "cam_ne" in warnings[0].getMessage()
