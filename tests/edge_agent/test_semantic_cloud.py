"""Semantic clouds from a segmentation and a depth image (:mod:`edge_agent.semantic_cloud`):
back-projection through a distorted lens, the output-pixel → image-pixel mapping, filters, voxel
downsampling (counts, majority class, confidence), the cap, frames, config and input errors."""

from __future__ import annotations

import numpy as np
import pytest

from core.camera import CameraModel
from core.geometry import invert_transform, rotation_from_rpy, undistort_normalized
from edge_agent.networks import Segmentation
from edge_agent.semantic_cloud import (
    ROBOT_BASE_FRAME,
    SemanticCloudConfig,
    SemanticCloudMaker,
    back_project,
    build_semantic_cloud,
    output_pixel_centres,
    pixel_rays,
    voxel_downsample,
)
from protocol.codec import decode, encode
from protocol.messages import SemanticCloud
from protocol.semantic_classes import SEMANTIC_CLASS_ID

FLOOR, WALL, TABLE = SEMANTIC_CLASS_ID["floor"], SEMANTIC_CLASS_ID["wall"], SEMANTIC_CLASS_ID[
    "table"]
W, H = 320, 240


def _camera(dist: tuple[float, ...] = (-0.28, 0.09, 0.0012, -0.0008, -0.012),
            T_cam_world: np.ndarray | None = None) -> CameraModel:
    K = np.array([[250.0, 0.0, 161.3], [0.0, 249.0, 118.7], [0.0, 0.0, 1.0]])
    return CameraModel("cam", W, H, K, np.array(dist),
                       np.eye(4) if T_cam_world is None else T_cam_world)


def _seg(h: int, w: int, cls: int = FLOOR, conf: float = 0.9) -> Segmentation:
    return Segmentation(np.full((h, w), cls, np.uint8), np.full((h, w), conf, np.float32),
                        W, H, 1.0)


