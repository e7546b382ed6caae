"""``smartedge record`` writes MCAP with ROS 2 schemas and CDR: an independent decoder
(``mcap-ros2-support``) reads every channel, the values are the messages', the wire bytes come
back exactly, old msgpack recordings still read, ``smartedge export tum`` / ``evaluate ate``
read poses from a recording, and a damaged or foreign channel gives a clear error."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("rosbags")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")

from mcap.reader import make_reader  # noqa: E402
from mcap.writer import Writer  # noqa: E402

from core.session import loopback_config  # noqa: E402
from core.trajectory import read_tum, write_tum_planar  # noqa: E402
from lab.evaluate import main as evaluate_main  # noqa: E402
from protocol import keys  # noqa: E402
from protocol.codec import encode  # noqa: E402
from protocol.messages import (  # noqa: E402
    CameraImage,
    Detection,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    SemanticCloud,
    ServiceStatus,
)
from smartedge.commands.export import main as export_main  # noqa: E402
from smartedge.commands.record import Recorder, RecordingError, read_recording  # noqa: E402
from tests.conftest import free_port  # noqa: E402

SITE, ROBOT, CAM = "lab", "hsr", "cam-1"
T0 = 1_700_000_000_000_000_000


def _messages(k: int) -> list[tuple[str, object]]:
    """One message of every type at step k, with values that depend on k."""
    rng = np.random.default_rng(k)
    stamp = T0 + k * 50_000_000
    cov = np.diag([1e-4, 2e-4, 3e-4])
    det = Detection(np.array([10.0, 20.0, 110.0 + k, 220.0]), 0.9,
                    rng.uniform(0, 400, (5, 2)), np.linspace(0.1, 0.9, 5), robot_id=ROBOT,
                    keypoint_sigmas_px=np.full(5, 1.5), robot_model="hsr")
    pts = rng.normal(size=(30 + k, 3)).astype(np.float32)
    return [
        (keys.pose_key(SITE, ROBOT), PoseEstimate(
            ROBOT, stamp, k, 1.0 + 0.1 * k, -2.0, 0.05 * k, cov, "fused",
            camera_ids=("cam-1", "cam-2"), flags=("multi_frame",))),
        (keys.correction_key(SITE, ROBOT), PoseCorrection(
            ROBOT, stamp, k, 0.5, 0.25, -0.3, cov, "correction")),
        (keys.odom_key(SITE, ROBOT), Odometry(
            ROBOT, stamp, k, 0.01 * k, 0.0, 0.02 * k, vx=0.3, wz=0.1, covariance=cov)),
        (keys.detections_key(SITE, CAM), RobotDetections(
            CAM, stamp, k, 848, 480, "kp-v3", (det,))),
        (keys.image_key(SITE, CAM), CameraImage(
            CAM, stamp, k, 848, 480, "jpeg", np.arange(100 + k, dtype=np.uint8))),
        (keys.edge_cloud_key(SITE, CAM), SemanticCloud(
            CAM, stamp, k, "world", pts, np.full(len(pts), 7 + k, np.uint16),
            np.full(len(pts), 0.5, np.float32))),
        (keys.status_key(SITE, "backend", "b1"), ServiceStatus(
            "backend", "b1", stamp, k, state="degraded", rates_hz={"fused": 14.5},
            counters={"invalid": k}, detail="camera cam-2 silent")),
    ]


def _write(path: Path, steps: int = 6, fmt: str = "ros2") -> list[tuple[str, int, bytes]]:
    rec = Recorder(path, fmt)
    written = []
    for k in range(steps):
        for j, (key, msg) in enumerate(_messages(k)):
            payload, receive_ns = encode(msg), T0 + k * 50_000_000 + j * 1000 + 3_000_000
            rec.write(key, payload, receive_ns)
            written.append((key, receive_ns, payload))
    rec.write("smartedge/lab/robot/hsr/odom", b"\x93garbage", T0 + 10**9)  # undecodable
    written.append(("smartedge/lab/robot/hsr/odom", T0 + 10**9, b"\x93garbage"))
    rec.close()
    return written


def _decoded(path: Path) -> dict[str, list[tuple[str, object]]]:
    """topic → [(schema name, decoded message)] through mcap-ros2-support; raises on any
    channel it cannot decode."""
    out: dict[str, list[tuple[str, object]]] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        for schema, channel, _message, obj in reader.iter_decoded_messages():
            assert channel.message_encoding == "cdr" and schema.encoding == "ros2msg"
            out.setdefault(channel.topic, []).append((schema.name, obj))
    return out


def test_every_channel_decodes_with_an_independent_decoder(tmp_path: Path) -> None:
    _write(tmp_path / "r.mcap")
    by_topic = _decoded(tmp_path / "r.mcap")
    types = {topic: items[0][0] for topic, items in by_topic.items()}
    pose_topic = "/smartedge/lab/robot/hsr/pose"
    assert types[pose_topic] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert types["/smartedge/lab/robot/hsr/odom"] == "nav_msgs/msg/Odometry"
    assert types["/smartedge/lab/edge/cam_1/detections"] == "smartedge_msgs/msg/RobotDetections"
    assert types["/smartedge/lab/edge/cam_1/image"] == "sensor_msgs/msg/CompressedImage"
    assert types["/smartedge/lab/edge/cam_1/cloud"] == "sensor_msgs/msg/PointCloud2"
    assert types["/smartedge/lab/status/backend/b1"] == "diagnostic_msgs/msg/DiagnosticArray"
    wire = [t for t in types if t.startswith("/_smartedge_wire/")]
    assert len(wire) == 7 and all(types[t] == "smartedge_msgs/msg/Wire" for t in wire)
    # the garbage odom payload: in the wire channel only
    assert len(by_topic["/_smartedge_wire/smartedge/lab/robot/hsr/odom"]) == 7
    assert len(by_topic["/smartedge/lab/robot/hsr/odom"]) == 6

    # values: what the messages said
    k = 4
    ref = dict(_messages(k))
    pose = by_topic[pose_topic][k][1]
    assert pose.header.frame_id == "map"
    assert pose.header.stamp.sec * 10**9 + pose.header.stamp.nanosec == T0 + k * 50_000_000
    assert pose.pose.pose.position.x == pytest.approx(1.0 + 0.1 * k)
    q = pose.pose.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(0.05 * k)
    assert pose.pose.covariance[35] == pytest.approx(3e-4)  # yaw variance, REP 103 order
    odom = by_topic["/smartedge/lab/robot/hsr/odom"][k][1]
    assert odom.twist.twist.linear.x == pytest.approx(0.3)
    dets = by_topic["/smartedge/lab/edge/cam_1/detections"][k][1]
    ref_det = ref[keys.detections_key(SITE, CAM)].detections[0]
    np.testing.assert_allclose(np.reshape(dets.detections[0].keypoints_px, (-1, 2)),
                               ref_det.keypoints_px)
    assert dets.detections[0].robot_id == ROBOT and dets.model_id == "kp-v3"
    assert dets.detections[0].robot_model == "hsr"
    cloud = by_topic["/smartedge/lab/edge/cam_1/cloud"][k][1]
    rows = np.frombuffer(bytes(cloud.data), dtype=np.dtype(
        {"names": ["x", "y", "z", "label", "confidence"],
         "formats": ["<f4", "<f4", "<f4", "<u2", "<f4"],
         "offsets": [f.offset for f in cloud.fields], "itemsize": cloud.point_step}))
    ref_cloud = ref[keys.edge_cloud_key(SITE, CAM)]
    np.testing.assert_array_equal(np.stack([rows["x"], rows["y"], rows["z"]], 1),
                                  ref_cloud.points_xyz)
    assert set(rows["label"]) == {7 + k}
    image = by_topic["/smartedge/lab/edge/cam_1/image"][k][1]
    assert image.format == "jpeg" and bytes(image.data) == bytes(range(100 + k))
    status = by_topic["/smartedge/lab/status/backend/b1"][k][1].status[0]
    assert status.level == 1 and status.message == "camera cam-2 silent"
    assert {v.key: v.value for v in status.values}["count/invalid"] == str(k)


def test_wire_bytes_come_back_exactly_in_both_formats(tmp_path: Path) -> None:
    for fmt in ("ros2", "msgpack"):
        written = _write(tmp_path / f"{fmt}.mcap", fmt=fmt)
        got = list(read_recording(tmp_path / f"{fmt}.mcap"))
        assert sorted(got) == sorted(written), fmt  # same (key, receive_ns, payload)
    assert len(written) == 43


def test_live_record_process_over_zenoh(tmp_path: Path) -> None:
    """``smartedge record`` as a process on real Zenoh: a ROS 2 MCAP whose wire channels hold
    exactly the published payloads and whose every channel decodes."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zargs = ["--mode", "client", "--connect", endpoint, "--no-multicast-scouting"]
    published: list[tuple[str, bytes]] = []
    with zenoh.open(loopback_config(listen=[endpoint])) as hub:
        log = tmp_path / "record.log"
        proc = subprocess.Popen([sys.executable, "-m", "smartedge", "record",
                                 str(tmp_path / "live.mcap"), *zargs],
                                stdout=log.open("w"), stderr=subprocess.STDOUT)
        # the recorder's subscription (it takes smartedge/**) reached the hub (was a fixed
        # 2.5 s); the probe publisher puts nothing
        probe = hub.declare_publisher(_messages(0)[0][0])
        deadline = time.monotonic() + 30
        while not probe.matching_status.matching:
            assert time.monotonic() < deadline and proc.poll() is None, log.read_text()
            time.sleep(0.05)
        probe.undeclare()
        for k in range(5):
            for key, msg in _messages(k):
                payload = encode(msg)
                hub.put(key, payload)
                published.append((key, payload))
            time.sleep(0.02)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0, log.read_text()
    assert "recorded 35 messages" in log.read_text(), log.read_text()
    got = [(k, p) for k, _, p in read_recording(tmp_path / "live.mcap")]
    assert sorted(got) == sorted(published)
    by_topic = _decoded(tmp_path / "live.mcap")
    assert len(by_topic) == 14 and all(len(v) == 5 for v in by_topic.values())


