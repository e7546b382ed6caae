"""The closed loop through images: :class:`lab.rendered_detections.RenderedDetections`
renders each simulated camera frame (true camera pose, robot at its true pose, per-frame sensor
noise) and runs the shipped ONNX models on it, in place of the detection noise model.

Checked: a frame gives the edge agent's message (one detection with keypoints within pixels of
the true projection, sigmas, the camera's stamp, the models' id); a frame without the robot in
the image is not rendered and has no detections; a static robot's clean render is reused while
the sensor noise differs per frame; :class:`SensorNoise` validates and 0 means identical
frames; a short :class:`SimulationRun` at 5 Hz streams these messages."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("moderngl")
pytest.importorskip("onnxruntime")

from protocol.messages import RobotDetections

K = 12  # the paper robot's keypoints
T0_NS = 1_700_000_000_000_000_000
#: a pose far to the west of the lab: cam1 (and cam4) look away from it
OUTSIDE_CAM1 = np.array([2.0, 5.0, 0.0])


@pytest.fixture(scope="module")
def scenario():
    from simulation.scenario import PAPER_SCENARIO, load_scenario

    return load_scenario(PAPER_SCENARIO)


@pytest.fixture(scope="module")
def det(scenario):
    from lab.rendered_detections import RenderedDetections

    d = RenderedDetections(scenario, world=None, threads=1)
    yield d
    d.images.release()


@pytest.fixture(scope="module")
def seen_pose(scenario, det) -> np.ndarray:
    """The first waypoint of traj3 that at least two cameras see."""
    for w in scenario.trajectory("traj3", False):
        pose = np.array([w.x, w.y, w.theta])
        if len(det.cameras_seeing(pose)) >= 2:
            return pose
    pytest.fail("no waypoint of traj3 is seen by two cameras")


def test_is_a_detection_simulator_with_the_shipped_models(det) -> None:
    from simulation.detections import DetectionSimulator

    assert isinstance(det, DetectionSimulator)
    assert det.model_id == det.models.model_id and det.model_id.startswith("hsr/")
    assert det.models.keypoints.calibrated
    assert set(det.pipelines) == set(det.cameras)


def test_detect_gives_keypoints_near_the_true_projection(det, seen_pose: np.ndarray) -> None:
    """Every camera that sees the pose: one detection, keypoints (12, 2) near the true
    projection (median over the cameras < 3 px, per camera < 8 px), sigmas, the camera's
    stamp, seq, size and the models' id."""
    rng = np.random.default_rng(1)
    cams = det.cameras_seeing(seen_pose)
    assert len(cams) >= 2
    errors = []
    for seq, cam in enumerate(cams):
        before = det.stats.frames
        msg = det.detect(cam, T0_NS, seen_pose, seq, rng)
        assert det.stats.frames == before + 1
        assert isinstance(msg, RobotDetections)
        assert msg.camera_id == cam and msg.seq == seq
        assert msg.stamp_ns == det.capture_stamp_ns(cam, T0_NS)
        assert msg.model_id == det.model_id
        assert (msg.image_width, msg.image_height) == (det.cameras[cam].width,
                                                       det.cameras[cam].height)
        assert len(msg.detections) == 1, cam
        d = msg.detections[0]
        assert d.keypoints_px.shape == (K, 2)
        assert d.keypoint_sigmas_px is not None and d.keypoint_sigmas_px.shape == (K,)
        assert np.all(np.isfinite(d.keypoint_sigmas_px)) and np.all(d.keypoint_sigmas_px > 0)
        truth = det.visibility(cam, seen_pose).uv
        err = np.linalg.norm(d.keypoints_px - truth, axis=1)
        assert float(np.median(err)) < 8.0, (cam, err)
        # the box holds the true keypoints (a few pixels of slack)
        x0, y0, x1, y1 = d.bbox_xyxy
        inside = ((truth[:, 0] >= x0 - 5) & (truth[:, 0] <= x1 + 5)
                  & (truth[:, 1] >= y0 - 5) & (truth[:, 1] <= y1 + 5))
        assert inside.mean() >= 0.9, (cam, d.bbox_xyxy, truth)
        errors.append(err)
    assert float(np.median(np.concatenate(errors))) < 3.0, errors


