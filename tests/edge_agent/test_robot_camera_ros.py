"""The real robot's head camera node (``smartedge robot-camera --source ros``, issue #28 item 2).

Everything goes over real Zenoh on loopback, messages serialized with rosbags (an independent
CDR encoder). Checked:

* ``tf2_msgs/msg/TFMessage`` decodes (both byte orders) to the transforms rosbags wrote; every
  cut and a hostile count are named errors; the /tf and /tf_static keys are the robot bridge's;
* the node, with the HSR's default topics: ``/tf_static`` published by a Zenoh
  AdvancedPublisher with a cache BEFORE the node starts (as rmw_zenoh's transient-local
  publishers do) still reaches it; a chain base_link -> head_pan_link -> head_tilt_link ->
  camera optical frame whose pan and tilt joints move between two /tf messages, with the image
  stamp between them: the node waits for the second message, and the cloud's
  ``T_frame_sensor`` matches the interpolated truth (built here from angles, not from the TF
  buffer) within 1 mm / 0.05 deg; the points of a known depth plane land on that plane in
  ``base_link``;
* an unknown camera frame, a stale joint and a stamp before the TF history give
  ``tf_missing``, ``tf_stale`` and ``tf_extrapolation``, named in the status; a garbage /tf
  message and a transform with a NaN are counted; the node goes on making clouds;
* ``smartedge robot-camera --source ros`` is this node; ``--source sim`` stays the simulation.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
import pytest

pytest.importorskip("onnxruntime")
zenoh = pytest.importorskip("zenoh")
pytest.importorskip("rosbags.typesys")

from core.session import loopback_config  # noqa: E402
from core.site import load_site  # noqa: E402
from edge_agent import ros_source as rs  # noqa: E402
from edge_agent import ros_tf  # noqa: E402
from edge_agent.robot_camera import (  # noqa: E402
    HSR_CAMERA_INFO_TOPIC,
    HSR_DEPTH_TOPIC,
    HSR_RGB_TOPIC,
    RosRobotCameraNode,
    build_node,
    build_parser,
)
from protocol import keys  # noqa: E402
from protocol.messages import SemanticCloud  # noqa: E402
from tests.conftest import REPO_ROOT, free_port  # noqa: E402

SITE_PATH = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
ROBOT = "hsr"
OPTICAL = "head_rgbd_sensor_rgb_frame"
T0_NS = 1_700_000_000_000_000_000
PLANE_M = 1.5


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------


def _store() -> Any:
    from robot_bridge.adapters.ros2 import typestore

    return typestore()


def _header(stamp_ns: int, frame_id: str) -> Any:
    t = _store().types
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return t["std_msgs/msg/Header"](t["builtin_interfaces/msg/Time"](sec, nsec), frame_id)


def tf_cdr(transforms: Sequence[tuple[str, str, int, tuple[float, ...], tuple[float, ...]]],
           little_endian: bool = True) -> bytes:
    """TFMessage of (parent, child, stamp_ns, translation, q_xyzw) items."""
    ts = _store()
    t = ts.types
    items = [t["geometry_msgs/msg/TransformStamped"](
        _header(stamp, parent), child,
        t["geometry_msgs/msg/Transform"](t["geometry_msgs/msg/Vector3"](*xyz),
                                         t["geometry_msgs/msg/Quaternion"](*q)))
        for parent, child, stamp, xyz, q in transforms]
    return bytes(ts.serialize_cdr(t[ros_tf.TF_MESSAGE_TYPE](items), ros_tf.TF_MESSAGE_TYPE,
                                  little_endian=little_endian))


def image_cdr(data: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> bytes:
    ts = _store()
    h, w = data.shape[:2]
    raw = np.ascontiguousarray(data).view(np.uint8).reshape(h, -1)
    msg = ts.types["sensor_msgs/msg/Image"](_header(stamp_ns, frame_id), h, w, encoding, 0,
                                            raw.shape[1], raw.reshape(-1))
    return bytes(ts.serialize_cdr(msg, rs.IMAGE_TYPE))


def camera_info_cdr(camera: Any, stamp_ns: int) -> bytes:
    ts = _store()
    P = np.zeros((3, 4))
    P[:, :3] = camera.K
    msg = ts.types["sensor_msgs/msg/CameraInfo"](
        _header(stamp_ns, OPTICAL), camera.height, camera.width, "plumb_bob",
        np.asarray(camera.dist, np.float64), np.asarray(camera.K, np.float64).reshape(-1),
        np.eye(3).reshape(-1), P.reshape(-1), 0, 0,
        ts.types["sensor_msgs/msg/RegionOfInterest"](0, 0, 0, 0, False))
    return bytes(ts.serialize_cdr(msg, rs.CAMERA_INFO_TYPE))


# --------------------------------------------------------------------------------------------
# the head's kinematics, written out independently of the TF buffer
# --------------------------------------------------------------------------------------------


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def quat_to_matrix(q: tuple[float, ...]) -> np.ndarray:
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rigid(R: np.ndarray, t: tuple[float, ...]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


#: optical frame in the tilt link: z forward (link x), x right (-link y), y down (-link z)
R_TILT_OPT = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
Q_TILT_OPT = (-0.5, 0.5, -0.5, 0.5)
T_TILT_OPT = (0.05, 0.02, 0.1)
PAN_XYZ = {0: (0.0, 0.0, 0.75), 1: (0.0, 0.0, 0.80)}  # the torso lifts a little too
TILT_XYZ = (0.02, 0.0, 0.2)


def head_tf(stamp_ns: int, pan: float, tilt: float, lift: float) -> bytes:
    """/tf of the two joints: pan (about z) with the torso at ``lift`` in [0, 1], tilt (about
    y)."""
    z = PAN_XYZ[0][2] + lift * (PAN_XYZ[1][2] - PAN_XYZ[0][2])
    return tf_cdr([
        ("base_link", "head_pan_link", stamp_ns, (0.0, 0.0, z),
         (0.0, 0.0, math.sin(pan / 2), math.cos(pan / 2))),
        ("head_pan_link", "head_tilt_link", stamp_ns, TILT_XYZ,
         (0.0, math.sin(tilt / 2), 0.0, math.cos(tilt / 2)))])


def static_tf() -> bytes:
    return tf_cdr([("head_tilt_link", OPTICAL, 0, T_TILT_OPT, Q_TILT_OPT)])


def truth_T_base_cam(pan: float, tilt: float, lift: float) -> np.ndarray:
    z = PAN_XYZ[0][2] + lift * (PAN_XYZ[1][2] - PAN_XYZ[0][2])
    return rigid(rot_z(pan), (0.0, 0.0, z)) @ rigid(rot_y(tilt), TILT_XYZ) @ \
        rigid(R_TILT_OPT, T_TILT_OPT)


# --------------------------------------------------------------------------------------------
# decoding and keys
# --------------------------------------------------------------------------------------------


def test_tf_message_decodes_like_rosbags_and_bad_ones_are_named() -> None:
    """Two transforms in both byte orders read back exactly (frame ids, stamps, values); every
    cut raises RosTfError with a tf_ counter; a count of 10^6 transforms in a short message is
    refused before reading; the keys match the robot bridge's spelling."""
    items = [("base_link", "head_pan_link", T0_NS + 5, (0.1, -0.2, 0.75), (0.0, 0.0, 0.6, 0.8)),
             ("/head_pan_link", "head_tilt_link", T0_NS + 7, (0.02, 0.0, 0.2),
              (0.0, 0.28, 0.0, 0.96))]
    for little in (True, False):
        out = ros_tf.decode_tf_message(tf_cdr(items, little))
        assert [(r.parent, r.child, r.stamp_ns, r.translation_m, r.q_xyzw) for r in out] == \
            items
    payload = tf_cdr(items)
    for cut in range(len(payload) - 1):
        with pytest.raises(ros_tf.RosTfError) as err:
            ros_tf.decode_tf_message(payload[:cut])
        assert err.value.counter.startswith("tf_"), (cut, err.value.counter)
    hostile = bytearray(payload)
    hostile[4:8] = (1_000_000).to_bytes(4, "little")
    with pytest.raises(ros_tf.RosTfError, match="1000000 transforms") as err:
        ros_tf.decode_tf_message(bytes(hostile))
    assert err.value.counter == "tf_too_many"
    hostile[4:8] = (4000).to_bytes(4, "little")
    with pytest.raises(ros_tf.RosTfError, match="cannot fit") as err:
        ros_tf.decode_tf_message(bytes(hostile))
    assert err.value.counter == "tf_truncated"
    assert ros_tf.decode_tf_message(tf_cdr([])) == []

    from robot_bridge.adapters.rmw_zenoh_wire import topic_key
    from robot_bridge.adapters.ros2 import ros2dds_key

    listener = ros_tf.TfListener("rmw_zenoh", domain_id=4)
    for ours, topic in ((listener.tf_key, "/tf"), (listener.static_key, "/tf_static")):
        assert zenoh.KeyExpr(ours).intersects(zenoh.KeyExpr(
            topic_key(4, topic, ros_tf.TF_MESSAGE_TYPE)))
    listener = ros_tf.TfListener("ros2dds", namespace="/robot1")
    assert (listener.tf_key, listener.static_key) == (ros2dds_key("/tf", "/robot1"),
                                                      ros2dds_key("/tf_static", "/robot1"))


