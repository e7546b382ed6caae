"""``estimate_from_detections``: the pose from a list of camera messages, for code outside the
service; wrong argument types are a ``TypeError`` naming what was expected, bad data a result
with a reason."""

from __future__ import annotations

import math

import numpy as np
import pytest

import backend_service
from backend_service.estimate import SolverConfig, estimate_from_detections, estimate_pose
from backend_service.frame_set import frame_set_from_detections
from core.pose import PlanarPose
from protocol.messages import Detection, RobotDetections
from tests.backend_service.pose_synth import ROBOT, example_site, pose_error, project_pose

SITE = example_site()
TRUTH = PlanarPose(10.3, 5.4, -2.88)
CAMS = ("cam_ne", "cam_sw")


def _message(cam_id: str, robot_id: str = "", keypoints: int | None = None,
             size: tuple[int, int] | None = None, seen: bool = True) -> RobotDetections:
    cam = SITE.camera(cam_id)
    uv, ok = project_pose(SITE, TRUTH, cam_id)
    uv = np.where(ok[:, None], uv, 0.0)
    if keypoints is not None:
        uv, ok = uv[:keypoints], ok[:keypoints]
    lo, hi = uv[ok].min(axis=0), uv[ok].max(axis=0)
    dets = (Detection(np.array([*lo, *hi]), 0.9, uv, ok.astype(float), robot_id),) if seen \
        else ()
    w, h = size or (cam.width, cam.height)
    return RobotDetections(cam_id, 5_000_000_000, 3, w, h, "m", dets)


def test_pose_from_messages_with_and_without_prior() -> None:
    msgs = [_message(c) for c in CAMS]
    for prior in (None, PlanarPose(TRUTH.x + 0.2, TRUTH.y, TRUTH.theta + 0.1)):
        res = estimate_from_detections(SITE, msgs, prior)
        assert res.ok, res.reason
        dp, dth = pose_error(res.pose, TRUTH)
        assert dp < 1e-3 and dth < math.radians(0.05)
        assert set(res.estimate.camera_ids) == set(CAMS)
    # the same as building the frame-set by hand
    fs, problems = frame_set_from_detections(SITE, msgs)
    assert problems == [] and fs.robot_id == ROBOT
    assert estimate_pose(fs, SITE).pose == estimate_from_detections(SITE, msgs).pose
    # exported at the package level
    assert backend_service.estimate_from_detections is estimate_from_detections


def test_single_message_and_named_robot() -> None:
    res = estimate_from_detections(SITE, _message("cam_ne", robot_id=ROBOT), robot_id=ROBOT,
                                   config=SolverConfig(single_camera="plain"))
    assert res.ok, res.reason


def test_unusable_messages_are_explained_not_raised() -> None:
    msgs = [_message("cam_ne", seen=False), _message("cam_sw", keypoints=5),
            _message("cam_nw", size=(640, 360)),
            RobotDetections("cam_zz", 1, 0, 848, 480, "m", ())]
    res = estimate_from_detections(SITE, msgs)
    assert not res.ok
    for needle in ("not seen", "keypoint count", "640x360", "unknown camera 'cam_zz'"):
        assert needle in res.reason, res.reason
    assert not estimate_from_detections(SITE, []).ok
    # one good camera among bad ones still gives a pose; duplicates are reported
    fs, problems = frame_set_from_detections(SITE, [_message("cam_ne"), _message("cam_ne"),
                                                    _message("cam_sw", seen=False)])
    assert fs.camera_ids == ("cam_ne",)
    assert any("twice" in p for p in problems) and any("not seen" in p for p in problems)


def test_wrong_argument_types_name_what_was_expected() -> None:
    msgs = [_message(c) for c in CAMS]
    with pytest.raises(TypeError, match="RobotDetections"):
        estimate_from_detections(SITE, [msgs[0], {"camera_id": "cam_sw"}])
    with pytest.raises(TypeError, match="sequence of RobotDetections"):
        estimate_from_detections(SITE, "cam_ne")
    with pytest.raises(TypeError, match="Site"):
        estimate_from_detections("site.yaml", msgs)
    with pytest.raises(TypeError, match="PlanarPose"):
        estimate_from_detections(SITE, msgs, prior=(1.0, 2.0, 0.0))
    with pytest.raises(TypeError, match="SolverConfig"):
        estimate_from_detections(SITE, msgs, config={"robust_loss": "none"})
    with pytest.raises(TypeError, match="estimate_from_detections"):
        estimate_pose(msgs, SITE)
