"""A service fed garbage bytes on every key it subscribes to keeps running and counts them."""

from __future__ import annotations

import argparse
import math
import threading
import time

import msgpack
import numpy as np
import pytest

from core.runtime import ZenohRunner
from core.session import loopback_config
from protocol import decode, encode, keys
from protocol.messages import Odometry, PoseEstimate, RobotDetections, ServiceStatus
from tests.conftest import free_port, wait_until

zenoh = pytest.importorskip("zenoh")

GARBAGE = [
    b"",
    b"\xc1",
    bytes(range(256)),
    msgpack.packb({"schema": "RobotDetections", "schema_version": 1, "camera_id": "cam1"}),
    msgpack.packb({"schema": "Odometry", "schema_version": 7}),
    msgpack.packb(
        {
            "schema": "SemanticCloud",
            "schema_version": 1,
            "sensor_id": "x",
            "points_xyz": {"dtype": "<f4", "shape": [10**9, 3], "data": b""},
        }
    ),
    msgpack.packb([1, 2, 3]),
    b"\x91" * 50_000 + b"\xc0",
    msgpack.packb(
        {
            "schema": "Odometry",
            "schema_version": 1,
            "robot_id": "hsr",
            "stamp_ns": 1,
            "seq": 0,
            "x": math.nan,
            "y": 0.0,
            "theta": 0.0,
        }
    ),
]


def _concrete(key_expr: str) -> str:
    return key_expr.replace("**", "x").replace("*", "cam1" if "/edge/" in key_expr else "hsr")


def _run(node) -> tuple[ZenohRunner, threading.Thread, str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    assert runner.started.wait(20)
    return runner, thread, endpoint


def _attack(session, node) -> int:
    """Publish every garbage payload (and one wrong-type message) on every subscribed key."""
    sent = 0
    status = encode(ServiceStatus("backend", "x", 1, 0))
    odometry = encode(Odometry("hsr", 1, 0, 0.0, 0.0, 0.0))
    for sub in node.subscriptions():
        if sub.liveliness:
            continue
        wrong_type = odometry if sub.message_type is ServiceStatus else status
        for payload in [*GARBAGE, wrong_type]:
            session.put(
                _concrete(sub.key_expr), payload, congestion_control=zenoh.CongestionControl.BLOCK
            )
            sent += 1
    return sent


def test_backend_survives_garbage_on_every_key(tmp_path) -> None:
    from backend_service.service import build_node
    from simulation.detections import DetectionSimulator
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    args = argparse.Namespace(
        site=scenario.site.source_path,
        id="main",
        solver=None,
        robust_loss="huber",
    )
    node = build_node(args)
    runner, thread, endpoint = _run(node)
    statuses: list[ServiceStatus] = []
    poses: list[PoseEstimate] = []
    with zenoh.open(loopback_config(connect=[endpoint])) as client:
        client.declare_subscriber(
            keys.status_key(node.site, "backend", "*"),
            lambda s: statuses.append(decode(s.payload.to_bytes())),
        )
        client.declare_subscriber(
            keys.camera_pose_key(node.site, "*"),
            lambda s: poses.append(decode(s.payload.to_bytes())),
        )
        assert wait_until(lambda: bool(statuses), 10)
        time.sleep(0.5)
        sent = _attack(client, node)
        assert wait_until(lambda: statuses[-1].counters.get("invalid", 0) >= sent, 15), (
            sent,
            statuses[-1].counters,
        )
        assert thread.is_alive()
        # and it still does its job: real detections of the robot at WP2 give a camera pose
        sim = DetectionSimulator(scenario)
        rng = np.random.default_rng(0)
        wp = scenario.waypoints["WP2"]
        stamp = time.time_ns()
        for i, cam in enumerate(sorted(scenario.site.cameras)):
            msg: RobotDetections = sim.detect(cam, stamp, np.array([wp.x, wp.y, wp.theta]), i, rng)
            client.put(keys.detections_key(node.site, cam), encode(msg))
        assert wait_until(lambda: bool(poses), 10)
        assert math.hypot(poses[0].x - wp.x, poses[0].y - wp.y) < 0.1
    runner.stop()
    thread.join(20)
    assert not thread.is_alive()


def test_robot_bridge_survives_garbage_on_every_key() -> None:
    from robot_bridge.service import build_node, build_parser
    from smartedge.simulated_site import register_simulation

    register_simulation()
    args = build_parser().parse_args(["--adapter", "sim", "--sim-epoch-ns", str(time.time_ns())])
    node = build_node(args)
    runner, thread, endpoint = _run(node)
    statuses: list[ServiceStatus] = []
    odometry: list[Odometry] = []
    with zenoh.open(loopback_config(connect=[endpoint])) as client:
        client.declare_subscriber(
            keys.status_key(node.site, "robot-bridge", "*"),
            lambda s: statuses.append(decode(s.payload.to_bytes())),
        )
        client.declare_subscriber(
            keys.odom_key(node.site, "*"), lambda s: odometry.append(decode(s.payload.to_bytes()))
        )
        assert wait_until(lambda: bool(statuses) and bool(odometry), 10)
        sent = _attack(client, node)
        assert wait_until(lambda: statuses[-1].counters.get("invalid", 0) >= sent, 15), (
            sent,
            statuses[-1].counters,
        )
        n = len(odometry)
        assert wait_until(lambda: len(odometry) > n + 10, 5), "odometry stopped flowing"
        assert thread.is_alive()
    runner.stop()
    thread.join(20)
    assert not thread.is_alive()