def _plane_depth(camera: CameraModel, n_cam: np.ndarray, d: float) -> np.ndarray:
    """(H, W) z of the plane {p: n . p = d} (camera optical frame) along every pixel's exact
    ray, found with OpenCV's undistortion (independent of the code under test)."""
    import cv2

    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    uv = np.stack([u, v], -1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(uv, camera.K, camera.dist, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    return (d / (rays @ n_cam)).reshape(H, W).astype(np.float32)


def test_undistortion_inverts_the_lens_model() -> None:
    """Distorting the undistorted coordinates gives back the pixel's, to 1e-12."""
    from core.geometry import distort_normalized

    cam = _camera()
    rays = pixel_rays(cam, W, H).rays
    assert np.all(np.isfinite(rays))
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    xd = (u.ravel() - cam.K[0, 2]) / cam.K[0, 0]
    yd = (v.ravel() - cam.K[1, 2]) / cam.K[1, 1]
    back = distort_normalized(rays, cam.dist)
    assert np.max(np.abs(back - np.column_stack([xd, yd]))) < 1e-12
    assert np.max(np.abs(rays - np.column_stack([xd, yd]))) > 0.05  # the lens is not trivial
    # no distortion: identity
    assert np.array_equal(undistort_normalized(np.array([[0.3, -0.2]]), np.zeros(5)),
                          [[0.3, -0.2]])


def test_planar_depth_through_a_distorted_lens_recovers_the_plane_within_a_mm() -> None:
    """A tilted plane 2-4 m away seen through a strongly distorted lens: every back-projected
    point lies on the plane (mm), at full and at quarter output resolution."""
    cam = _camera()
    n = np.array([0.2, -0.35, 1.0])
    n /= np.linalg.norm(n)
    d = 3.0
    depth = _plane_depth(cam, n, d)
    for h, w in ((H, W), (H // 4, W // 4), (37, 53)):
        pts, cls, conf = back_project(_seg(h, w), depth, cam)
        assert pts.shape == (h * w, 3) and cls.shape == conf.shape == (h * w,)
        off = pts @ n - d
        assert np.max(np.abs(off)) < 1e-3, (h, w, np.max(np.abs(off)))
    # the same depth read with the lens ignored is off by centimetres: the test can fail
    flat = _camera(dist=())
    pts, _, _ = back_project(_seg(H, W), depth, flat)
    assert np.max(np.abs(pts @ n - d)) > 0.05


def test_output_pixel_maps_to_the_nearest_image_pixel_at_a_non_trivial_scale() -> None:
    """A 320x240 image segmented at 53x37: output pixel (i, j) takes the depth of the image
    pixel nearest ((j + 0.5) W / w - 0.5, (i + 0.5) H / h - 0.5), and its ray."""
    h, w = 37, 53
    u, v = output_pixel_centres(w, h, W, H)
    assert u[0] == pytest.approx(0.5 * W / w - 0.5) and v[-1] == pytest.approx(
        (h - 0.5) * H / h - 0.5)
    cam = _camera(dist=())
    # depth encodes its own pixel: z = 1 + (v * W + u) * 1e-5
    depth = (1.0 + np.arange(W * H, dtype=np.float64) * 1e-5).reshape(H, W).astype(np.float32)
    pts, _, _ = back_project(_seg(h, w), depth, cam)
    got = np.rint((pts[:, 2].astype(np.float64) - 1.0) / 1e-5).astype(np.int64)
    ui, vi = np.floor(u + 0.5).astype(int), np.floor(v + 0.5).astype(int)
    want = (vi[:, None] * W + ui[None, :]).ravel()
    assert np.abs(got - want).max() <= 1  # float32 depth resolution
    # the ray is that pixel's: re-projecting the point lands on the integer pixel
    uv = cam.project_cam(pts)
    assert np.allclose(uv[:, 0], np.tile(ui, h), atol=1e-3)
    assert np.allclose(uv[:, 1], np.repeat(vi, w), atol=1e-3)


def test_no_depth_range_confidence_and_dynamic_classes_are_filtered() -> None:
    cam = _camera(dist=())
    depth = np.full((H, W), 2.0, np.float32)
    depth[0:10] = 0.0
    depth[10:20] = np.inf
    depth[20:30] = np.nan
    depth[30:40] = 0.1  # closer than min_range_m
    depth[40:50] = 50.0  # beyond max_range_m
    cls = np.full((H, W), FLOOR, np.uint8)
    cls[:, 0:10] = SEMANTIC_CLASS_ID["person"]
    cls[:, 10:20] = SEMANTIC_CLASS_ID["robot"]
    cls[:, 20:30] = SEMANTIC_CLASS_ID["unlabeled"]
    conf = np.full((H, W), 0.9, np.float32)
    conf[:, 30:40] = 0.1
    conf[:, 40:50] = np.nan
    seg = Segmentation(cls, conf, W, H, 0.0)
    config = SemanticCloudConfig(voxel_m=0.0, min_confidence=0.5, max_range_m=6.0,
                                 max_points=100_000)
    cloud = build_semantic_cloud(seg, depth, cam, sensor_id="cam", stamp_ns=5, seq=0,
                                 frame_id="cam_optical", T_frame_sensor=None, config=config)
    assert len(cloud.points_xyz) == (H - 50) * (W - 50)
    assert np.all(cloud.class_ids == FLOOR)
    assert np.allclose(cloud.points_xyz[:, 2], 2.0)
    keep_all = SemanticCloudConfig(voxel_m=0.0, min_confidence=0.0, drop_classes=(),
                                   min_range_m=0.0, max_range_m=100.0, max_points=100_000)
    cloud = build_semantic_cloud(seg, depth, cam, sensor_id="cam", stamp_ns=5, seq=0,
                                 frame_id="cam_optical", T_frame_sensor=None, config=keep_all)
    assert len(cloud.points_xyz) == (H - 30) * (W - 10)  # only no-depth and NaN confidence


def test_voxel_downsampling_counts_means_majority_class_and_its_confidence() -> None:
    pts = np.array([
        [0.01, 0.01, 0.01], [0.02, 0.03, 0.04], [0.04, 0.04, 0.04],  # voxel (0, 0, 0)
        [0.06, 0.01, 0.01],                                          # voxel (1, 0, 0)
        [-0.01, 0.01, 0.01], [-0.02, 0.02, 0.02],                   # voxel (-1, 0, 0): a tie
    ])
    cls = np.array([WALL, FLOOR, WALL, TABLE, TABLE, WALL], np.uint8)
    conf = np.array([0.8, 0.3, 0.6, 0.7, 0.9, 0.5], np.float32)
    mean, majority, mconf, counts = voxel_downsample(pts, cls, conf, 0.05)
    assert len(mean) == 3 and sorted(counts.tolist()) == [1, 2, 3]
    by_count = {int(c): i for i, c in enumerate(counts)}
    i3, i1, i2 = by_count[3], by_count[1], by_count[2]
    assert np.allclose(mean[i3], pts[:3].mean(axis=0))
    assert majority[i3] == WALL and mconf[i3] == pytest.approx(0.7)  # mean of WALL's 0.8, 0.6
    assert majority[i1] == TABLE and mconf[i1] == pytest.approx(0.7)
    assert majority[i2] == min(WALL, TABLE) and majority.dtype == np.uint8  # tie: lower id
    # grid aligned with the frame: a point at -0.01 is not in the voxel of +0.01
    assert np.allclose(mean[i2], pts[4:].mean(axis=0))


def test_dense_surface_downsamples_to_one_point_per_voxel_and_caps() -> None:
    cam = _camera(dist=())
    depth = np.full((H, W), 2.0, np.float32)  # a wall 2 m ahead, ~1.9 x 2.5 m visible
    seg = _seg(H, W, WALL)
    full = build_semantic_cloud(seg, depth, cam, sensor_id="cam", stamp_ns=1, seq=0,
                                frame_id="c", T_frame_sensor=None,
                                config=SemanticCloudConfig(voxel_m=0.1, max_points=100_000))
    ext = np.ptp(full.points_xyz[:, :2], axis=0)
    cells = np.prod(np.ceil(ext / 0.1) + 1)
    assert 0.8 * np.prod(ext / 0.1) < len(full.points_xyz) <= cells
    assert len(full.points_xyz) < H * W / 50
    capped = build_semantic_cloud(seg, depth, cam, sensor_id="cam", stamp_ns=1, seq=0,
                                  frame_id="c", T_frame_sensor=None,
                                  config=SemanticCloudConfig(voxel_m=0.1, max_points=100))
    assert len(capped.points_xyz) == 100
    # the cap is an even subsample: it still spans the wall
    assert np.all(np.ptp(capped.points_xyz[:, :2], axis=0) > 0.8 * ext)


def test_points_are_transformed_into_the_frame_and_the_message_round_trips() -> None:
    """A camera 2.5 m up looking down at 30 deg sees the floor: with T_world_cam the points lie
    at world z = 0; the message carries frame, stamp, transform and survives the codec."""
    T_world_cam = np.eye(4)
    R_look = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical→base
    T_world_cam[:3, :3] = rotation_from_rpy(0.0, np.deg2rad(30.0), 0.3) @ R_look
    T_world_cam[:3, 3] = (4.0, 2.0, 2.5)
    cam = _camera(T_cam_world=invert_transform(T_world_cam))
    n_world = np.array([0.0, 0.0, 1.0])
    n_cam = T_world_cam[:3, :3].T @ n_world
    d_cam = -(T_world_cam[:3, 3] @ n_world)  # plane z = 0 in camera coordinates
    depth = _plane_depth(cam, n_cam, d_cam)
    depth[depth < 0] = np.inf  # above the horizon
    cloud = build_semantic_cloud(_seg(60, 80), depth, cam, sensor_id="cam1", stamp_ns=123,
                                 seq=7, frame_id="map", T_frame_sensor=T_world_cam,
                                 config=SemanticCloudConfig(max_range_m=8.0))
    assert len(cloud.points_xyz) > 500
    assert np.max(np.abs(cloud.points_xyz[:, 2])) < 2e-3
    assert cloud.frame_id == "map" and cloud.stamp_ns == 123 and cloud.seq == 7
    assert np.allclose(cloud.T_frame_sensor, T_world_cam)
    again = decode(encode(cloud))
    assert isinstance(again, SemanticCloud)
    assert np.array_equal(again.points_xyz, cloud.points_xyz)
    assert np.array_equal(again.class_ids, cloud.class_ids)


def test_maker_rate_seq_timing_and_robot_frame() -> None:
    cam = _camera(dist=())
    calls = []

    def segmenter(image: np.ndarray) -> Segmentation:
        calls.append(image.shape)
        return _seg(H // 2, W // 2, FLOOR)

    T_base_cam = np.eye(4)
    T_base_cam[:3, 3] = (0.1, 0.0, 1.0)
    maker = SemanticCloudMaker(segmenter, cam, sensor_id="hsr", frame_id=ROBOT_BASE_FRAME,
                               T_frame_sensor=T_base_cam, rate_hz=2.0)
    image = np.zeros((H, W, 3), np.uint8)
    depth = np.full((H, W), 1.5, np.float32)
    assert maker.due(0)
    cloud, timing = maker.make(image, depth, 0)
    assert not maker.due(400_000_000) and maker.due(500_000_000)
    cloud2, _ = maker.make(image, depth, 500_000_000)
    assert (cloud.seq, cloud2.seq) == (0, 1) and cloud.frame_id == "base_link"
    assert np.allclose(cloud.points_xyz[:, 2], 2.5, atol=1e-5)  # z_cam 1.5 + 1.0 up
    assert timing.segmentation_ms >= 0.0 and timing.cloud_ms > 0.0 and len(calls) == 2
    with pytest.raises(ValueError, match="rate"):
        SemanticCloudMaker(segmenter, cam, sensor_id="x", frame_id="map", T_frame_sensor=None,
                           rate_hz=0.0)


@pytest.mark.parametrize(("change", "field"), [
    ({"voxel_m": -0.1}, "voxel_m"),
    ({"voxel_m": float("nan")}, "voxel_m"),
    ({"min_confidence": 1.5}, "min_confidence"),
    ({"min_range_m": -1.0}, "min_range_m"),
    ({"max_range_m": 0.2}, "max_range_m"),
    ({"max_points": 0}, "max_points"),
    ({"max_points": 10**7}, "max_points"),
    ({"max_points": 1.5}, "max_points"),
    ({"drop_classes": ("persn",)}, "drop_classes"),
])
def test_config_errors_name_the_field(change: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SemanticCloudConfig(**change)


def test_config_accepts_a_single_class_name() -> None:
    assert SemanticCloudConfig(drop_classes="person").drop_classes == ("person",)  # type: ignore[arg-type]


@pytest.mark.parametrize(("seg", "depth", "field"), [
    (Segmentation(np.zeros((10, 10), np.int32), np.zeros((10, 10), np.float32), W, H, 0.0),
     np.ones((H, W), np.float32), "class_ids"),
    (Segmentation(np.zeros((10,), np.uint8), np.zeros((10,), np.float32), W, H, 0.0),
     np.ones((H, W), np.float32), "class_ids"),
    (Segmentation(np.zeros((10, 10), np.uint8), np.zeros((10, 11), np.float32), W, H, 0.0),
     np.ones((H, W), np.float32), "confidence"),
    (Segmentation(np.zeros((10, 10), np.uint8), np.zeros((10, 10), np.uint8), W, H, 0.0),
     np.ones((H, W), np.float32), "confidence"),
    (Segmentation(np.zeros((10, 10), np.uint8), np.zeros((10, 10), np.float32), 640, 480, 0.0),
     np.ones((H, W), np.float32), "image_width"),
    (Segmentation(np.zeros((10, 10), np.uint8), np.zeros((10, 10), np.float32), W, H, 0.0),
     np.ones((H, W + 1), np.float32), "depth_m"),
    (Segmentation(np.zeros((10, 10), np.uint8), np.zeros((10, 10), np.float32), W, H, 0.0),
     np.ones((H, W), np.uint16), "depth_m"),
])
def test_wrong_inputs_raise_value_errors_naming_the_field(seg, depth, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        build_semantic_cloud(seg, depth, _camera(), sensor_id="c", stamp_ns=0, seq=0,
                             frame_id="map", T_frame_sensor=np.eye(4))
    with pytest.raises(ValueError, match="T_frame_sensor"):
        build_semantic_cloud(_seg(10, 10), np.ones((H, W), np.float32), _camera(),
                             sensor_id="c", stamp_ns=0, seq=0, frame_id="map",
                             T_frame_sensor=np.eye(3))
