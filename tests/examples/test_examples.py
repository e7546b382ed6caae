"""The scripts in ``examples/``: each runs as a subprocess (``python examples/X.py ...``)
against the real stack (the example site, real Zenoh on loopback, a real MCAP recording, a real
map file), and its printed numbers are checked against what was put in.

Zenoh: the test holds a listening peer on a free loopback port with scouting off; the example
connects to it in client mode, so it never listens on the default port of a running system."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

import protocol
from core.geometry import se3_from_planar
from core.session import loopback_config
from core.site import load_site
from protocol import keys
from tests.conftest import EXAMPLE_SITE, REPO_ROOT, free_port, wait_until

zenoh = pytest.importorskip("zenoh")

EXAMPLES_DIR = REPO_ROOT / "examples"
T0_NS = 1_700_000_000_000_000_000
#: a float printed by an example, e.g. ``x=10.002``
NUMBER = r"(-?\d+(?:\.\d+)?)"


def example(name: str) -> list[str]:
    """The command line that runs ``examples/<name>`` with this interpreter."""
    return [sys.executable, str(EXAMPLES_DIR / name)]


def run(argv: list[str], timeout_s: float = 30.0) -> str:
    """Run an example to its end; its stdout (it must exit 0)."""
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, env=_env(),
                          cwd=REPO_ROOT)
    assert proc.returncode == 0, f"{argv}: exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("ZENOH_CONFIG", None)  # the examples' zenoh flags alone decide
    return env


def client_args(endpoint: str) -> list[str]:
    return ["--mode", "client", "--connect", endpoint]


@pytest.fixture
def hub() -> Iterator[tuple[zenoh.Session, str]]:
    """A listening Zenoh peer on a free loopback port (scouting off) and its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(loopback_config(listen=[endpoint])) as session:
        yield session, endpoint


# ----------------------------------------------------------------------------------------------


def test_solve_pose_finds_the_true_pose() -> None:
    out = run([*example("solve_pose.py"), "--x-m", "9.4", "--y-m", "6.7", "--theta-deg", "-70",
               "--noise-px", "1.0", "--seed", "4"])
    assert "cam_ne, cam_nw, cam_se, cam_sw" in out  # every camera of the site sees it
    x_m, y_m, theta_deg = map(float, re.search(
        rf"pose:\s+x={NUMBER} m\s+y={NUMBER} m\s+theta={NUMBER} deg", out).groups())
    assert math.hypot(x_m - 9.4, y_m - 6.7) < 0.05
    assert abs(theta_deg + 70.0) < 2.0
    std_x_cm, std_y_cm, std_theta_deg = map(float, re.search(
        rf"std:\s+x={NUMBER} cm\s+y={NUMBER} cm\s+theta={NUMBER} deg", out).groups())
    assert 0.1 < std_x_cm < 5.0 and 0.1 < std_y_cm < 5.0 and 0.05 < std_theta_deg < 3.0
    error_cm, error_deg = map(float, re.search(rf"error: {NUMBER} cm\s+\+?{NUMBER} deg",
                                               out).groups())
    assert error_cm == pytest.approx(100 * math.hypot(x_m - 9.4, y_m - 6.7), abs=0.06)
    assert error_deg == pytest.approx(theta_deg + 70.0, abs=0.02)


def test_publish_detections_puts_each_frame_on_the_camera_key(hub) -> None:
    session, endpoint = hub
    received: list[tuple[str, protocol.Message]] = []
    subscriber = session.declare_subscriber(
        "smartedge/**", lambda s: received.append((str(s.key_expr),
                                                   protocol.decode(s.payload.to_bytes()))))
    count, rate_hz = 8, 20.0
    out = run([*example("publish_detections.py"), "--camera", "cam_se", "--count", str(count),
               "--rate-hz", str(rate_hz), "--x-m", "10.5", "--y-m", "5.5", "--theta-deg", "90",
               *client_args(endpoint)])
    assert wait_until(lambda: len(received) >= count, 3.0)
    subscriber.undeclare()
    assert out.count("put seq=") == count
    assert {key for key, _ in received} == {keys.detections_key("lab", "cam_se")}
    messages = [msg for _, msg in received]
    assert [m.seq for m in messages] == list(range(count))
    stamps_ns = np.array([m.stamp_ns for m in messages])
    assert (np.diff(stamps_ns) > 0).all()
    # paced at the rate asked (on a schedule: a late frame is followed by a quicker one)
    assert stamps_ns[-1] - stamps_ns[0] > 0.9e9 * (count - 1) / rate_hz
    # the keypoints are where the camera sees the robot's keypoints (1 px noise)
    site = load_site(EXAMPLE_SITE)
    T = se3_from_planar(10.5, 5.5, math.radians(90.0))
    kp_world = site.robot_model("hsr").keypoints_base_m @ T[:3, :3].T + T[:3, 3]
    uv_true, _ = site.camera("cam_se").project(kp_world)
    for msg in messages:
        assert (msg.camera_id, msg.image_width, msg.image_height) == ("cam_se", 848, 480)
        (det,) = msg.detections
        assert det.keypoint_scores.tolist() == [1.0] * 12
        assert np.abs(det.keypoints_px - uv_true).max() < 6.0


