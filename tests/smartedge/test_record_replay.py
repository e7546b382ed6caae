"""``smartedge record`` / ``smartedge replay``: live traffic into MCAP and back.

The live run: the simulated site publishes detections and odometry in real time to a real
``smartedge backend`` process, while ``smartedge record`` captures every key (inputs and the
backend's estimates). Offline, the backend's one pipeline fed with the recorded inputs at their
recorded receive times gives the estimates the live backend published."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mcap")
pytest.importorskip("gtsam")

from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig
from core.session import loopback_config
from lab.launcher import ServiceProcess, start_service
from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import Odometry, PoseEstimate, RobotDetections
from simulation.publisher import publish_run
from simulation.runner import SimulationRun
from simulation.scenario import load_scenario
from smartedge.commands.record import Recorder, RecordingError, read_recording, replay_main
from tests.conftest import free_port, wait_until

SITE_FILE = Path(__file__).resolve().parents[2] / "simulation" / "sites" / "paper_lab.yaml"
#: simulated seconds published live (10 s: 600 detections, 200 odometry, 146 camera poses, all
#: 146 matched offline, 11 statuses; was 14 s)
SIM_S = 10.0


def _stop(proc: ServiceProcess) -> None:
    assert proc.stop(timeout_s=30.0) == 0, proc.log_tail()


@pytest.fixture(scope="module")
def live_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    import zenoh

    tmp = tmp_path_factory.mktemp("record")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    zargs = ["--mode", "client", "--connect", endpoint, "--no-multicast-scouting"]
    hub = zenoh.open(loopback_config(listen=[endpoint]))
    site = load_scenario().site.name
    statuses: list[bytes] = []
    pose_stamps_ns: list[int] = []
    hub.declare_subscriber(keys.status_key(site, "backend", "*"),
                           lambda s: statuses.append(s.payload.to_bytes()))
    hub.declare_subscriber(keys.camera_pose_key(site, "*"),
                           lambda s: pose_stamps_ns.append(decode(s.payload.to_bytes()).stamp_ns))
    # only the recorder (it takes smartedge/**) subscribes to this key; nothing is put on it
    recorder_probe = hub.declare_publisher(f"{keys.ROOT}/{site}/test_probe/recorder_ready")
    try:
        backend = start_service(["backend", "--site", str(SITE_FILE), *zargs], tmp / "backend.log")
        recorder = start_service(["record", str(tmp / "live.mcap"), *zargs], tmp / "record.log")
        # sessions open, subscriptions declared (was a fixed 3 s): the backend publishes its
        # status (after its subscriptions), the recorder's subscription reached the hub
        assert wait_until(lambda: bool(statuses), 60, 0.05), (tmp / "backend.log").read_text()
        assert wait_until(lambda: recorder_probe.matching_status.matching, 30, 0.05), (
            tmp / "record.log").read_text()
        time.sleep(0.2)
        sc = load_scenario()
        # stamps on the wall clock: publish_run paces arrivals from start_stamp_ns at speed 1
        sc = sc.with_overrides(start_stamp_ns=time.time_ns())
        run = SimulationRun(sc, "traj3", seed=3)
        publish_run(hub, run, speed=1.0, accept_corrections=False, until_s=SIM_S)
        # the last frame-sets and estimates (was a fixed 1.5 s): a camera pose of the last
        # 0.2 s, at most 1.5 s, then the recorder's share of the hub's routing
        last_ns = sc.start_stamp_ns + round((SIM_S - 0.2) * 1e9)
        wait_until(lambda: any(t >= last_ns for t in pose_stamps_ns), 1.5, 0.05)
        time.sleep(0.3)
        _stop(recorder)
        _stop(backend)
    finally:
        hub.close()
    assert "recorded" in (tmp / "record.log").read_text()
    return tmp / "live.mcap"


def test_recording_holds_inputs_and_outputs(live_recording: Path) -> None:
    counts: dict[str, int] = {}
    last_receive = 0
    for key, receive_ns, payload in read_recording(live_recording):
        assert receive_ns >= last_receive  # receive order
        last_receive = receive_ns
        topic = keys.parse_key(key).topic
        counts[topic] = counts.get(topic, 0) + 1
        decode(payload)  # every payload is a valid message
    assert counts["detections"] > 4 * 15 * SIM_S * 0.8  # 4 cameras at 15 Hz
    assert counts["odom"] > 20 * SIM_S * 0.8
    assert counts["camera_pose"] > 20 and counts["backend"] >= 5  # estimates, status


def test_every_channel_of_the_live_recording_decodes_as_ros2(live_recording: Path) -> None:
    """The recording ``smartedge record`` wrote during the live run: an independent decoder
    (``mcap-ros2-support``) reads every channel, each key has its typed and its wire channel."""
    decoder = pytest.importorskip("mcap_ros2.decoder")
    from mcap.reader import make_reader

    from smartedge import record_ros

    per_topic: dict[str, tuple[str, int]] = {}
    with live_recording.open("rb") as f:
        reader = make_reader(f, decoder_factories=[decoder.DecoderFactory()])
        for schema, channel, _message, obj in reader.iter_decoded_messages():
            assert obj is not None
            name, n = per_topic.get(channel.topic, (schema.name, 0))
            per_topic[channel.topic] = (name, n + 1)
    keys_seen = {key for key, _, _ in read_recording(live_recording)}
    for key in keys_seen:
        wire_name, n_wire = per_topic[record_ros.wire_topic(key)]
        assert wire_name == record_ros.WIRE_TYPE
        typed_name, n_typed = per_topic[record_ros.ros_topic(key)]
        assert typed_name in record_ros.ROS_TYPES.values(), typed_name
        assert n_typed == n_wire, key  # every payload decoded and converted
    names = {name for name, _ in per_topic.values()}
    assert {"smartedge_msgs/msg/RobotDetections", "nav_msgs/msg/Odometry",
            "geometry_msgs/msg/PoseWithCovarianceStamped",
            "diagnostic_msgs/msg/DiagnosticArray"} <= names, names


def test_offline_pipeline_on_the_recording_gives_the_live_estimates(live_recording: Path) -> None:
    sc = load_scenario()
    pipeline = BackendPipeline(sc.site, PipelineConfig.from_site(sc.site))
    offline: list[PoseEstimate] = []
    live: list[PoseEstimate] = []
    for key, receive_ns, payload in read_recording(live_recording):
        msg = decode(payload)
        if isinstance(msg, (RobotDetections, Odometry)):
            offline += pipeline.step(msg, receive_ns).camera
        elif key.endswith("/camera_pose"):
            live.append(msg)
    offline += pipeline.flush().camera
    by_stamp = {(e.stamp_ns, "multi_frame" in e.flags): e for e in offline}
    matched = 0
    for e in live:
        twin = by_stamp.get((e.stamp_ns, "multi_frame" in e.flags))
        if twin is None:
            continue
        matched += 1
        # the same estimate: the solver stops within its tolerance, and a prior that differs
        # in the last digits (the fused pose at a receive time a little apart) moves where it
        # stops by nanometres (seen: 2e-9 rad): 0.1 um / 0.1 urad is still the same solve
        np.testing.assert_allclose([twin.x, twin.y, twin.theta], [e.x, e.y, e.theta],
                                   rtol=0.0, atol=1e-7)
    # the receive times of the recorder and the backend differ by a millisecond or so; a
    # frame-set closed by its wait timeout may then differ, nothing else
    assert len(live) > 20 and matched >= 0.9 * len(live), (matched, len(live))


def test_replay_publishes_the_recording_back(tmp_path: Path) -> None:
    import zenoh

    rec = Recorder(tmp_path / "small.mcap")
    site, robot = "paper_lab", "hsr"
    sent = []
    for k in range(20):
        msg = Odometry(robot, 1_000_000_000 + k * 50_000_000, k, 0.01 * k, 0.0, 0.0,
                       covariance=np.eye(3) * 1e-4)
        payload = encode(msg)
        sent.append(payload)
        rec.write(keys.odom_key(site, robot), payload, 5_000_000_000 + k * 1_000_000)
    rec.close()
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    got: list[bytes] = []
    with zenoh.open(loopback_config(listen=[endpoint])) as listener:
        listener.declare_subscriber(keys.odom_key(site, robot),
                                    lambda s: got.append(s.payload.to_bytes()))
        time.sleep(0.3)
        done = threading.Event()

        def replay() -> None:
            replay_main([str(tmp_path / "small.mcap"), "--rate", "0", "--mode", "client",
                         "--connect", endpoint, "--no-multicast-scouting"])
            done.set()

        threading.Thread(target=replay, daemon=True).start()
        assert done.wait(20)
        deadline = time.monotonic() + 5
        while len(got) < len(sent) and time.monotonic() < deadline:
            time.sleep(0.05)
    assert got == sent


def test_damaged_recordings_give_a_clear_error(tmp_path: Path, capsys) -> None:
    rec = Recorder(tmp_path / "a.mcap")
    for k in range(200):
        rec.write("smartedge/lab/robot/hsr/odom", bytes(300), 10**9 + k)
    rec.close()
    data = (tmp_path / "a.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(RecordingError, match=r"cut\.mcap: not a complete MCAP recording"):
        list(read_recording(tmp_path / "cut.mcap"))
    (tmp_path / "junk.mcap").write_bytes(b"not an mcap file at all" * 10)
    with pytest.raises(RecordingError, match=r"junk\.mcap"):
        list(read_recording(tmp_path / "junk.mcap"))
    with pytest.raises(RecordingError, match="no such recording"):
        list(read_recording(tmp_path / "missing.mcap"))
    assert replay_main([str(tmp_path / "cut.mcap")]) == 1
    assert "not a complete MCAP recording" in capsys.readouterr().err
    # the undamaged file reads completely, undecodable payloads included
    assert len(list(read_recording(tmp_path / "a.mcap"))) == 200