def test_export_tum_round_trip_and_ate_from_a_recording(tmp_path: Path, capsys) -> None:
    _write(tmp_path / "r.mcap", steps=20)
    key = keys.pose_key(SITE, ROBOT)
    assert export_main(["tum", str(tmp_path / "r.mcap"), "--key", key,
                        "--out", str(tmp_path / "est.tum")]) == 0
    traj = read_tum(tmp_path / "est.tum")
    k = np.arange(20)
    np.testing.assert_allclose(traj.stamps_s, (T0 + k * 50_000_000) * 1e-9)
    np.testing.assert_allclose(traj.positions_m[:, 0], 1.0 + 0.1 * k, atol=1e-9)
    np.testing.assert_allclose(2 * np.arctan2(traj.quat_xyzw[:, 2], traj.quat_xyzw[:, 3]),
                               0.05 * k, atol=1e-9)
    # the same poses from the ROS topic (the typed channel, as any ROS 2 MCAP has it)
    assert export_main(["tum", str(tmp_path / "r.mcap"), "--key", "/smartedge/lab/robot/hsr/pose",
                        "--out", str(tmp_path / "ros.tum")]) == 0
    np.testing.assert_allclose(read_tum(tmp_path / "ros.tum").positions_m, traj.positions_m)
    # ATE of the recording against a "motion capture" 3 cm off in y
    gt = np.stack([1.0 + 0.1 * k, np.full(20, -2.03), 0.05 * k], 1)
    write_tum_planar(tmp_path / "gt.tum", (T0 + k * 50_000_000) * 1e-9, gt)
    capsys.readouterr()
    assert evaluate_main(["ate", str(tmp_path / "gt.tum"), str(tmp_path / "r.mcap"),
                          "--est-key", key]) == 0
    out = capsys.readouterr().out
    assert "rmse\t0.030000" in out and "matched poses: 20" in out, out
    # errors are named
    assert export_main(["tum", str(tmp_path / "r.mcap"), "--key", "smartedge/lab/robot/x/pose",
                        "--out", str(tmp_path / "x.tum")]) == 1
    assert "no key or topic 'smartedge/lab/robot/x/pose'" in capsys.readouterr().err
    assert export_main(["tum", str(tmp_path / "r.mcap"), "--key", keys.image_key(SITE, CAM),
                        "--out", str(tmp_path / "x.tum")]) == 1
    assert "none of its messages is a pose" in capsys.readouterr().err
    assert evaluate_main(["ate", str(tmp_path / "gt.tum"), str(tmp_path / "r.mcap")]) == 1
    assert "--est-key" in capsys.readouterr().err