def test_robot_outside_the_image_gives_no_detections_and_no_render(det) -> None:
    cam = "cam1"
    assert not det.images.robot_in_image(cam, OUTSIDE_CAM1)
    assert cam not in det.cameras_seeing(OUTSIDE_CAM1)
    frames, out, renders = det.stats.frames, det.stats.out_of_view, det.images.renders
    msg = det.detect(cam, T0_NS + 5, OUTSIDE_CAM1, 9, np.random.default_rng(2))
    assert isinstance(msg, RobotDetections) and msg.detections == ()
    assert msg.stamp_ns == det.capture_stamp_ns(cam, T0_NS + 5) and msg.seq == 9
    assert msg.model_id == det.model_id
    assert det.stats.frames == frames + 1 and det.stats.out_of_view == out + 1
    assert det.images.renders == renders


def test_static_robot_reuses_the_clean_render(det, seen_pose: np.ndarray) -> None:
    cam = det.cameras_seeing(seen_pose)[0]
    rng = np.random.default_rng(3)
    det.detect(cam, T0_NS, seen_pose, 0, rng)  # the clean render of this pose is cached now
    hits, renders = det.stats.cache_hits, det.stats.renders
    a = det.detect(cam, T0_NS + 66_000_000, seen_pose, 1, rng)
    b = det.detect(cam, T0_NS + 133_000_000, seen_pose, 2, rng)
    assert det.stats.cache_hits == hits + 2 and det.stats.renders == renders
    assert len(a.detections) == len(b.detections) == 1
    # the same scene, different noise: nearly the same keypoints, sub-pixel apart at most
    diff = np.abs(a.detections[0].keypoints_px - b.detections[0].keypoints_px)
    assert float(np.median(diff)) < 1.0
    # a moved robot is rendered again
    moved = seen_pose + np.array([0.05, 0.0, 0.0])
    det.detect(cam, T0_NS, moved, 3, rng)
    assert det.stats.renders == renders + 1


def test_frames_of_a_static_robot_differ_by_sensor_noise(det, seen_pose: np.ndarray) -> None:
    cam = det.cameras_seeing(seen_pose)[0]
    rng = np.random.default_rng(4)
    clean = det.images.render_clean(cam, seen_pose).astype(np.int16)
    a = det.images.render(cam, seen_pose, rng)
    b = det.images.render(cam, seen_pose, rng)
    assert a.shape == b.shape == clean.shape and a.dtype == b.dtype == np.uint8
    assert not np.array_equal(a, b)
    mad = float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))
    assert 0.5 < mad < 5.0, mad
    noise = a.astype(np.int16) - clean
    assert abs(float(noise.mean())) < 0.5  # zero-mean
    assert 0.5 < float(noise.std()) < 5.0
    # the same generator state gives the same frame (reproducible runs)
    c = det.images.render(cam, seen_pose, np.random.default_rng(4))
    np.testing.assert_array_equal(a, c)


@pytest.mark.parametrize("sigma", [-1.0, float("nan"), float("inf")])
def test_sensor_noise_rejects_bad_sigmas(sigma: float) -> None:
    from simulation.site_cameras import SensorNoise

    with pytest.raises(ValueError, match="sigma_dn"):
        SensorNoise(sigma)


def test_zero_sensor_noise_gives_identical_frames(scenario, seen_pose: np.ndarray) -> None:
    from simulation.site_cameras import SensorNoise, SiteCameraRenderer

    images = SiteCameraRenderer(scenario, noise=SensorNoise(0))
    try:
        rng = np.random.default_rng(5)
        a = images.render("cam1", seen_pose, rng)
        b = images.render("cam1", seen_pose, rng)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, images.render_clean("cam1", seen_pose))
        assert images.renders == 1 and a.std() > 5.0  # one real render, not a blank image
        a[0, 0] = 255 - a[0, 0]  # a returned frame is the caller's, not the cache
        assert not np.array_equal(a, images.render_clean("cam1", seen_pose))
    finally:
        images.release()