def test_subscribe_pose_prints_the_published_poses(hub) -> None:
    session, endpoint = hub
    proc = subprocess.Popen([*example("subscribe_pose.py"), "--count", "4", "--timeout-s", "10",
                             *client_args(endpoint)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=_env(), cwd=REPO_ROOT)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")),
                              daemon=True)
    reader.start()
    try:
        publisher = session.declare_publisher(keys.pose_key("lab", "hsr"))
        assert wait_until(lambda: publisher.matching_status.matching, 15.0), lines
        publisher.put(b"\x00 not msgpack")  # skipped and said so, as is a wrong type
        publisher.put(protocol.encode(protocol.Odometry("hsr", T0_NS, 0, 0.0, 0.0, 0.0)))
        cov = np.diag([0.02**2, 0.03**2, math.radians(1.0) ** 2])
        for seq in range(4):
            publisher.put(protocol.encode(protocol.PoseEstimate(
                robot_id="hsr", stamp_ns=T0_NS + seq * 20_000_000, seq=seq, x=1.0 + 0.25 * seq,
                y=-2.0 + 0.125 * seq, theta=math.radians(10.0 * seq), covariance=cov,
                source="fused")))
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    reader.join(5)
    out = "".join(lines)
    assert "subscribed to smartedge/lab/robot/hsr/pose" in out
    assert out.count("undecodable message on smartedge/lab/robot/hsr/pose") == 2
    poses = re.findall(rf"seq=(\d+) stamp_ns=(\d+) x={NUMBER} m y={NUMBER} m theta={NUMBER} deg "
                       rf"std={NUMBER} cm source=fused", out)
    assert [(int(s), int(t), float(x), float(y), float(th), float(std))
            for s, t, x, y, th, std in poses] == [
        (seq, T0_NS + seq * 20_000_000, 1.0 + 0.25 * seq, -2.0 + 0.125 * seq, 10.0 * seq,
         round(100 * math.hypot(0.02, 0.03), 1)) for seq in range(4)]


def test_subscribe_pose_stops_after_its_timeout(hub) -> None:
    _, endpoint = hub
    t0 = time.monotonic()
    proc = subprocess.run([*example("subscribe_pose.py"), "--count", "3", "--timeout-s", "0.5",
                           *client_args(endpoint)], capture_output=True, text=True, timeout=30,
                          env=_env(), cwd=REPO_ROOT)
    assert "no pose for 0.5 s: stopping" in proc.stdout and "seq=" not in proc.stdout
    assert proc.returncode == 1, proc.stdout + proc.stderr  # no pose at all: a failure
    assert time.monotonic() - t0 < 20.0


def test_read_recording_counts_every_channel(tmp_path: Path) -> None:
    from smartedge.commands.record import Recorder  # the writer of `smartedge record`

    site = load_site(EXAMPLE_SITE)
    cov = np.diag([1e-4, 1e-4, 1e-4])
    samples: list[tuple[str, bytes]] = []  # (key, payload) in receive order
    for seq in range(6):
        stamp_ns = T0_NS + seq * 50_000_000
        for camera_id in ("cam_sw", "cam_se")[: 1 + seq % 2]:  # cam_se every other frame
            cam = site.camera(camera_id)
            msg = protocol.RobotDetections(camera_id, stamp_ns, seq, cam.width, cam.height,
                                           "test-model")
            samples.append((keys.detections_key("lab", camera_id), protocol.encode(msg)))
        pose = protocol.PoseEstimate("hsr", stamp_ns, seq, 2.0 + 0.5 * seq, 3.0,
                                     math.radians(-45.0), cov, "fused")
        samples.append((keys.pose_key("lab", "hsr"), protocol.encode(pose)))
    samples.append((keys.pose_key("lab", "hsr"), b"garbage"))  # recorded as it came
    recorder = Recorder(tmp_path / "run.mcap")
    for i, (key, payload) in enumerate(samples):
        recorder.write(key, payload, receive_ns=T0_NS + i * 100_000_000)
    recorder.close()

    out = run([*example("read_recording.py"), str(tmp_path / "run.mcap"), "--poses", "3"])
    # 6 + 3 detections, 6 poses and the garbage; 15 steps of 0.1 s between the receive times
    assert f"{tmp_path / 'run.mcap'}: 16 messages on 3 keys over 1.5 s" in out
    assert re.search(r"\s6\s+smartedge/lab/edge/cam_sw/detections\n", out)
    assert re.search(r"\s3\s+smartedge/lab/edge/cam_se/detections\n", out)
    assert re.search(r"\s7\s+smartedge/lab/robot/hsr/pose\n", out)
    assert "first 3 poses:" in out
    printed = re.findall(rf"stamp_ns=(\d+) x={NUMBER} m y={NUMBER} m theta={NUMBER} deg", out)
    assert [(int(t), float(x), float(y), float(th)) for t, x, y, th in printed] == [
        (T0_NS + seq * 50_000_000, 2.0 + 0.5 * seq, 3.0, -45.0) for seq in range(3)]


