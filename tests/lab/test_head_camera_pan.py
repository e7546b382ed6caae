"""The robot's head camera while the head pans and tilts (issue #28, item 2, simulation side).

* the head's kinematics: pan = tilt = 0 is exactly the site file's ``head_camera.T_base_cam``,
  the TF chain composes to ``T_base_cam``, joints stay in their limits and under 40 deg/s,
  the look-around is deterministic from the seed;
* ``smartedge sim-head``'s ``/tf`` and ``/tf_static``, decoded with rosbags into
  :class:`core.tf_buffer.TfBuffer`, give the true ``T_base_cam`` at stamps between two
  ``/tf`` messages;
* the placement figure: the head's published RGB-D frames (decoded with rosbags), the camera's
  pose looked up in that TF buffer at each image stamp, the semantic cloud built by
  :mod:`edge_agent.semantic_cloud` in ``base_link`` and placed in the map with the robot's true
  pose, against the truth (the renderer's exact depth back-projected with OpenCV at the *true*
  panned camera pose): median <= 2 cm; the same frames placed with the fixed (pan = 0) mounting
  are far off, so the test can fail;
* over real Zenoh on loopback, the service publishes the rmw_zenoh way: keys with the type
  hash, attachments with sequence numbers, liveliness tokens of a node and its publishers.
"""

from __future__ import annotations

import math
import threading
import time
from typing import Any

import numpy as np
import pytest

from core.geometry import se3_from_planar
from core.tf_buffer import TfBuffer
from protocol.semantic_classes import SEMANTIC_CLASS_ID
from simulation.head import (
    BASE_FRAME,
    CAMERA_FRAME,
    PAN_FRAME,
    TILT_FRAME,
    TORSO_FRAME,
    HeadKinematics,
    HeadMotion,
    SimulatedHead,
)
from tests.conftest import free_port, wait_until

pytest.importorskip("rosbags.typesys")

EPOCH_NS = 1_750_000_000_000_000_000
WALL = SEMANTIC_CLASS_ID["wall"]
ROOM_X, ROOM_Y = (0.0, 20.0), (0.0, 12.0)  # the paper lab's walls
#: the issue's target for the head camera's cloud placement
TARGET_MEDIAN_M = 0.02


def _home() -> np.ndarray:
    """The site file's head camera mounting."""
    live = _live()
    return live.site.robot_model(live.robot_id).head_camera.T_base_cam


def _live(epoch_ns: int = EPOCH_NS) -> Any:
    from simulation.live import LiveSimSpec, LiveSimulation
    from simulation.scenario import PAPER_SCENARIO

    return LiveSimulation(LiveSimSpec(str(PAPER_SCENARIO), "traj3", False, 0, epoch_ns))


def _wall_distance(p: np.ndarray) -> np.ndarray:
    return np.min(np.abs(np.stack([p[:, 0] - ROOM_X[0], p[:, 0] - ROOM_X[1],
                                   p[:, 1] - ROOM_Y[0], p[:, 1] - ROOM_Y[1]])), axis=0)


def _angle(R: np.ndarray) -> float:
    return math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))


# --------------------------------------------------------------------------------------------
# kinematics
# --------------------------------------------------------------------------------------------


def test_head_at_rest_is_the_site_mounting_and_the_chain_composes() -> None:
    live = _live()
    home = live.site.robot_model(live.robot_id).head_camera.T_base_cam
    kin = HeadKinematics(home)
    np.testing.assert_allclose(kin.T_base_cam(0.0, 0.0), home, atol=1e-12)
    chain = kin.transforms(0.4, -0.2)
    assert [(t.parent, t.child, t.static) for t in chain] == [
        (BASE_FRAME, TORSO_FRAME, True), (TORSO_FRAME, PAN_FRAME, False),
        (PAN_FRAME, TILT_FRAME, False), (TILT_FRAME, CAMERA_FRAME, True)]
    T = np.eye(4)
    for t in chain:
        T = T @ t.T_parent_child
    np.testing.assert_allclose(T, kin.T_base_cam(0.4, -0.2), atol=1e-12)
    # pan turns the camera about base z: its optical axis turns by the pan angle in the plane
    z0, z1 = home[:3, 2], kin.T_base_cam(0.5, 0.0)[:3, 2]
    yaw0, yaw1 = math.atan2(z0[1], z0[0]), math.atan2(z1[1], z1[0])
    assert yaw1 - yaw0 == pytest.approx(0.5, abs=1e-9)
    assert z1[2] == pytest.approx(z0[2], abs=1e-12)
    # positive tilt looks further down
    assert kin.T_base_cam(0.0, 0.2)[2, 2] < z0[2]
    with pytest.raises(ValueError, match="pan"):
        kin.T_base_cam(2.0, 0.0)
    with pytest.raises(ValueError, match="tilt"):
        kin.transforms(0.0, float("nan"))


