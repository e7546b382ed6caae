"""The service runtime: a node behind real Zenoh keeps running on garbage and reports status."""

from __future__ import annotations

import threading

import pytest

from protocol import Odometry, PoseEstimate, ServiceStatus, decode, encode, keys
from protocol.runtime import Outgoing, ScriptedRunner, ServiceNode, Subscription, ZenohRunner
from tests.conftest import free_port, wait_until

zenoh = pytest.importorskip("zenoh")
SITE = "rt"


class EchoNode(ServiceNode):
    """Turns each odometry message into a PoseEstimate (so the output proves the input)."""

    service = "backend"

    def subscriptions(self):
        return [Subscription(keys.odom_key(SITE, "*"), Odometry)]

    def handle(self, key, message, recv_ns):
        if message.x < 0:
            raise RuntimeError("node bug")  # must be contained and counted
        est = PoseEstimate(
            message.robot_id,
            message.stamp_ns,
            message.seq,
            message.x,
            message.y,
            message.theta,
            message.covariance,
            "fused",
        )
        return [Outgoing(keys.pose_key(SITE, message.robot_id), est)]


def test_scripted_runner_counts_invalid_and_handler_errors() -> None:
    runner = ScriptedRunner(EchoNode(SITE, "main"))
    key = keys.odom_key(SITE, "hsr")
    assert runner.feed(key, b"\x00garbage") == []
    assert (
        runner.feed(key, encode(PoseEstimate("hsr", 1, 0, 0.0, 0.0, 0.0, [[0] * 3] * 3, "fused")))
        == []
    )  # wrong type on the key
    assert runner.feed(key, encode(Odometry("hsr", 1, 0, -1.0, 0.0, 0.0))) == []
    out = runner.feed(key, encode(Odometry("hsr", 2, 1, 3.0, 4.0, 0.5)))
    assert [o.message.x for o in out] == [3.0]
    counters = runner.node.stats.snapshot_counters()
    assert counters == {"received": 4, "invalid": 2, "handler_errors": 1}


def test_zenoh_runner_survives_garbage_and_publishes_status() -> None:
    from protocol.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = EchoNode(SITE, "main")
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    assert runner.started.wait(10)
    poses, statuses, alive = [], [], []
    with zenoh.open(loopback_config(connect=[endpoint])) as client:
        client.declare_subscriber(
            keys.pose_key(SITE, "*"), lambda s: poses.append(decode(s.payload.to_bytes()))
        )
        client.declare_subscriber(
            keys.status_key(SITE, "*", "*"), lambda s: statuses.append(decode(s.payload.to_bytes()))
        )
        client.liveliness().declare_subscriber(
            keys.alive_key(SITE, "*", "*"), lambda s: alive.append(str(s.kind)), history=True
        )
        pub = client.declare_publisher(
            keys.odom_key(SITE, "hsr"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        assert wait_until(lambda: any("PUT" in a for a in alive), 10)
        for junk in (
            b"",
            b"\xc1",
            b"\x81\xa6schema\xa4Nope",
            encode(Odometry("hsr", 1, 0, -5.0, 0.0, 0.0)),
        ):
            pub.put(junk)
        assert wait_until(
            lambda: (pub.put(encode(Odometry("hsr", 9, 9, 1.0, 2.0, 0.1))), bool(poses))[1], 10, 0.2
        )
        assert poses[0].x == 1.0 and poses[0].source == "fused"
        assert wait_until(lambda: any(s.counters.get("invalid", 0) >= 3 for s in statuses), 5)
        assert all(isinstance(s, ServiceStatus) for s in statuses)
        last = statuses[-1]
        assert last.counters["handler_errors"] == 1 and last.service == "backend"
        runner.stop()
        thread.join(10)
        assert not thread.is_alive()
        assert wait_until(lambda: any("DELETE" in a for a in alive), 10)
        assert wait_until(lambda: any(s.state == "stopping" for s in statuses), 5)