def test_read_recording_names_a_file_that_is_not_mcap(tmp_path: Path) -> None:
    bad = tmp_path / "not.mcap"
    bad.write_bytes(b"not an mcap file")
    proc = subprocess.run([*example("read_recording.py"), str(bad)], capture_output=True,
                          text=True, timeout=30, env=_env(), cwd=REPO_ROOT)
    assert proc.returncode == 1
    assert proc.stderr.startswith(f"error: {bad}: ") and "Traceback" not in proc.stderr


def test_load_map_counts_the_voxels_of_each_class(tmp_path: Path) -> None:
    from mapper.map_io import save_map_npz
    from mapper.mapping import MappingConfig, SemanticMapping
    from mapper.semantic_map import SemanticMapConfig
    from protocol.semantic_classes import SEMANTIC_CLASS_ID

    site = load_site(EXAMPLE_SITE)
    # one 0.1 m voxel per point: the points sit at voxel centres, away from the faces
    floor = np.array([[2.05 + 0.1 * i, 1.05 + 0.1 * j, 0.05] for i in range(10) for j in range(10)])
    table = np.array([[2.25 + 0.1 * i, 1.25 + 0.1 * j, 0.75] for i in range(4) for j in range(2)])
    points = np.concatenate([floor, table]).astype(np.float32)
    class_ids = np.array([SEMANTIC_CLASS_ID["floor"]] * 100 + [SEMANTIC_CLASS_ID["table"]] * 8,
                         dtype=np.uint16)
    mapping = SemanticMapping(site, MappingConfig(map=SemanticMapConfig(voxel_size_m=0.1)))
    cloud = protocol.SemanticCloud(
        "cam_sw", T0_NS, 0, site.world_frame, points, class_ids,
        np.full(len(points), 0.9, dtype=np.float32), site.camera("cam_sw").T_world_cam.copy())
    outcome = mapping.on_cloud(cloud, "edge", "cam_sw", now_ns=T0_NS)
    assert outcome.accepted, outcome.reason
    save_map_npz(mapping.map, tmp_path / "map.npz")

    out = run([*example("load_map.py"), str(tmp_path / "map.npz")])
    assert "108 voxels of 0.1 m, 108 with semantics" in out
    assert re.search(r"floor\s+100 voxels", out) and re.search(r"table\s+8 voxels", out)
    assert ("bounding box (world frame): x [2.00, 3.00] m  y [1.00, 2.00] m  z [0.00, 0.80] m"
            in out)


def test_every_example_is_run_by_a_test_and_listed() -> None:
    scripts = {p.name for p in EXAMPLES_DIR.glob("*.py")}
    assert len(scripts) >= 5
    run_here = set(re.findall(r'example\("(\w+\.py)"\)', Path(__file__).read_text()))
    assert scripts <= run_here, f"examples no test runs: {sorted(scripts - run_here)}"
    readme = (EXAMPLES_DIR / "README.md").read_text()
    assert all(f"examples/{name}" in readme for name in scripts), "examples/README.md"


def _start_example(argv: list[str]) -> tuple[subprocess.Popen, list[str], threading.Thread]:
    """An example as a process whose output lines are collected as they come."""
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=_env(), cwd=REPO_ROOT)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(iter(proc.stdout.readline, "")),
                              daemon=True)
    reader.start()
    return proc, lines, reader


def _stop_example(proc: subprocess.Popen, reader: threading.Thread) -> int:
    from tests.conftest import stop_process

    code = stop_process(proc, timeout_s=20.0)
    reader.join(5)
    return code


