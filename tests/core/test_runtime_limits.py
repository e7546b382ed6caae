"""The runtime's byte bounds: channels bounded in bytes, oversized samples refused in the Zenoh
callback, refusals counted per reason."""

from __future__ import annotations

import threading

import msgpack
import pytest

from core.runtime import (
    Outgoing,
    ScriptedRunner,
    ServiceNode,
    Stats,
    Subscription,
    ZenohRunner,
    _Channel,
)
from protocol import Odometry, PoseEstimate, ServiceStatus, decode, encode, keys
from protocol.limits import PAYLOAD_CAPS, payload_cap, queue_byte_budget
from tests.conftest import free_port, wait_until

SITE = "rtl"


class EchoNode(ServiceNode):
    """Turns each odometry message into a PoseEstimate stamped by the runner's clock."""

    service = "backend"

    def subscriptions(self):
        return [Subscription(keys.odom_key(SITE, "*"), Odometry, capacity=64)]

    def handle(self, key, message, recv_ns):
        est = PoseEstimate(message.robot_id, self.clock(), message.seq, message.x, message.y,
                           message.theta, message.covariance, "fused")
        return [Outgoing(keys.pose_key(SITE, message.robot_id), est)]


def _item(n: int, tag: int = 0) -> tuple[str, bytes, int]:
    return (f"k{tag}", bytes(n), tag)


@pytest.mark.parametrize("drop_oldest", [True, False])
def test_a_channel_is_bounded_in_bytes(drop_oldest: bool) -> None:
    stats = Stats()
    channel = _Channel(100, drop_oldest, stats, "sub", max_bytes=100)
    for tag in range(3):
        channel.put(_item(40, tag))
    assert len(channel) == 2 and channel.queued_bytes == 80
    kept = [channel.pop()[2], channel.pop()[2]]  # type: ignore[index]
    assert kept == ([1, 2] if drop_oldest else [0, 1])
    assert channel.pop() is None and channel.queued_bytes == 0
    assert stats.snapshot_counters() == {"dropped": 1, "dropped.sub": 1, "dropped.byte_budget": 1}


def test_a_channel_bounded_in_count_does_not_blame_the_bytes() -> None:
    stats = Stats()
    channel = _Channel(2, True, stats, "sub", max_bytes=1000)
    for tag in range(5):
        channel.put(_item(10, tag))
    assert len(channel) == 2 and channel.queued_bytes == 20
    assert stats.snapshot_counters() == {"dropped": 3, "dropped.sub": 3}


def test_a_sample_larger_than_the_whole_budget_is_dropped() -> None:
    stats = Stats()
    channel = _Channel(10, True, stats, "sub", max_bytes=100)
    channel.put(_item(30))
    channel.put(_item(101, 1))
    assert len(channel) == 0 and channel.queued_bytes == 0  # the old one went first, then the new
    assert stats.snapshot_counters()["dropped"] == 2


def test_subscription_limits_default_to_the_type_and_may_be_tighter() -> None:
    sub = Subscription("k/*", Odometry)
    assert sub.payload_limit == payload_cap("Odometry")
    assert sub.byte_budget == queue_byte_budget("Odometry")
    tight = Subscription("k/*", Odometry, max_payload_bytes=100, max_queued_bytes=10)
    assert tight.payload_limit == 100 and tight.byte_budget == 100  # one payload always fits
    assert Subscription("k/*", Odometry, max_payload_bytes=10**9).payload_limit == sub.payload_limit


def test_refusals_are_counted_per_reason() -> None:
    runner = ScriptedRunner(EchoNode(SITE, "main"))
    key = keys.odom_key(SITE, "hsr")
    wire = msgpack.unpackb(encode(Odometry("hsr", 1, 0, 1.0, 0.0, 0.0)), raw=False)
    runner.feed(key, msgpack.packb({**wire, "pad": b"\0" * 5000}))
    runner.feed(key, msgpack.packb({**wire, "pad": b"\0" * PAYLOAD_CAPS["Odometry"]}))
    runner.feed(key, b"\xc1")
    assert len(runner.feed(key, encode(Odometry("hsr", 2, 1, 1.0, 0.0, 0.0)), recv_ns=77)) == 1
    assert runner.published[-1].message.stamp_ns == 77  # the node's clock is the scripted time
    assert runner.node.stats.snapshot_counters() == {
        "received": 4, "invalid": 3, "invalid.unknown_key_too_large": 1,
        "invalid.payload_too_large": 1,
    }


def test_zenoh_runner_refuses_oversized_samples_in_the_callback() -> None:
    zenoh = pytest.importorskip("zenoh")
    from core.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = EchoNode(SITE, "main")
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]))
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    assert runner.started.wait(10)
    poses: list[PoseEstimate] = []
    statuses: list[ServiceStatus] = []
    try:
        with zenoh.open(loopback_config(connect=[endpoint])) as client:
            client.declare_subscriber(keys.pose_key(SITE, "*"),
                                      lambda s: poses.append(decode(s.payload.to_bytes())))
            client.declare_subscriber(keys.status_key(SITE, "*", "*"),
                                      lambda s: statuses.append(decode(s.payload.to_bytes())))
            pub = client.declare_publisher(keys.odom_key(SITE, "hsr"),
                                           congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_until(lambda: bool(statuses), 10)
            wire = msgpack.unpackb(encode(Odometry("hsr", 1, 0, 1.0, 0.0, 0.0)), raw=False)
            oversized = msgpack.packb({**wire, "pad": b"\0" * (2 * 1024 * 1024)})
            for _ in range(5):
                pub.put(oversized)
            assert wait_until(lambda: (pub.put(encode(Odometry("hsr", 9, 9, 1.0, 2.0, 0.1))),
                                       bool(poses))[1], 10, 0.2)
            assert wait_until(
                lambda: statuses[-1].counters.get("invalid.payload_too_large", 0) == 5, 5)
            counters = statuses[-1].counters
            assert counters["invalid"] == 5 and counters["received"] >= 6
            assert counters.get("dropped", 0) == 0
    finally:
        runner.stop()
        thread.join(10)
    assert not thread.is_alive()


def test_a_delay_bounded_channel_sheds_the_oldest_samples_when_popped() -> None:
    stats = Stats()
    channel = _Channel(100, True, stats, "sub", max_bytes=10_000, max_delay_ns=50)
    for recv_ns in (0, 10, 60, 100):
        channel.put(("k", bytes(5), recv_ns))
    item = channel.pop(now_ns=100)  # 0 and 10 waited more than 50 ns: shed, oldest first
    assert item is not None and item[2] == 60
    assert len(channel) == 1 and channel.queued_bytes == 5
    assert stats.snapshot_counters() == {"shed": 2, "shed.sub": 2}
    assert channel.pop(now_ns=1_000) is None  # the last one is shed too, nothing returned
    assert stats.snapshot_counters()["shed"] == 3 and channel.queued_bytes == 0


def test_a_channel_without_a_delay_bound_never_sheds() -> None:
    stats = Stats()
    channel = _Channel(100, True, stats, "sub")
    channel.put(("k", b"x", 0))
    assert channel.pop(now_ns=10**18) is not None and stats.snapshot_counters() == {}


def test_a_subscription_refuses_a_non_positive_delay_bound() -> None:
    with pytest.raises(ValueError, match="max_queue_delay_s"):
        Subscription("k/*", Odometry, max_queue_delay_s=0.0)