# --------------------------------------------------------------------------------------------
# the node over Zenoh
# --------------------------------------------------------------------------------------------


@pytest.fixture
def sessions() -> Iterator[tuple[Any, Any]]:
    """(robot, node) Zenoh sessions on loopback; the robot's has timestamping on, as
    rmw_zenoh's configuration has (an AdvancedPublisher with a cache needs it)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = loopback_config(listen=[endpoint])
    config.insert_json5("timestamping", '{"enabled": true}')
    robot = zenoh.open(config)
    node = zenoh.open(loopback_config(connect=[endpoint]))
    try:
        yield robot, node
    finally:
        node.close()
        robot.close()


@pytest.fixture(scope="module")
def head_view() -> np.ndarray:
    """A rendered 640x480 view of the robot's own head camera (robot mode)."""
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    sample = SampleGenerator(load_scenario(), "robot", seed=2)(0)
    assert sample.image_rgb.shape == (480, 640, 3)
    return sample.image_rgb.copy()


class _Robot:
    """The robot's publishers the rmw_zenoh way: colour, depth, camera info and /tf as plain
    publishers with rmw_zenoh's attachment, /tf_static as an AdvancedPublisher with a cache of
    1 and publisher detection (rmw_zenoh's transient-local publisher)."""

    def __init__(self, session: Any) -> None:
        import zenoh.ext as zext

        from robot_bridge.adapters.rmw_zenoh_wire import topic_key

        self.pubs = {
            "rgb": session.declare_publisher(topic_key(0, HSR_RGB_TOPIC, rs.IMAGE_TYPE)),
            "depth": session.declare_publisher(topic_key(0, HSR_DEPTH_TOPIC, rs.IMAGE_TYPE)),
            "info": session.declare_publisher(topic_key(0, HSR_CAMERA_INFO_TOPIC,
                                                        rs.CAMERA_INFO_TYPE)),
            "tf": session.declare_publisher(topic_key(0, "/tf", ros_tf.TF_MESSAGE_TYPE)),
        }
        self.static = zext.declare_advanced_publisher(
            session, topic_key(0, "/tf_static", ros_tf.TF_MESSAGE_TYPE),
            cache=zext.CacheConfig(max_samples=1), publisher_detection=True)
        self.seq = dict.fromkeys(self.pubs, 0)

    def put(self, name: str, payload: bytes) -> None:
        from robot_bridge.adapters.rmw_zenoh_wire import encode_attachment

        self.seq[name] += 1
        gid = bytes([len(name)] * 16)
        self.pubs[name].put(payload, attachment=encode_attachment(self.seq[name],
                                                                  time.time_ns(), gid))

    def frame(self, rgb: np.ndarray, stamp_ns: int, frame_id: str = OPTICAL) -> None:
        depth = np.full(rgb.shape[:2], int(PLANE_M * 1000), np.uint16)
        self.put("rgb", image_cdr(rgb, "rgb8", stamp_ns, frame_id))
        self.put("depth", image_cdr(depth, "16UC1", stamp_ns, frame_id))

    def close(self) -> None:
        for pub in self.pubs.values():
            pub.undeclare()
        self.static.undeclare()