def test_robot_adapter_robot_is_initialized_from_the_backends_pose(hub) -> None:
    """The example's robot starts lost: the bridge publishes its odometry and a lost
    localization, and once fused poses of the backend arrive while it stands still the bridge
    hands the adapter an initial pose, which the robot's localization then reports."""
    session, endpoint = hub
    odometry: list[protocol.Odometry] = []
    localization: list[protocol.PoseEstimate] = []
    subs = [
        session.declare_subscriber(keys.robot_key("lab", "hsr", "odom"), lambda s: odometry.append(
            protocol.decode(s.payload.to_bytes(), protocol.Odometry))),
        session.declare_subscriber(keys.robot_key("lab", "hsr", "localization"),
                                   lambda s: localization.append(
                                       protocol.decode(s.payload.to_bytes(),
                                                       protocol.PoseEstimate))),
    ]
    proc, lines, reader = _start_example(
        [*example("robot_adapter.py"), "--site", str(EXAMPLE_SITE), "--robot", "hsr",
         "--adapter", "wheels", "--wheels-start", "10.5", "5.5", "90", *client_args(endpoint)])
    try:
        assert wait_until(lambda: len(odometry) >= 5 or proc.poll() is not None, 30.0), lines
        assert proc.poll() is None, "".join(lines)
        pose_pub = session.declare_publisher(keys.pose_key("lab", "hsr"))
        status_pub = session.declare_publisher(keys.status_key("lab", "backend", "main"))
        cov = np.diag([0.01**2, 0.01**2, math.radians(0.5) ** 2])
        rng = np.random.default_rng(0)

        def initialized() -> bool:
            now = time.time_ns()
            status_pub.put(protocol.encode(protocol.ServiceStatus("backend", "main", now, 0)))
            pose_pub.put(protocol.encode(protocol.PoseEstimate(
                "hsr", now, len(lines), 10.5 + rng.normal(0, 0.005), 5.5 + rng.normal(0, 0.005),
                math.radians(90.0), cov, "fused", ("cam_sw", "cam_se"))))
            return any(line.startswith("initialization: pose set to") for line in lines)

        assert wait_until(initialized, 30.0, 0.1), "".join(lines)[-3000:]
        x, y, theta = map(float, re.search(
            rf"initialization: pose set to x={NUMBER} m y={NUMBER} m theta={NUMBER} deg",
            "".join(lines)).groups())
        assert math.hypot(x - 10.5, y - 5.5) < 0.03 and abs(theta - 90.0) < 1.0
        # the robot now knows where it is: its localization says so, not lost
        n = len(localization)
        assert wait_until(lambda: len(localization) > n + 2, 10.0)
        last = localization[-1]
        assert math.hypot(last.x - x, last.y - y) < 1e-3
    finally:
        code = _stop_example(proc, reader)
        for sub in subs:
            sub.undeclare()
    assert code == 0, "".join(lines)[-3000:]
    assert all(o.robot_id == "hsr" for o in odometry)
    assert [o.seq for o in odometry] == sorted(o.seq for o in odometry)


@pytest.mark.slow
def test_frame_source_runs_rendered_frames_through_the_shipped_networks(
        hub, tmp_path: Path) -> None:
    """``--source vendor`` of the example on rendered images of cam1 with the robot in view:
    the edge agent publishes detections whose box holds the robot's true keypoints."""
    pytest.importorskip("moderngl")
    pytest.importorskip("onnxruntime")
    import cv2

    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=11)
    folder = tmp_path / "frames"
    folder.mkdir()
    truth: list[np.ndarray] = []
    i = 0
    while len(truth) < 3 and i < 400:
        s = gen(i)
        i += 1
        r = s.robots[0]
        if s.camera.camera_id != "cam1" or r.bbox_xyxy is None or r.in_image.sum() < 8 or \
                (r.bbox_xyxy[3] - r.bbox_xyxy[1]) < 40:
            continue
        cv2.imwrite(str(folder / f"{len(truth):03d}.png"), s.image_rgb[..., ::-1])
        truth.append(np.asarray(r.bbox_xyxy, float))
    assert len(truth) == 3
    session, endpoint = hub
    received: list[protocol.RobotDetections] = []
    sub = session.declare_subscriber(
        keys.detections_key("paper_lab", "cam1"),
        lambda s: received.append(protocol.decode(s.payload.to_bytes(), protocol.RobotDetections)))
    proc, lines, reader = _start_example(
        [*example("frame_source.py"), "--site",
         str(REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"), "--camera", "cam1",
         "--source", "vendor", "--vendor-folder", str(folder), "--vendor-rate", "4",
         "--threads", "1", *client_args(endpoint)])
    try:
        assert wait_until(lambda: len(received) >= 6 or proc.poll() is not None, 90.0, 0.1), \
            "".join(lines)[-3000:]
    finally:
        code = _stop_example(proc, reader)
        sub.undeclare()
    assert code == 0, "".join(lines)[-3000:]
    from edge_agent.boxes import box_iou

    for msg in received:
        assert (msg.image_width, msg.image_height) == (848, 480)
    # every image shows the robot: its box is found in (nearly) every published frame
    hits = [any(max(box_iou(d.bbox_xyxy, t) for t in truth) >= 0.5 for d in msg.detections)
            for msg in received]
    assert sum(hits) >= len(received) - 1, hits
