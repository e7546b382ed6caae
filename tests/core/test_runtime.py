"""The service runtime: a node behind real Zenoh keeps running on garbage and reports status."""

from __future__ import annotations

import gc
import threading
import time

import pytest

from core.runtime import Outgoing, ScriptedRunner, ServiceNode, Subscription, ZenohRunner
from protocol import Odometry, PoseEstimate, ServiceStatus, decode, encode, keys
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
    from core.session import loopback_config

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


class UpkeepNode(EchoNode):
    """An echo node with deferred upkeep: ``slices`` idle slices of 5 ms each."""

    def __init__(self, site: str, instance_id: str, slices: int) -> None:
        super().__init__(site, instance_id)
        self.left = slices
        self.calls: list[int] = []

    def idle(self, now_ns):
        self.calls.append(now_ns)
        if self.left < 0:
            raise RuntimeError("upkeep bug")  # contained and counted like a handler's
        if self.left == 0:
            return False
        self.left -= 1
        time.sleep(0.005)
        return True


def test_scripted_runner_runs_the_idle_upkeep_after_a_tick() -> None:
    node = UpkeepNode(SITE, "main", slices=3)
    runner = ScriptedRunner(node)
    runner.feed(keys.odom_key(SITE, "hsr"), encode(Odometry("hsr", 2, 1, 3.0, 4.0, 0.5)))
    assert node.left == 3  # a message is not idle time
    runner.tick(10)
    assert node.left == 0 and len(node.calls) == 4  # three slices, then "nothing left"
    assert runner.idle() == 0


def test_zenoh_runner_runs_idle_upkeep_between_messages_and_freezes_start_up() -> None:
    """The worker runs the node's idle upkeep when nothing waits, slice by slice, and answers a
    message between two slices; an upkeep error is counted, the service runs on; what start-up
    made is out of the garbage collector's view (gc.freeze)."""
    from core.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    node = UpkeepNode(SITE, "main", slices=200)  # 1 s of upkeep in 5 ms slices
    runner = ZenohRunner(node, loopback_config(listen=[endpoint]), status=False)
    thread = threading.Thread(target=runner.run, daemon=True)
    thread.start()
    try:
        assert runner.started.wait(10)
        assert gc.get_freeze_count() > 0
        poses: list[tuple[float, object]] = []
        with zenoh.open(loopback_config(connect=[endpoint])) as client:
            client.declare_subscriber(keys.pose_key(SITE, "*"), lambda s: poses.append(
                (time.monotonic(), decode(s.payload.to_bytes()))))
            pub = client.declare_publisher(keys.odom_key(SITE, "hsr"),
                                           congestion_control=zenoh.CongestionControl.BLOCK)
            assert wait_until(lambda: len(node.calls) > 5, 10)
            sent = []
            for i in range(5):  # answered while the upkeep still has slices left
                sent.append(time.monotonic())
                pub.put(encode(Odometry("hsr", 10 + i, i, 1.0 + i, 2.0, 0.1)))
                time.sleep(0.05)
            assert wait_until(lambda: len(poses) == 5, 10)
            assert node.left > 0
            # each within a few slices of its sending, not after the whole second of upkeep
            assert max(rx - tx for (rx, _), tx in zip(poses, sent, strict=True)) < 0.5
            assert wait_until(lambda: node.left == 0, 10)
            node.left = -1  # the next slice raises
            pub.put(encode(Odometry("hsr", 99, 99, 5.0, 2.0, 0.1)))
            assert wait_until(lambda: node.stats.snapshot_counters().get("handler_errors", 0)
                              >= 1, 10)
            node.left = 0
            pub.put(encode(Odometry("hsr", 100, 100, 6.0, 2.0, 0.1)))
            assert wait_until(lambda: any(p.x == 6.0 for _, p in poses), 10)
    finally:
        runner.stop()
        thread.join(10)
        gc.unfreeze()


def test_the_signal_handler_never_waits_for_the_worker_loops_lock() -> None:
    """SIGTERM runs its handler in the main thread between two bytecodes of the worker loop,
    maybe while the loop holds the wake event's lock: the handler must not take that lock
    (it hung a backend until it was killed)."""
    from core.session import loopback_config

    runner = ZenohRunner(EchoNode(SITE, "main"), loopback_config())

    def interrupted_inside_the_lock() -> None:
        with runner._wake._cond:  # where the loop is when clearing or waiting on the event
            runner._on_signal(15, None)

    thread = threading.Thread(target=interrupted_inside_the_lock, daemon=True)
    thread.start()
    thread.join(2)
    assert not thread.is_alive(), "the signal handler waited for the worker loop's lock"
    assert runner._stop.is_set()