def _tick_for(node: RosRobotCameraNode, seconds: float) -> list[Any]:
    out: list[Any] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        out += [o.message for o in node.tick(time.time_ns())
                if o.key == keys.robot_cloud_key("paper_lab", ROBOT)]
        time.sleep(0.01)
    return out


def _tick_until(node: RosRobotCameraNode, predicate: Any, timeout_s: float = 30.0
                ) -> list[Any]:
    out: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while not predicate(out):
        assert time.monotonic() < deadline, (node.counters(), node.state())
        for item in node.tick(time.time_ns()):
            if item.key == keys.robot_cloud_key("paper_lab", ROBOT):
                assert item.reliable
                out.append(item.message)
        time.sleep(0.01)
    return out


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0))))


def test_head_camera_clouds_follow_the_panning_head(sessions: tuple[Any, Any],
                                                    head_view: np.ndarray) -> None:
    """The whole node on the HSR's default topics (see the module docstring)."""
    robot_session, node_session = sessions
    np.testing.assert_allclose(quat_to_matrix(Q_TILT_OPT), R_TILT_OPT, atol=1e-12)
    site = load_site(SITE_PATH)
    head = site.robot_model(ROBOT).head_camera
    assert head is not None and (head.width, head.height) == (640, 480)
    head_cam = head.camera_model(f"{ROBOT}_head")
    robot = _Robot(robot_session)
    robot.static.put(static_tf())  # before the node exists: only the cache can deliver it
    time.sleep(0.2)
    args = build_parser().parse_args([
        "--source", "ros", "--site", str(SITE_PATH), "--ros-domain-id", "0", "--threads", "1",
        "--tf-wait-s", "5"])
    node = build_node(args)
    assert node.clouds is not None, node.state()
    node.attach(node_session)
    try:
        time.sleep(0.5)
        robot.put("info", camera_info_cdr(head_cam, T0_NS))
        _tick_until(node, lambda _: node.source.latest_info is not None, 10.0)
        assert node.tf.static_history
        assert node.tf_buffer.is_static(OPTICAL), node.tf_buffer.detail()

        # the head pans 0 -> 0.2 rad and tilts -0.1 -> -0.3 rad over 100 ms; the image is
        # stamped 40 ms in; TF for the end of the move comes after the image
        ta, tb = T0_NS, T0_NS + 100_000_000
        t_img = ta + 40_000_000
        robot.put("tf", head_tf(ta, 0.0, -0.1, 0.0))
        robot.frame(head_view, t_img)
        # until the frame has arrived and waits for TF (a loaded machine may take a while)
        early = _tick_until(node, lambda out: bool(out) or node._waiting is not None, 10.0)
        assert early == [], "a cloud before TF covered the image stamp"
        early = _tick_for(node, 0.3)  # and it keeps waiting
        assert early == [], "a cloud before TF covered the image stamp"
        assert node._waiting is not None and node._waiting.got.frame.stamp_ns == t_img
        robot.put("tf", head_tf(tb, 0.2, -0.3, 1.0))
        cloud: SemanticCloud = _tick_until(node, bool)[0]
        truth = truth_T_base_cam(0.08, -0.18, 0.4)
        T = np.asarray(cloud.T_frame_sensor)
        dt_mm = float(np.linalg.norm(T[:3, 3] - truth[:3, 3])) * 1e3
        dr_deg = _angle_deg(T[:3, :3].T @ truth[:3, :3])
        print(f"T_base_cam vs interpolated truth: {dt_mm:.4f} mm, {dr_deg:.5f} deg")
        assert dt_mm < 1.0 and dr_deg < 0.05
        assert (cloud.frame_id, cloud.sensor_id, cloud.stamp_ns) == ("base_link", ROBOT, t_img)
        # the depth plane z = 1.5 m of the optical frame, seen from base_link
        p = cloud.points_xyz.astype(np.float64)
        assert len(p) > 100
        p_cam = (p - truth[:3, 3]) @ truth[:3, :3]
        print(f"{len(p)} points, |z_cam - {PLANE_M}| max "
              f"{np.abs(p_cam[:, 2] - PLANE_M).max() * 1e3:.3f} mm")
        assert np.abs(p_cam[:, 2] - PLANE_M).max() < 1e-3
        # and they fill the camera's view of the plane (its corners at 1.5 m)
        half_w = PLANE_M * 320 / head_cam.K[0, 0]
        assert p_cam[:, 0].min() < -0.5 * half_w and p_cam[:, 0].max() > 0.5 * half_w
        counters = node.counters()
        assert counters["clouds_published"] == 1 and counters["tf_static_messages"] >= 1
        assert node.state()[0] == "ok", node.state()

        # failures: each skipped, counted, named; the node goes on
        node.tf_wait_ns = 200_000_000
        robot.frame(head_view, tb + 1_200_000_000, frame_id="hand_camera_frame")
        _tick_until(node, lambda _: node.counters().get("tf_missing", 0) >= 1, 10.0)
        state, detail = node.state()
        assert state == "degraded" and "hand_camera_frame" in detail and \
            "tf_missing" in detail, detail
        robot.frame(head_view, tb + 2_500_000_000)
        _tick_until(node, lambda _: node.counters().get("tf_stale", 0) >= 1, 10.0)
        assert "stale" in node.state()[1] and "tf_stale" in node.state()[1], node.state()
        robot.frame(head_view, ta - 1_000_000_000)
        _tick_until(node, lambda _: node.counters().get("tf_extrapolation", 0) >= 1, 10.0)
        assert "tf_extrapolation" in node.state()[1], node.state()
        counters = node.counters()
        assert (counters["tf_missing"], counters["tf_stale"], counters["tf_extrapolation"],
                counters["clouds_published"]) == (1, 1, 1, 1), counters

        # garbage on /tf and a transform with a NaN: counted, nothing else happens
        robot.put("tf", b"\x00\x01\x00\x00\x05\x00\x00\x00garbage")
        robot.put("tf", tf_cdr([("base_link", "head_pan_link", tb + 10,
                                 (float("nan"), 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))]))
        _tick_until(node, lambda _: node.counters().get("tf_refused_invalid", 0) >= 1 and
                    node.counters().get("tf_truncated", 0) >= 1, 10.0)

        # the head moves on; a new frame between two new messages gives a new cloud
        tc, td = ta + 5_000_000_000, ta + 5_100_000_000
        seen_tf = node.counters().get("tf_messages", 0)
        robot.put("tf", head_tf(tc, -0.4, 0.1, 0.0))
        robot.put("tf", head_tf(td, -0.2, 0.0, 0.0))
        # both in the buffer before the frame (the frame may only wait tf_wait_ns = 200 ms)
        _tick_until(node, lambda _: node.counters().get("tf_messages", 0) >= seen_tf + 2, 10.0)
        robot.frame(head_view, tc + 50_000_000)
        cloud = _tick_until(node, bool)[0]
        truth = truth_T_base_cam(-0.3, 0.05, 0.0)
        T = np.asarray(cloud.T_frame_sensor)
        assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 1e-3
        assert _angle_deg(T[:3, :3].T @ truth[:3, :3]) < 0.05
        assert node.counters()["clouds_published"] == 2
    finally:
        robot.close()
        node.close()


def test_robot_camera_command_dispatches_on_source(capsys: pytest.CaptureFixture[str]) -> None:
    """``smartedge robot-camera --source ros`` is this node (its options), the default stays
    the simulated head camera."""
    from smartedge.cli import main

    with pytest.raises(SystemExit) as done:
        main(["robot-camera", "--source", "ros", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "--tf-wait-s" in out and "--depth-topic" in out
    with pytest.raises(SystemExit) as done:
        main(["robot-camera", "--help"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "--tf-wait-s" not in out and "--source {sim,ros}" in out
