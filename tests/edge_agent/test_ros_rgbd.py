"""ROS depth images and RGB-D pairs into the edge agent (issue #28, item 1: depth + pairs).

Messages are made with rosbags (an independent CDR encoder); the edge agent decodes them itself.
Checked:

* ``16UC1`` (millimetres) and ``32FC1`` (metres) depth decode exactly to float32 metres with
  NaN where there is no depth, in both byte orders and with row padding; a wrong step, a step
  that is not whole pixels, a truncated message at every cut and a colour encoding on the depth
  topic are named errors with their counters;
* over real Zenoh on loopback, colour + depth published the rmw_zenoh way pair by header
  stamp (exact and within the tolerance), pairs that cannot match are counted
  ``rgbd_unmatched``, a depth image of another size ``depth_size_mismatch`` (the colour frame
  still counts), and the source keeps going;
* the edge agent with ``--ros-depth-topic`` turns a rendered cam2 frame and its rendered depth
  (16UC1) into a semantic cloud in the world frame whose points lie on the rendered surfaces;
* decode + convert time of an 848x480 16UC1 depth image, printed.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
cv2 = pytest.importorskip("cv2")
rosbags_typesys = pytest.importorskip("rosbags.typesys")

from core.site import load_site  # noqa: E402
from edge_agent import ros_source as rs  # noqa: E402
from protocol import keys  # noqa: E402
from protocol.messages import SemanticCloud  # noqa: E402
from tests.conftest import REPO_ROOT  # noqa: E402

SITE_PATH = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
CAMERA = "cam2"
W, H = 848, 480
COLOUR_TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"
STAMP0_NS = 1_700_000_000_000_000_000


def _store() -> Any:
    return rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_HUMBLE)


def _header(stamp_ns: int, frame_id: str) -> Any:
    ts = _store()
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return ts.types["std_msgs/msg/Header"](ts.types["builtin_interfaces/msg/Time"](sec, nsec),
                                           frame_id)


def raw_image_cdr(data: np.ndarray, width: int, height: int, encoding: str, step: int,
                  stamp_ns: int = STAMP0_NS, bigendian: bool = False,
                  frame_id: str = "camera_color_optical_frame") -> bytes:
    """``sensor_msgs/Image`` CDR with these exact fields and ``data`` bytes."""
    ts = _store()
    msg = ts.types["sensor_msgs/msg/Image"](_header(stamp_ns, frame_id), height, width,
                                            encoding, int(bigendian), step,
                                            np.frombuffer(data.tobytes(), np.uint8))
    return bytes(ts.serialize_cdr(msg, rs.IMAGE_TYPE))


def depth_cdr(depth: np.ndarray, encoding: str, stamp_ns: int = STAMP0_NS,
              bigendian: bool = False, pad: int = 0) -> bytes:
    """A depth image of ``depth`` (uint16 mm for 16UC1, float32 m for 32FC1) with ``pad``
    bytes at the end of each row."""
    h, w = depth.shape
    dtype = np.dtype((">" if bigendian else "<") + ("u2" if encoding == "16UC1" else "f4"))
    rows = depth.astype(dtype).view(np.uint8).reshape(h, -1)
    data = np.zeros((h, rows.shape[1] + pad), np.uint8)
    data[:, :rows.shape[1]] = rows
    return raw_image_cdr(data, w, h, encoding, data.shape[1], stamp_ns, bigendian)


def colour_cdr(rgb: np.ndarray, stamp_ns: int) -> bytes:
    h, w = rgb.shape[:2]
    return raw_image_cdr(np.ascontiguousarray(rgb), w, h, "rgb8", w * 3, stamp_ns)


# --------------------------------------------------------------------------------------------
# decoding
# --------------------------------------------------------------------------------------------


def test_16uc1_and_32fc1_decode_exactly_in_both_byte_orders() -> None:
    """Millimetres to metres (0: NaN) and metres as they are (NaN, inf, 0, negative: NaN),
    little and big endian, rows padded by 6 bytes: exactly the values published."""
    rng = np.random.default_rng(3)
    mm = rng.integers(0, 65535, size=(7, 11), dtype=np.uint16)
    mm[0, :3] = 0
    want_mm = mm.astype(np.float32) / np.float32(1000.0)
    want_mm[mm == 0] = np.nan
    metres = rng.uniform(0.2, 9.0, size=(7, 11)).astype(np.float32)
    metres[1, :4] = [np.nan, np.inf, 0.0, -1.5]
    want_m = metres.copy()
    want_m[1, :4] = np.nan
    for big in (False, True):
        for pad in (0, 6):
            msg = rs.decode_depth_image(depth_cdr(mm, "16UC1", bigendian=big, pad=pad))
            assert (msg.width, msg.height, msg.encoding, msg.is_bigendian) == (11, 7, "16UC1",
                                                                               big)
            out = rs.depth_to_m(msg)
            assert out.dtype == np.float32 and out.shape == (7, 11)
            np.testing.assert_array_equal(out, want_mm)
            assert np.isnan(out[0, :3]).all()
            out = rs.depth_to_m(rs.decode_depth_image(depth_cdr(metres, "32FC1", bigendian=big,
                                                                pad=pad)))
            np.testing.assert_array_equal(out, want_m)
    # the flag is what tells the byte order: the same bytes with the flag cleared differ
    msg = rs.decode_depth_image(depth_cdr(mm, "16UC1", bigendian=True))
    swapped = rs.depth_to_m(rs.RosImage(msg.stamp_ns, msg.frame_id, msg.height, msg.width,
                                        msg.encoding, False, msg.step, msg.data))
    assert not np.array_equal(swapped, want_mm, equal_nan=True)


def test_bad_depth_messages_are_named_errors() -> None:
    """Step shorter than a row: ros_bad_size (odd padding is handled); every cut: a
    RosImageError;
    a colour encoding on the depth topic and a depth encoding on the colour topic:
    ros_bad_encoding naming it."""
    mm = np.full((4, 6), 1234, np.uint16)
    with pytest.raises(rs.RosImageError, match="step 10 < width 6") as err:
        rs.decode_depth_image(raw_image_cdr(np.zeros(40, np.uint8), 6, 4, "16UC1", 10))
    assert err.value.counter == "ros_bad_size"
    # a step that is not whole pixels (25 bytes for 6 float32) is handled, not refused
    rows = np.zeros((4, 25), np.uint8)
    rows[:, :24] = np.full((4, 6), 2.5, "<f4").view(np.uint8)
    out = rs.depth_to_m(rs.decode_depth_image(raw_image_cdr(rows, 6, 4, "32FC1", 25)))
    np.testing.assert_array_equal(out, np.full((4, 6), np.float32(2.5)))
    payload = depth_cdr(mm, "16UC1")
    for cut in range(len(payload) - 1):
        with pytest.raises(rs.RosImageError) as err:
            rs.decode_depth_image(payload[:cut])
        assert err.value.counter in ("ros_truncated", "ros_not_cdr", "ros_bad_field"), cut
    with pytest.raises(rs.RosImageError, match="'rgb8' is not a depth encoding") as err:
        rs.decode_depth_image(colour_cdr(np.zeros((4, 6, 3), np.uint8), STAMP0_NS))
    assert err.value.counter == "ros_bad_encoding"
    with pytest.raises(rs.RosImageError, match="depth image") as err:
        rs.decode_image(payload)
    assert err.value.counter == "ros_bad_encoding"
    stamp, frame_id = rs.decode_header(payload)
    assert (stamp, frame_id) == (STAMP0_NS, "camera_color_optical_frame")


def test_depth_decode_time_at_848x480() -> None:
    """Decode + convert one 848x480 16UC1 depth image (median of 30), printed; asserted with
    room for a loaded test machine."""
    rng = np.random.default_rng(0)
    mm = rng.integers(0, 8000, size=(H, W), dtype=np.uint16)
    payload = depth_cdr(mm, "16UC1")
    source = rs.RosImageSource(rs.RosTopicConfig("ros2dds", COLOUR_TOPIC,
                                                 depth_topic=DEPTH_TOPIC), None, None)
    samples = []
    for _ in range(30):
        t0 = time.perf_counter()
        out, stamp = source.decode_depth(payload)
        samples.append(time.perf_counter() - t0)
    assert out.shape == (H, W) and stamp == STAMP0_NS
    ms = float(np.median(samples)) * 1e3
    print(f"16UC1 depth decode + convert at {W}x{H}: {ms:.3f} ms per frame (median of 30)")
    assert ms < 15.0


# --------------------------------------------------------------------------------------------
# RGB-D pairs over Zenoh
# --------------------------------------------------------------------------------------------


class _Pub:
    """A ROS 2 publisher the rmw_zenoh way (key with type hash, attachment)."""

    def __init__(self, session: Any, topic: str) -> None:
        from robot_bridge.adapters.rmw_zenoh_wire import topic_key

        self.pub = session.declare_publisher(topic_key(0, topic, rs.IMAGE_TYPE))
        self.seq = 0
        self.gid = bytes(range(16)) if "depth" in topic else bytes(range(1, 17))

    def put(self, payload: bytes) -> None:
        from robot_bridge.adapters.rmw_zenoh_wire import encode_attachment

        self.seq += 1
        self.pub.put(payload, attachment=encode_attachment(self.seq, time.time_ns(), self.gid))

    def close(self) -> None:
        self.pub.undeclare()


def _wait(predicate: Any, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_rgbd_pairs_sync_by_stamp_and_unmatched_are_counted(zenoh_pair: Any) -> None:
    """Pairs of one stamp and of stamps 3 ms apart come out as frames with depth; a colour
    whose depth is 20 ms off and that depth are both counted unmatched once newer messages
    show they cannot pair; a depth of another size is counted and the colour frame still
    comes out, without depth; the status names the counts."""
    a, b, _ = zenoh_pair
    config = rs.RosTopicConfig("rmw_zenoh", COLOUR_TOPIC, depth_topic=DEPTH_TOPIC)
    source = rs.RosImageSource(config, None, None)
    source.attach(b)
    colour, depth = _Pub(a, COLOUR_TOPIC), _Pub(a, DEPTH_TOPIC)
    rgb = np.zeros((48, 64, 3), np.uint8)
    rgb[..., 1] = 200
    mm = np.full((48, 64), 1500, np.uint16)
    time.sleep(0.3)  # subscriptions known to the publisher's session

    def take_one(timeout_s: float = 10.0) -> rs.RosFrame:
        deadline = time.monotonic() + timeout_s
        while (got := source.take_frame()) is None:
            assert time.monotonic() < deadline, (source.error_counts(), source.health())
            time.sleep(0.01)
        return got

    try:
        t0 = STAMP0_NS
        colour.put(colour_cdr(rgb, t0))
        depth.put(depth_cdr(mm, "16UC1", t0))
        frame = take_one().frame
        assert frame.stamp_ns == t0 and frame.depth_m is not None
        np.testing.assert_array_equal(frame.depth_m, np.full((48, 64), np.float32(1.5)))

        t1 = t0 + 100_000_000  # depth 3 ms after colour, depth first on the wire
        depth.put(depth_cdr(mm, "16UC1", t1 + 3_000_000))
        colour.put(colour_cdr(rgb, t1))
        frame = take_one().frame
        assert frame.stamp_ns == t1 and frame.depth_m is not None

        t2 = t1 + 100_000_000  # 20 ms apart: no pair; then a good pair 100 ms later
        colour.put(colour_cdr(rgb, t2))
        depth.put(depth_cdr(mm, "16UC1", t2 + 20_000_000))
        time.sleep(0.2)
        assert source.take_frame() is None
        t3 = t2 + 100_000_000
        colour.put(colour_cdr(rgb, t3))
        depth.put(depth_cdr(mm, "16UC1", t3))
        frame = take_one().frame
        assert frame.stamp_ns == t3
        assert source.error_counts().get("rgbd_unmatched") == 2, source.error_counts()

        t4 = t3 + 100_000_000  # depth of half the size
        colour.put(colour_cdr(rgb, t4))
        depth.put(depth_cdr(mm[::2, ::2], "16UC1", t4))
        got = take_one()
        assert got.frame.stamp_ns == t4 and got.frame.depth_m is None
        assert got.frame_id == "camera_color_optical_frame"
        counts = source.error_counts()
        assert counts.get("depth_size_mismatch") == 1 and counts.get("rgbd_unmatched") == 2
        state, detail = source.health()
        assert state == "degraded" and "depth image 32x24" in detail and \
            "rgbd_unmatched=2" in detail, detail

        # a burst of colour without depth: bounded, all counted once depth moves on
        for i in range(10):
            colour.put(colour_cdr(rgb, t4 + (i + 1) * 33_000_000))
            time.sleep(0.05)
            assert source.take_frame() is None
        assert len(source._colour_pending) <= rs.RGBD_QUEUE
        t5 = t4 + 2_000_000_000
        colour.put(colour_cdr(rgb, t5))
        depth.put(depth_cdr(mm, "16UC1", t5))
        assert take_one().frame.stamp_ns == t5
        counts = source.error_counts()
        unmatched = counts.get("rgbd_unmatched", 0)
        assert unmatched == 2 + 10, counts  # the ten lone colour images
        assert "ros_messages_lost" not in counts, counts
    finally:
        colour.close()
        depth.close()
        source.close()


# --------------------------------------------------------------------------------------------
# the edge agent's semantic clouds from a ROS RGB-D pair
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rendered_rgbd() -> tuple[np.ndarray, np.ndarray]:
    """A rendered 848x480 view of cam2 and its rendered depth (inf: nothing)."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=5)
    for i in range(50):
        s = gen(i)
        if s.camera.camera_id == CAMERA:
            return s.image_rgb.copy(), np.asarray(s.depth_m, np.float32).copy()
    pytest.fail("no view of cam2 in the first 50 samples")


