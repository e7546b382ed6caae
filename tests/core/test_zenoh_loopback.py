"""Two real Zenoh sessions on loopback: every message type arrives intact; liveliness works."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from protocol import decode, encode, keys
from protocol.messages import (
    Detection,
    Odometry,
    PoseCorrection,
    PoseEstimate,
    RobotDetections,
    ServiceStatus,
)
from tests.conftest import wait_until
from tests.protocol.strategies import sample_cloud, sample_odometry

zenoh = pytest.importorskip("zenoh")

SITE = "testsite"


def _messages() -> list[tuple[str, object]]:
    det = Detection(
        np.array([10.0, 20, 110, 220]),
        0.93,
        np.random.default_rng(0).random((12, 2)) * 400,
        np.linspace(0, 1, 12),
    )
    cov = np.diag([1e-4, 1e-4, 1e-3])
    return [
        (
            keys.detections_key(SITE, "cam_a"),
            RobotDetections("cam_a", 11, 0, 848, 480, "m1", (det,)),
        ),
        (keys.edge_cloud_key(SITE, "cam_a"), sample_cloud(100_000)),
        (keys.odom_key(SITE, "hsr"), sample_odometry()),
        (keys.robot_cloud_key(SITE, "hsr"), sample_cloud(10, seed=3)),
        (
            keys.pose_key(SITE, "hsr"),
            PoseEstimate("hsr", 12, 0, 1.0, 2.0, 0.3, cov, "fused", ("cam_a", "cam_b")),
        ),
        (
            keys.correction_key(SITE, "hsr"),
            PoseCorrection("hsr", 13, 0, 1.0, 2.0, 0.3, cov, "initialization", 0.4, 0.1),
        ),
        (
            keys.status_key(SITE, "backend", "main"),
            ServiceStatus(
                "backend", "main", 14, 0, counters={"invalid": 2}, rates_hz={"pose": 30.0}
            ),
        ),
    ]


def test_every_message_type_crosses_zenoh_intact(zenoh_pair) -> None:
    a, b, _ = zenoh_pair
    received: dict[str, bytes] = {}
    lock = threading.Lock()

    def on_sample(sample) -> None:  # Zenoh thread: just hand the bytes over
        with lock:
            received[str(sample.key_expr)] = sample.payload.to_bytes()

    sub = b.declare_subscriber(f"{keys.ROOT}/{SITE}/**", on_sample)
    messages = _messages()
    pub_opts = {
        "encoding": zenoh.Encoding("application/msgpack"),
        "congestion_control": zenoh.CongestionControl.BLOCK,
        "reliability": zenoh.Reliability.RELIABLE,
    }
    publishers = {key: a.declare_publisher(key, **pub_opts) for key, _ in messages}

    def all_arrived() -> bool:
        for key, msg in messages:
            if key not in received:
                publishers[key].put(encode(msg))
        with lock:
            return len(received) == len(messages)

    assert wait_until(all_arrived, timeout_s=10.0, step_s=0.2)
    for key, msg in messages:
        back = decode(received[key], expected=keys.parse_key(key).message_type)
        assert back == msg
    sub.undeclare()


def test_liveliness_token_appears_and_disappears(zenoh_pair) -> None:
    a, b, _ = zenoh_pair
    events: list[tuple[str, str]] = []
    token_key = keys.alive_key(SITE, "edge-agent", "cam_a")

    def on_change(sample) -> None:
        events.append((str(sample.kind), str(sample.key_expr)))

    sub = b.liveliness().declare_subscriber(keys.alive_key(SITE, "*", "*"), on_change, history=True)
    token = a.liveliness().declare_token(token_key)
    assert wait_until(lambda: any("PUT" in k and key == token_key for k, key in events))
    token.undeclare()
    assert wait_until(lambda: any("DELETE" in k and key == token_key for k, key in events))
    sub.undeclare()


def test_odometry_survives_a_burst_with_block_congestion_control(zenoh_pair) -> None:
    a, b, _ = zenoh_pair
    got: list[bytes] = []
    sub = b.declare_subscriber(
        keys.odom_key(SITE, "hsr"), lambda s: got.append(s.payload.to_bytes())
    )
    pub = a.declare_publisher(
        keys.odom_key(SITE, "hsr"),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    # let the subscription propagate before the burst
    probe = Odometry("hsr", 0, 0, 0.0, 0.0, 0.0)
    assert wait_until(lambda: (pub.put(encode(probe)), bool(got))[1], timeout_s=10, step_s=0.1)
    got.clear()
    for i in range(2000):
        pub.put(encode(Odometry("hsr", i + 1, i + 1, float(i), 0.0, 0.0)))
    assert wait_until(lambda: len(got) >= 2000, timeout_s=10)
    seqs = [seq for seq in (decode(p).seq for p in got) if seq > 0]  # drop late probes
    assert seqs == list(range(1, 2001))
    sub.undeclare()