def test_damaged_and_foreign_channels_give_a_clear_error(tmp_path: Path) -> None:
    from smartedge import record_ros

    # a wire message whose length field lies
    with (tmp_path / "bad.mcap").open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(name=record_ros.WIRE_TYPE, encoding="ros2msg",
                                data=record_ros.schema_text(record_ros.WIRE_TYPE))
        cid = w.register_channel(topic="/_smartedge_wire/smartedge/lab/robot/hsr/odom",
                                 message_encoding="cdr", schema_id=sid,
                                 metadata={record_ros.KEY_METADATA: "smartedge/lab/robot/hsr/odom"})
        good = record_ros.wire_cdr(b"\x01\x02\x03")
        w.add_message(channel_id=cid, log_time=1, publish_time=1, data=good, sequence=0)
        w.add_message(channel_id=cid, log_time=2, publish_time=2, data=good[:6] + b"\xff" * 10,
                      sequence=1)
        w.finish()
    with pytest.raises(RecordingError, match=r"bad\.mcap: channel /_smartedge_wire/smartedge/"
                       r"lab/robot/hsr/odom, message 1: Wire\.data says .* 1 messages read"):
        list(read_recording(tmp_path / "bad.mcap"))
    # a channel smartedge record does not write (a ros2 bag topic)
    with (tmp_path / "foreign.mcap").open("wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        ts = record_ros.typestore()
        sid = w.register_schema(name="geometry_msgs/msg/PoseStamped", encoding="ros2msg",
                                data=record_ros.schema_text("geometry_msgs/msg/PoseStamped"))
        cid = w.register_channel(topic="/mocap/hsr", message_encoding="cdr", schema_id=sid)
        t = ts.types
        for k in range(3):
            msg = t["geometry_msgs/msg/PoseStamped"](
                header=t["std_msgs/msg/Header"](
                    stamp=t["builtin_interfaces/msg/Time"](sec=100 + k, nanosec=0),
                    frame_id="mocap"),
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=float(k), y=2.0, z=0.1),
                    orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
            w.add_message(channel_id=cid, log_time=k + 1, publish_time=k + 1, sequence=k,
                          data=bytes(ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped")))
        w.finish()
    with pytest.raises(RecordingError, match=r"channel /mocap/hsr \(cdr, geometry_msgs/msg/"
                       r"PoseStamped\) is not a smartedge record channel"):
        list(read_recording(tmp_path / "foreign.mcap"))
    # ... while export reads it: motion capture from a ROS 2 recording
    assert export_main(["tum", str(tmp_path / "foreign.mcap"), "--key", "/mocap/hsr",
                        "--out", str(tmp_path / "mocap.tum")]) == 0
    mocap = read_tum(tmp_path / "mocap.tum")
    np.testing.assert_allclose(mocap.positions_m, [[0, 2, 0.1], [1, 2, 0.1], [2, 2, 0.1]])
    np.testing.assert_allclose(mocap.stamps_s, [100, 101, 102])


def test_the_ros_package_builds_every_message_file() -> None:
    """The ``smartedge_msgs`` .msg files are the ones the colcon package generates."""
    from smartedge import record_ros

    pkg = record_ros.MSG_DIR / "smartedge_msgs"
    cmake = (pkg / "CMakeLists.txt").read_text()
    files = sorted(p.name for p in (pkg / "msg").glob("*.msg"))
    assert files == ["Detection.msg", "RobotDetections.msg", "Wire.msg"]
    assert all(f'"msg/{name}"' in cmake for name in files)
    assert all(f"smartedge_msgs/msg/{Path(n).stem}" in record_ros.typestore().types
               for n in files)