def test_look_around_is_smooth_bounded_and_deterministic() -> None:
    head = SimulatedHead(HeadKinematics(_home()), HeadMotion(seed=3), EPOCH_NS)
    stamps = EPOCH_NS + np.arange(0, 60_000_000_000, 10_000_000)  # 60 s at 100 Hz
    joints = np.array([head.joints_at(int(s)) for s in stamps])
    k = head.kinematics
    for j, (lo, hi) in enumerate((k.pan_limits_rad, k.tilt_limits_rad)):
        assert np.all(joints[:, j] >= lo) and np.all(joints[:, j] <= hi)
    speed = np.abs(np.diff(joints, axis=0)) / 0.01
    assert speed[:, 0].max() <= math.radians(40.0)
    assert speed[:, 0].max() > math.radians(30.0)  # it does look around
    assert math.degrees(joints[:, 0].max()) > 65 and math.degrees(joints[:, 0].min()) < -65
    assert np.abs(np.diff(speed, axis=0)).max() / 0.01 < 1.0  # smooth: bounded acceleration
    again = SimulatedHead(HeadKinematics(_home()), HeadMotion(seed=3), EPOCH_NS)
    assert again.joints_at(EPOCH_NS + 1_234_567_890) == head.joints_at(EPOCH_NS + 1_234_567_890)
    other = SimulatedHead(HeadKinematics(_home()), HeadMotion(seed=4), EPOCH_NS)
    assert other.joints_at(EPOCH_NS) != head.joints_at(EPOCH_NS)
    still = SimulatedHead(HeadKinematics(_home()), None, EPOCH_NS)
    np.testing.assert_allclose(still.T_base_cam(EPOCH_NS + 5), _home(), atol=1e-12)


# --------------------------------------------------------------------------------------------
# /tf into the TF buffer
# --------------------------------------------------------------------------------------------


def _collect(stream: Any, t0_s: float, t1_s: float, step_s: float = 0.01,
             epoch_ns: int = EPOCH_NS) -> list[Any]:
    """Every message the stream publishes while simulated time runs from t0 to t1."""
    out: list[Any] = []
    for t in np.arange(t0_s, t1_s, step_s):
        out += stream.due(epoch_ns + round(float(t) * 1e9))
    return out


def _tf_buffer(messages: list[Any]) -> TfBuffer:
    from lab import simulated_head as hr
    from robot_bridge.adapters.ros2 import deserialize_tf_message

    tf = TfBuffer()
    for m in messages:
        if m.topic in (hr.TF_TOPIC, hr.TF_STATIC_TOPIC):
            added = tf.add_tf_message(deserialize_tf_message(m.payload),
                                      static=m.topic == hr.TF_STATIC_TOPIC)
            assert added > 0
    return tf


def test_published_tf_gives_the_true_camera_pose_between_messages() -> None:
    from lab import simulated_head as hr

    head = SimulatedHead.for_site_head(_home(), EPOCH_NS, seed=0)
    stream = hr.HeadRosStream(head, None)
    messages = _collect(stream, 0.0, 3.0, step_s=0.013)
    tf_stamps = [m.stamp_ns for m in messages if m.topic == hr.TF_TOPIC]
    assert len(tf_stamps) == pytest.approx(90, abs=2)
    assert np.all(np.diff(tf_stamps) == round(1e9 / 30))  # none skipped, none twice
    assert sum(m.topic == hr.TF_STATIC_TOPIC for m in messages) == 3  # at start, then at 1 Hz
    tf = _tf_buffer(messages)
    worst_m = worst_rad = 0.0
    for t in np.linspace(0.1, 2.9, 57):  # mostly between two /tf stamps
        stamp = EPOCH_NS + int(t * 1e9)
        T = tf.lookup(BASE_FRAME, CAMERA_FRAME, stamp)
        truth = head.T_base_cam(stamp)
        worst_m = max(worst_m, float(np.linalg.norm(T[:3, 3] - truth[:3, 3])))
        worst_rad = max(worst_rad, _angle(T[:3, :3].T @ truth[:3, :3]))
    # linear interpolation over 33 ms of a 36.7 deg/s sine: ~1e-4 rad at worst
    assert worst_m < 1e-4 and worst_rad < 2e-4, (worst_m, worst_rad)
    assert tf.counters["missing"] == 0 and tf.counters["invalid"] == 0