def test_edge_agent_makes_a_world_cloud_from_a_ros_rgbd_pair(
        zenoh_pair: Any, rendered_rgbd: tuple[np.ndarray, np.ndarray]) -> None:
    """``--source ros --ros-depth-topic``: a rendered cam2 frame with its rendered depth as
    16UC1 becomes a SemanticCloud in the world frame (T_frame_sensor = the calibrated
    T_world_cam) whose points, projected back into cam2, lie on the rendered depth."""
    from edge_agent.service import build_node, build_parser

    a, b, _ = zenoh_pair
    rgb, depth_m = rendered_rgbd
    mm = np.where(np.isfinite(depth_m), np.round(depth_m * 1000.0), 0).astype(np.uint16)
    args = build_parser().parse_args([
        "--site", str(SITE_PATH), "--camera", CAMERA, "--source", "ros", "--threads", "1",
        "--ros-image-topic", COLOUR_TOPIC, "--ros-camera-info-topic", "none",
        "--ros-depth-topic", DEPTH_TOPIC, "--ros-domain-id", "0"])
    node = build_node(args)
    assert isinstance(node.source, rs.RosImageSource)
    assert node.source.provides_depth and node.clouds is not None
    node.attach(b)
    colour, depth = _Pub(a, COLOUR_TOPIC), _Pub(a, DEPTH_TOPIC)
    time.sleep(0.3)
    clouds: list[Any] = []
    try:
        deadline = time.monotonic() + 60.0
        next_put = 0.0
        while not clouds:
            assert time.monotonic() < deadline, (node.stats.snapshot_counters(), node.state())
            if time.monotonic() >= next_put:
                colour.put(colour_cdr(rgb, STAMP0_NS))
                depth.put(depth_cdr(mm, "16UC1", STAMP0_NS))
                next_put = time.monotonic() + 2.0
            time.sleep(0.02)
            for item in node.tick(time.time_ns()):
                if item.key == keys.edge_cloud_key("paper_lab", CAMERA):
                    assert item.reliable
                    clouds.append(item.message)
    finally:
        colour.close()
        depth.close()
        node.close()
    cloud: SemanticCloud = clouds[0]
    assert cloud.T_frame_sensor is not None
    cam = load_site(SITE_PATH).camera(CAMERA)
    assert cloud.frame_id == load_site(SITE_PATH).world_frame and cloud.stamp_ns == STAMP0_NS
    np.testing.assert_allclose(cloud.T_frame_sensor, cam.T_world_cam, atol=1e-12)
    assert len(cloud.points_xyz) > 200
    p = cloud.points_xyz.astype(np.float64) @ cam.T_cam_world[:3, :3].T + cam.T_cam_world[:3, 3]
    uv, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    uv = np.round(uv.reshape(-1, 2)).astype(int)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    assert inside.mean() > 0.99
    err = np.abs(depth_m[uv[inside, 1], uv[inside, 0]] - p[inside, 2])
    print(f"edge cloud from a ROS RGB-D pair: {len(p)} points, |z - rendered depth| median "
          f"{np.median(err) * 100:.2f} cm, 90th percentile {np.quantile(err, 0.9) * 100:.2f} cm")
    # voxel means (5 cm voxels) sit on the surfaces except at depth edges
    assert np.median(err) < 0.02 and np.quantile(err, 0.9) < 0.10