def test_short_closed_loop_run_streams_rendered_detections(scenario, det) -> None:
    """4 s of traj3 at 5 Hz through the renderer and the networks: one message per camera
    frame, with the models' id, consecutive seqs; the robot is found, near its true
    projection at the frame's capture time."""
    from simulation.runner import SimulationRun

    sc5 = scenario.with_overrides(cameras=dataclasses.replace(scenario.cameras, rate_hz=5.0))
    run = SimulationRun(sc5, "traj3", seed=0, world=det.world, detector=det)
    assert run.detector is det and run.world is det.world
    frames = det.stats.frames
    msgs = [m.message for m in run.messages(until_s=4.0)]
    dets = [m for m in msgs if isinstance(m, RobotDetections)]
    n_cams = len(sc5.site.cameras)
    assert 4 * 5 * n_cams - n_cams <= len(dets) <= 4 * 5 * n_cams + n_cams, len(dets)
    assert det.stats.frames == frames + len(dets)
    assert all(m.model_id == det.model_id for m in dets)
    for cam in sc5.site.cameras:
        seqs = sorted(m.seq for m in dets if m.camera_id == cam)
        assert seqs == list(range(len(seqs))), (cam, seqs)
    found = [m for m in dets if m.detections]
    assert found, "no frame of the run had a detection"
    assert len(found) >= 0.5 * len(dets), (len(found), len(dets))
    errors = []
    for m in found:
        cam_site = sc5.site.cameras[m.camera_id]
        true_ns = m.stamp_ns + cam_site.clock_offset_ns - det.clock_residual_ns[m.camera_id]
        pose = run.ground_truth_at(np.array([true_ns]))[0]
        d = m.detections[0]
        assert d.keypoint_sigmas_px is not None
        errors.append(np.linalg.norm(d.keypoints_px - det.visibility(m.camera_id, pose).uv,
                                     axis=1))
    assert float(np.median(np.concatenate(errors))) < 5.0


def test_a_batch_of_frames_gives_each_frame_its_own_message(det, seen_pose: np.ndarray) -> None:
    """The cameras' frames of one capture through the networks together
    (:meth:`detect_many`, one batch per network) give the messages each frame gives alone."""
    from simulation.detections import FrameRequest

    cams = list(det.cameras)
    assert len(det.cameras_seeing(seen_pose)) >= 2
    poses = [seen_pose, seen_pose + np.array([0.02, -0.01, 0.05]), OUTSIDE_CAM1, seen_pose]

    def requests() -> list[FrameRequest]:
        return [FrameRequest(c, T0_NS + 7 * i, poses[i % len(poses)], i,
                             np.random.default_rng(100 + i)) for i, c in enumerate(cams)]

    batch = det.detect_many(requests())
    alone = [det.detect(r.camera_id, r.true_capture_ns, r.pose, r.seq, r.rng)
             for r in requests()]
    assert batch == alone
    assert sum(bool(m.detections) for m in batch) >= 2  # the batch held frames with the robot


def test_the_runner_batches_the_frames_of_one_capture_without_changing_them(
        scenario, det) -> None:
    """A run's messages are the same whether the runner hands the detector the cameras'
    frames of one capture together or one by one."""
    from simulation.runner import SimulationRun

    sc5 = scenario.with_overrides(cameras=dataclasses.replace(scenario.cameras, rate_hz=5.0))
    streams = {}
    calls = {}
    real_detect_many = det.detect_many
    for batched in (True, False):
        sizes: list[int] = []

        def counting(frames, sizes=sizes):  # type: ignore[no-untyped-def]
            sizes.append(len(frames))
            return real_detect_many(frames)

        det.detect_many = counting  # type: ignore[method-assign]
        det.batches_frames = batched  # type: ignore[misc]
        try:
            run = SimulationRun(sc5, "traj3", seed=1, world=det.world, detector=det)
            streams[batched] = [(m.arrival_ns, m.message) for m in run.messages(until_s=2.0)]
        finally:
            del det.detect_many, det.batches_frames
        calls[batched] = sizes
    assert streams[True] == streams[False]
    n_cams = len(sc5.site.cameras)
    assert max(calls[True]) == n_cams and set(calls[False]) == {1}
    assert sum(calls[True]) == sum(calls[False])