# --------------------------------------------------------------------------------------------
# the placement figure
# --------------------------------------------------------------------------------------------


class _RecordingFeed:
    """The real :class:`simulation.live.HeadCameraFeed`, keeping each frame's exact depth and
    labels (the truth and the segmentation of this test)."""

    def __init__(self, feed: Any) -> None:
        self.feed = feed
        self.head = feed.head
        self.frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def due(self, now_ns: int) -> int | None:
        return self.feed.due(now_ns)

    def render(self, capture_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = self.feed.images.render_head(self.feed.head, self.feed.live.ground_truth(capture_ns),
                                           self.feed.camera_id, self.feed.T_base_cam(capture_ns))
        rgb, depth, class_id = self.feed.render(capture_ns)
        assert np.array_equal(class_id, out.class_id)
        self.frames[capture_ns] = (np.asarray(out.depth_m, np.float64), class_id)
        return rgb, depth, class_id

    @property
    def skipped(self) -> int:
        return self.feed.skipped

    @property
    def seq(self) -> int:
        return self.feed.seq

    def release(self) -> None:
        self.feed.release()


def _truth_segmentation(class_id: np.ndarray, scale: int = 2) -> Any:
    from edge_agent.networks import Segmentation

    h, w = class_id.shape
    oh, ow = h // scale, w // scale
    v = np.floor((np.arange(oh) + 0.5) * h / oh).astype(int)
    u = np.floor((np.arange(ow) + 0.5) * w / ow).astype(int)
    cls = class_id[np.ix_(v, u)].astype(np.uint8)
    return Segmentation(cls, np.ones(cls.shape, np.float32), w, h, 0.0)


def _truth_surface_world(depth_m: np.ndarray, class_id: np.ndarray, K: np.ndarray,
                         dist: np.ndarray, T_world_cam: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Every pixel with depth back-projected with OpenCV (its own undistortion) into the
    world: the dense true surface the camera saw, and each point's class id."""
    import cv2

    v, u = np.nonzero(np.isfinite(depth_m) & (depth_m > 0) & (depth_m < 10.0))
    uv = np.stack([u, v], axis=1).astype(np.float64).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(uv, K, dist, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    xy = xy.reshape(-1, 2)
    z = depth_m[v, u]
    p_cam = np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)
    return p_cam @ T_world_cam[:3, :3].T + T_world_cam[:3, 3], class_id[v, u]


def _camera_from_info(msg: Any) -> Any:
    from core.camera import CameraModel

    return CameraModel("head", int(msg.width), int(msg.height),
                       np.asarray(msg.k, np.float64).reshape(3, 3),
                       np.asarray(msg.d, np.float64), np.eye(4))


def _placement(depth_noise: Any, t_end_s: float = 6.2) -> dict[str, Any]:
    """Runs the publisher over [0, t_end_s] of simulated time with the panning head and
    places every published frame: per frame, the median distance of its cloud's points to the
    true surface with T_base_cam from the TF buffer, from the head's truth and the fixed
    mounting."""
    from scipy.spatial import cKDTree

    from edge_agent.semantic_cloud import (
        ROBOT_BASE_FRAME,
        SemanticCloudConfig,
        build_semantic_cloud,
    )
    from lab import simulated_head as hr
    from robot_bridge.adapters.ros2 import typestore
    from simulation.live import HeadCameraFeed

    live = _live()
    home = live.site.robot_model(live.robot_id).head_camera.T_base_cam
    head = SimulatedHead.for_site_head(home, live.spec.epoch_ns, seed=live.spec.seed)
    feed = _RecordingFeed(HeadCameraFeed(live, rate_hz=2.0, depth_noise=depth_noise, head=head))
    stream = hr.HeadRosStream(head, feed)  # type: ignore[arg-type]
    try:
        t0 = time.perf_counter()
        messages = _collect(stream, 0.0, t_end_s)
        publish_s = time.perf_counter() - t0
    finally:
        feed.release()
    tf = _tf_buffer(messages)
    ts = typestore()
    by_stamp: dict[int, dict[str, Any]] = {}
    for m in messages:
        if m.topic in (hr.COLOR_TOPIC, hr.DEPTH_TOPIC, hr.CAMERA_INFO_TOPIC):
            msg = ts.deserialize_cdr(m.payload, m.ros_type)
            assert msg.header.frame_id == CAMERA_FRAME
            stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            assert stamp == m.stamp_ns
            by_stamp.setdefault(stamp, {})[m.topic] = msg
    config = SemanticCloudConfig(max_range_m=8.0)
    frames = []
    for stamp, msgs in sorted(by_stamp.items()):
        color, depth_msg, info = (msgs[hr.COLOR_TOPIC], msgs[hr.DEPTH_TOPIC],
                                  msgs[hr.CAMERA_INFO_TOPIC])
        assert color.encoding == "rgb8" and depth_msg.encoding == "16UC1"
        depth_m = (np.frombuffer(depth_msg.data.tobytes(), "<u2")
                   .reshape(depth_msg.height, depth_msg.width).astype(np.float32) / 1000.0)
        camera = _camera_from_info(info)
        exact_depth, class_id = feed.frames[stamp]
        T_world_base = se3_from_planar(*live.ground_truth(stamp))
        T_base_cam_true = head.T_base_cam(stamp)
        surface = _truth_surface_world(exact_depth, class_id, camera.K, camera.dist,
                                       T_world_base @ T_base_cam_true)
        truth = cKDTree(surface[0])
        walls = surface[1] == WALL
        seg = _truth_segmentation(class_id)
        row: dict[str, Any] = {"stamp_ns": stamp,
                               "pan_deg": math.degrees(head.joints_at(stamp)[0]),
                               # the truth itself checked against the site: wall pixels on the
                               # lab's wall planes (a render that ignored the pan would not be)
                               "wall_px": int(walls.sum()),
                               "wall_off_m": _wall_distance(surface[0][walls])}
        for name, T_base_cam in (("tf", tf.lookup(BASE_FRAME, CAMERA_FRAME, stamp)),
                                 ("truth", T_base_cam_true), ("fixed", home)):
            cloud = build_semantic_cloud(seg, depth_m, camera, sensor_id="hsr", stamp_ns=stamp,
                                         seq=0, frame_id=ROBOT_BASE_FRAME,
                                         T_frame_sensor=T_base_cam, config=config)
            p = cloud.points_xyz.astype(np.float64) @ T_world_base[:3, :3].T + T_world_base[:3, 3]
            row[name] = truth.query(p)[0]
        frames.append(row)
    costs = np.array(stream.frame_costs_ms)
    return {"frames": frames, "publish_s": publish_s, "render_ms": np.median(costs[1:, 0]),
            "encode_ms": np.median(costs[1:, 1]), "counters": dict(stream.counters)}


def _report(label: str, result: dict[str, Any]) -> dict[str, float]:
    frames = result["frames"]
    medians = {name: float(np.median(np.concatenate([f[name] for f in frames])))
               for name in ("tf", "truth", "fixed")}
    print(f"\n{label}: {len(frames)} frames, pan {min(f['pan_deg'] for f in frames):.0f}.."
          f"{max(f['pan_deg'] for f in frames):.0f} deg; median placement error: "
          f"TF lookup {medians['tf'] * 100:.2f} cm, true T_base_cam "
          f"{medians['truth'] * 100:.2f} cm,"
          f" fixed mounting {medians['fixed'] * 100:.1f} cm; per frame (TF): "
          + " ".join(f"{np.median(f['tf']) * 100:.2f}" for f in frames))
    return medians


@pytest.fixture(scope="module")
def gl() -> None:
    pytest.importorskip("moderngl", reason="rendering needs moderngl")
    pytest.importorskip("scipy")
    pytest.importorskip("cv2")


def test_panning_head_cloud_is_placed_within_2cm_of_the_truth(gl: None) -> None:
    """The issue's target: the semantic cloud of a head camera that pans, its pose from /tf
    at the image stamp, is placed within 2 cm (median) of the true surface; with the fixed
    mounting the same frames are far off."""
    from simulation.site_cameras import DepthNoise

    result = _placement(DepthNoise(sigma_per_m=0.0))
    frames = result["frames"]
    assert len(frames) >= 12
    pans = [f["pan_deg"] for f in frames]
    assert max(pans) > 45 and min(pans) < -45  # the head really looked around
    medians = _report("exact depth", result)
    with_walls = [f for f in frames if f["wall_px"] > 2000]
    assert len(with_walls) >= 4
    assert all(np.median(f["wall_off_m"]) < 0.01 for f in with_walls)
    assert medians["tf"] <= TARGET_MEDIAN_M
    assert all(np.median(f["tf"]) <= 1.5 * TARGET_MEDIAN_M for f in frames)
    assert medians["tf"] == pytest.approx(medians["truth"], abs=0.002)
    # the test can fail: the fixed mounting puts the panned frames' clouds far from the truth
    assert medians["fixed"] > 10 * TARGET_MEDIAN_M
    turned = [f for f in frames if abs(f["pan_deg"]) > 30]
    assert all(np.median(f["fixed"]) > 0.2 for f in turned)


def test_panning_head_cloud_with_depth_noise(gl: None) -> None:
    """The same with the simulated depth camera's noise (sigma_z = 0.0025 z^2): reported, and
    still within a few cm."""
    from simulation.site_cameras import DepthNoise

    result = _placement(DepthNoise(), t_end_s=3.2)
    medians = _report("depth noise", result)
    print(f"publisher cost per frame (median after the first): render + noise "
          f"{result['render_ms']:.1f} ms, CDR of colour + depth + info "
          f"{result['encode_ms']:.1f} ms")
    assert medians["tf"] <= 2 * TARGET_MEDIAN_M
    assert medians["fixed"] > 5 * TARGET_MEDIAN_M


# --------------------------------------------------------------------------------------------
# over Zenoh, the rmw_zenoh way
# --------------------------------------------------------------------------------------------


def test_sim_head_publishes_the_rmw_zenoh_way_over_loopback(gl: None) -> None:
    zenoh = pytest.importorskip("zenoh")
    from core.runtime import ZenohRunner
    from core.session import loopback_config
    from lab import simulated_head as hr
    from robot_bridge.adapters.rmw_zenoh_wire import (
        decode_attachment,
        parse_liveliness_token,
        topic_key,
    )

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    epoch_ns = time.time_ns() - 2_000_000_000
    args = hr.build_parser().parse_args([
        "--sim-epoch-ns", str(epoch_ns), "--ros-domain-id", "7", "--rate", "4"])
    node = hr.build_node(args)
    received: dict[str, list[tuple[bytes, Any]]] = {}
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        att = sample.attachment
        with lock:
            received.setdefault(str(sample.key_expr), []).append(
                (sample.payload.to_bytes(), None if att is None else att.to_bytes()))

    session = zenoh.open(loopback_config(listen=[endpoint]))
    sub = session.declare_subscriber("7/**", on_sample)
    runner = ZenohRunner(node, loopback_config(connect=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    try:
        color_key = topic_key(7, hr.COLOR_TOPIC, hr.IMAGE_TYPE)
        tf_key = topic_key(7, hr.TF_TOPIC, hr.TF_MESSAGE_TYPE)
        static_key = topic_key(7, hr.TF_STATIC_TOPIC, hr.TF_MESSAGE_TYPE)
        # (the first samples may go out before the link is up: /tf_static comes again at 1 Hz)
        assert wait_until(lambda: len(received.get(color_key, [])) >= 5
                          and len(received.get(tf_key, [])) >= 30
                          and len(received.get(static_key, [])) >= 1, timeout_s=30.0), \
            {k: len(v) for k, v in received.items()}
        tokens = [str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/7/**") if r.ok]
    finally:
        runner.stop()
        thread.join(timeout=10)
        sub.undeclare()
        session.close()
    assert not thread.is_alive()
    with lock:
        got = {k: list(v) for k, v in received.items()}
    for topic, ros_type in hr.TOPIC_TYPES.items():
        key = topic_key(7, topic, ros_type)
        assert got.get(key), f"nothing on {key}"
        seqs = []
        for _, att in got[key]:
            assert att is not None, f"{topic}: a sample without rmw_zenoh's attachment"
            seqs.append(decode_attachment(att).sequence_number)
        # sequence numbers from 1 per publisher, in order (a sample lost while the loopback
        # link warms up shows as a gap, which ROS subscribers count; none once it runs)
        assert seqs[0] >= 1 and np.all(np.diff(seqs) > 0), (topic, seqs)
        tail = seqs[-min(len(seqs), 10):]
        assert tail == list(range(tail[0], tail[0] + len(tail))), (topic, seqs)
    parsed = [parse_liveliness_token(k) for k in tokens]
    assert sum(t.kind == "NN" and t.node_name == hr.DEFAULT_NODE_NAME for t in parsed) == 1
    published = {t.topic for t in parsed if t.kind == "MP"}
    assert published == set(hr.TOPIC_TYPES), published
    # what arrived decodes, and /tf over the wire gives the true head pose
    tf = _tf_buffer([hr.RosMessage(topic, ros_type, payload, 0)
                     for topic, ros_type in hr.TOPIC_TYPES.items() if ros_type == hr.TF_MESSAGE_TYPE
                     for payload, _ in got[topic_key(7, topic, ros_type)]])
    head = node.stream.head
    from robot_bridge.adapters.ros2 import typestore

    ts = typestore()
    image_stamps = []
    for payload, _ in got[color_key]:
        msg = ts.deserialize_cdr(payload, hr.IMAGE_TYPE)
        assert (msg.height, msg.width, msg.encoding) == (480, 640, "rgb8")
        image_stamps.append(int(msg.header.stamp.sec) * 1_000_000_000
                            + int(msg.header.stamp.nanosec))
    # the /tf stamps that arrived: an image stamped after the last of them (the run stopped
    # before the next /tf came) would be extrapolated, and one between two that are not one
    # period apart lies across a sample lost while the link warmed up; only images between two
    # consecutive /tf are compared
    from robot_bridge.adapters.ros2 import deserialize_tf_message

    tf_stamps = np.array(sorted(
        int(t.header.stamp.sec) * 1_000_000_000 + int(t.header.stamp.nanosec)
        for payload, _ in got[tf_key] for t in deserialize_tf_message(payload).transforms))
    period_ns = round(1e9 / 30)
    looked_up = 0
    for stamp in image_stamps:
        k = int(np.searchsorted(tf_stamps, stamp))
        if not 0 < k < len(tf_stamps) or tf_stamps[k] - tf_stamps[k - 1] > period_ns + 1_000_000:
            continue
        if tf.can_transform(BASE_FRAME, CAMERA_FRAME, stamp):
            T = tf.lookup(BASE_FRAME, CAMERA_FRAME, stamp)
            assert np.linalg.norm(T[:3, 3] - head.T_base_cam(stamp)[:3, 3]) < 1e-4
            looked_up += 1
    assert looked_up >= 2


def test_tf_static_reaches_a_late_subscriber_from_the_publishers_cache(
        zenoh_pair: Any) -> None:
    """/tf_static is transient local as tf2's static broadcaster: a subscriber that joins after
    the only publication (an AdvancedSubscriber with history, as rmw_zenoh's and the robot
    camera's) still gets it, from the publisher's cache."""
    zext = pytest.importorskip("zenoh.ext")
    from lab import simulated_head as hr
    from robot_bridge.adapters.ros2 import deserialize_tf_message

    a, b, _ = zenoh_pair
    publishers = hr.RosZenohPublishers(a, domain_id=3)
    qos = hr._qos_by_topic()[hr.TF_STATIC_TOPIC]
    publishers.advertise(hr.TF_STATIC_TOPIC, hr.TF_MESSAGE_TYPE, qos)
    head = SimulatedHead.for_site_head(_home(), EPOCH_NS, seed=0)
    payload = hr.tf_message_cdr(head.static_transforms(), EPOCH_NS)
    publishers.put(hr.RosMessage(hr.TF_STATIC_TOPIC, hr.TF_MESSAGE_TYPE, payload, EPOCH_NS))
    time.sleep(0.3)  # published and gone before anyone listens
    got: list[bytes] = []
    key = publishers.keys()[hr.TF_STATIC_TOPIC].rsplit("/", 1)[0] + "/*"
    sub = zext.declare_advanced_subscriber(
        b, key, lambda s: got.append(s.payload.to_bytes()),
        history=zext.HistoryConfig(detect_late_publishers=True))
    try:
        assert wait_until(lambda: len(got) >= 1, timeout_s=5.0)
    finally:
        sub.undeclare()
        publishers.close()
    tf = TfBuffer()
    assert tf.add_tf_message(deserialize_tf_message(got[0]), static=True) == 2
    np.testing.assert_allclose(tf.lookup(TORSO_FRAME, BASE_FRAME), np.linalg.inv(
        head.kinematics.T_base_torso), atol=1e-9)


# --------------------------------------------------------------------------------------------
# the real chain: sim-head -> Zenoh -> smartedge robot-camera --source ros -> cloud
# --------------------------------------------------------------------------------------------


def test_real_chain_places_the_panning_head_cloud_within_2cm(gl: None) -> None:
    """``smartedge sim-head`` and ``smartedge robot-camera --source ros`` (the real robot's node,
    with the shipped segmentation network) as Zenoh runners on loopback: every cloud's
    ``T_frame_sensor`` is the head's true pose at the image stamp (TF looked up at the stamp,
    between two /tf messages) and the clouds land within 2 cm (median) of the true surface,
    while the fixed mounting would put them tens of cm off."""
    zenoh = pytest.importorskip("zenoh")
    pytest.importorskip("onnxruntime")
    rc = pytest.importorskip("edge_agent.robot_camera")
    from scipy.spatial import cKDTree

    from core.runtime import ZenohRunner
    from core.session import loopback_config
    from lab import simulated_head as hr
    from protocol import decode, keys
    from simulation.site_cameras import SiteCameraRenderer

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    epoch_ns = time.time_ns() + 500_000_000
    live = _live(epoch_ns)
    sim = live.spec.to_argv()
    publisher = hr.build_node(hr.build_parser().parse_args(
        [*sim, "--ros-domain-id", "9", "--depth-sigma-per-m", "0"]))
    camera = rc.build_node(rc.build_parser().parse_args(
        ["--site", live.site.source_path, "--ros-domain-id", "9", "--cloud-rate", "1",
         "--threads", "1"]))
    clouds: list[Any] = []
    session = zenoh.open(loopback_config(listen=[endpoint]))
    sub = session.declare_subscriber(keys.robot_cloud_key(live.site.name, live.robot_id),
                                     lambda s: clouds.append(decode(s.payload.to_bytes())))
    runners = [ZenohRunner(n, loopback_config(listen=["tcp/127.0.0.1:0"], connect=[endpoint]))
               for n in (publisher, camera)]
    threads = [threading.Thread(target=r.run, daemon=True) for r in runners]
    for t in threads:
        t.start()
    try:
        assert wait_until(lambda: len(clouds) >= 5, timeout_s=20.0), camera.state()
    finally:
        for r in reversed(runners):
            r.stop()
        for t in threads:
            t.join(timeout=10)
        sub.undeclare()
        session.close()
    head = publisher.stream.head
    home = live.site.robot_model(live.robot_id).head_camera
    images = SiteCameraRenderer(live.scenario)
    errors, fixed, pans = [], [], []
    try:
        for cloud in clouds:
            stamp = cloud.stamp_ns
            truth_T = head.T_base_cam(stamp)
            T = np.asarray(cloud.T_frame_sensor)
            assert np.linalg.norm(T[:3, 3] - truth_T[:3, 3]) < 1e-3
            assert math.degrees(_angle(T[:3, :3].T @ truth_T[:3, :3])) < 0.05
            T_world_base = se3_from_planar(*live.ground_truth(stamp))
            out = images.render_head(home, live.ground_truth(stamp), "head", truth_T)
            surface, _ = _truth_surface_world(np.asarray(out.depth_m, np.float64),
                                              out.class_id, home.K, home.dist,
                                              T_world_base @ truth_T)
            tree = cKDTree(surface)
            p_base = cloud.points_xyz.astype(np.float64)
            errors.append(tree.query(p_base @ T_world_base[:3, :3].T + T_world_base[:3, 3])[0])
            # the same points as if the head had not moved
            p_cam = (p_base - T[:3, 3]) @ T[:3, :3]
            T_fixed = T_world_base @ home.T_base_cam
            fixed.append(tree.query(p_cam @ T_fixed[:3, :3].T + T_fixed[:3, 3])[0])
            pans.append(math.degrees(head.joints_at(stamp)[0]))
    finally:
        images.release()
    median = float(np.median(np.concatenate(errors)))
    median_fixed = float(np.median(np.concatenate(fixed)))
    print(f"\nreal chain: {len(clouds)} clouds, pan {min(pans):.0f}..{max(pans):.0f} deg, median "
          f"placement {median * 100:.2f} cm (fixed mounting {median_fixed * 100:.1f} cm)")
    assert max(pans) - min(pans) > 40
    assert median <= TARGET_MEDIAN_M
    assert median_fixed > 10 * TARGET_MEDIAN_M


def test_demo_runs_the_simulated_head_and_the_ros_robot_camera() -> None:
    """``smartedge demo``'s head camera is the ROS path: ``sim-head`` (2 Hz RGB-D, /tf) and
    ``robot-camera --source ros``; both build in-process from those argv as the demo does, and
    ``--no-clouds`` leaves both out."""
    import argparse
    from pathlib import Path

    from lab import demo
    from lab.simulated_head import HeadRosNode

    live = _live()
    args = argparse.Namespace(no_feedback=False, kidnapped=False, processes=False,
                              detections="noise", no_clouds=False)
    services = demo.Services(args, live.spec, Path(live.site.source_path),
                             "tcp/127.0.0.1:7447", "none", ["cam1"])
    commands = dict(services.commands())
    assert commands["sim-head"][:3] == ["sim-head", "--rate", f"{demo.DEMO_HEAD_RATE_HZ:g}"]
    assert commands["robot-camera"][:3] == ["robot-camera", "--source", "ros"]
    head_node, _ = demo._build_in_process(commands["sim-head"])
    assert isinstance(head_node, HeadRosNode) and head_node.stream.feed is not None
    assert head_node.stream.head.motion is not None  # it looks around
    head_node.close()
    rc = pytest.importorskip("edge_agent.robot_camera", reason="the ROS robot camera node")
    camera_node, _ = demo._build_in_process(commands["robot-camera"])
    assert isinstance(camera_node, rc.RosRobotCameraNode)
    camera_node.close()
    args.no_clouds = True
    names = [name for name, _ in services.commands()]
    assert "sim-head" not in names and "robot-camera" not in names


def test_ros2dds_transport_uses_plain_topic_keys(zenoh_pair: Any) -> None:
    """``--ros-transport ros2dds``: the keys zenoh-bridge-ros2dds uses (the topic name under the
    bridge's namespace), CDR without an attachment, no rmw_zenoh tokens."""
    from lab import simulated_head as hr
    from robot_bridge.adapters.ros2 import deserialize_tf_message

    a, b, _ = zenoh_pair
    got: list[tuple[str, bytes, Any]] = []
    sub = b.declare_subscriber("robot1/**", lambda s: got.append(
        (str(s.key_expr), s.payload.to_bytes(), s.attachment)))
    publishers = hr.RosZenohPublishers(a, transport="ros2dds", namespace="robot1")
    try:
        publishers.advertise(hr.TF_TOPIC, hr.TF_MESSAGE_TYPE)
        assert publishers.keys() == {hr.TF_TOPIC: "robot1/tf"}
        assert publishers.token_keys() == []
        head = SimulatedHead.for_site_head(_home(), EPOCH_NS, seed=0)
        payload = hr.tf_message_cdr(head.dynamic_transforms(EPOCH_NS), EPOCH_NS)
        msg = hr.RosMessage(hr.TF_TOPIC, hr.TF_MESSAGE_TYPE, payload, EPOCH_NS)
        assert wait_until(lambda: (publishers.put(msg), bool(got))[1], timeout_s=5.0)
    finally:
        publishers.close()
        sub.undeclare()
    key, data, attachment = got[0]
    assert key == "robot1/tf" and attachment is None
    decoded = deserialize_tf_message(data)
    frames = [(t.header.frame_id, t.child_frame_id) for t in decoded.transforms]
    assert frames == [(TORSO_FRAME, PAN_FRAME), (PAN_FRAME, TILT_FRAME)]
