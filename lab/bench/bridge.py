"""``smartedge bench bridge``: what the robot bridge's ROS output costs.

1. Encoding one pose output (``PoseWithCovarianceStamped``) per ROS flavour: CDR for
   zenoh-bridge-ros2dds, ROS 1 serialization, CDR plus the 33-byte attachment for rmw_zenoh;
   the peer is the smartedge msgpack ``PoseEstimate`` the backend sends the bridge.
2. Latency over two real Zenoh sessions on loopback, from ``adapter.publish_pose`` to a
   subscriber on the robot side (median and 95th percentile), for the ``ros2`` and the
   ``rmw_zenoh`` adapters, at the pose output's default 10 Hz and flat out.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence

import numpy as np

from lab.launcher import free_port
from protocol import codec
from protocol.messages import PoseEstimate

S = 1_000_000_000


def _estimate(seq: int = 0) -> PoseEstimate:
    cov = np.array([[4e-4, 1e-5, 0.0], [1e-5, 4e-4, 0.0], [0.0, 0.0, 2e-4]])
    return PoseEstimate("hsr", 1_700_000_000 * S + seq * S // 10, seq, 1.0, 2.0, 0.3, cov,
                        "fused", ("cam_a", "cam_b"), frame_id="map")


def _per_call_us(fn: Callable[[], object], n: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - t0) / n * 1e6


def encoding(n: int) -> dict[str, float]:
    """µs per encoded pose output, per flavour."""
    from robot_bridge.adapters import rmw_zenoh_wire, ros2

    est = _estimate()
    gid = bytes(range(16))
    return {
        "msgpack PoseEstimate (peer)": _per_call_us(lambda: codec.encode(est), n),
        "ros2 CDR (zenoh-bridge-ros2dds)": _per_call_us(
            lambda: ros2.serialize_pose_estimate(est), n),
        "ros1 (zenoh-plugin-ros1)": _per_call_us(
            lambda: ros2.serialize_pose_estimate(est, ros1=True), n),
        "rmw_zenoh CDR + attachment": _per_call_us(
            lambda: (ros2.serialize_pose_estimate(est),
                     rmw_zenoh_wire.encode_attachment(1, time.time_ns(), gid)), n),
    }


def latency(adapter_name: str, n: int, rate_hz: float) -> tuple[float, float, int]:
    """(median ms, p95 ms, received) from publish_pose to the robot side's subscriber."""
    import zenoh

    from core.session import loopback_config
    from robot_bridge.adapters import rmw_zenoh, rmw_zenoh_wire, ros2

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bridge_side = zenoh.open(loopback_config(listen=[endpoint]))
    robot_side = zenoh.open(loopback_config(connect=[endpoint]))
    topics = ros2.RosTopics.nav2()
    if adapter_name == "rmw_zenoh":
        adapter: ros2.RobotAdapter = rmw_zenoh.RmwZenohAdapter(bridge_side, topics)
        key = rmw_zenoh_wire.topic_key(
            0, topics.pose_topic, ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE)
    else:
        adapter = ros2.RosZenohAdapter(bridge_side, topics)
        key = ros2.ros2dds_key(topics.pose_topic)
    sent: dict[int, int] = {}
    lat_ns: list[int] = []

    def on_sample(sample: zenoh.Sample) -> None:
        msg = ros2.typestore().deserialize_cdr(sample.payload.to_bytes(),
                                               ros2.POSE_WITH_COVARIANCE_STAMPED_TYPE)
        stamp = msg.header.stamp.sec * S + msg.header.stamp.nanosec
        t_sent = sent.get(stamp)
        if t_sent is not None:
            lat_ns.append(time.perf_counter_ns() - t_sent)

    sub = robot_side.declare_subscriber(key, on_sample)
    try:
        for i in range(50):  # until the route carries data
            adapter.publish_pose(_estimate(10**6 + i))
            time.sleep(0.02)
        period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        for i in range(n):
            est = _estimate(i)
            sent[est.stamp_ns] = time.perf_counter_ns()
            adapter.publish_pose(est)
            if period:
                time.sleep(period)
        time.sleep(0.3)
    finally:
        sub.undeclare()
        adapter.close()
        robot_side.close()
        bridge_side.close()
    if not lat_ns:
        return float("nan"), float("nan"), 0
    ms = sorted(v * 1e-6 for v in lat_ns)
    return statistics.median(ms), ms[min(len(ms) - 1, int(0.95 * len(ms)))], len(ms)


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench bridge", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--encode-n", type=int, default=5000, help="encodings per flavour")
    parser.add_argument("--n", type=int, default=100, help="pose outputs per latency run")
    args = parser.parse_args(argv)
    print(f"encoding one pose output ({args.encode_n} each):")
    enc = encoding(args.encode_n)
    peer = enc["msgpack PoseEstimate (peer)"]
    for name, us in enc.items():
        print(f"  {name:34s} {us:8.1f} us  ({us / peer:.2f}x the msgpack peer)")
    print(f"publish_pose -> robot-side subscriber over loopback Zenoh ({args.n} each):")
    for rate in (10.0, 0.0):
        for name in ("ros2", "rmw_zenoh"):
            med, p95, got = latency(name, args.n, rate)
            label = f"{rate:g} Hz" if rate else "flat out"
            print(f"  {name:10s} {label:9s} median {med:6.3f} ms  p95 {p95:6.3f} ms  "
                  f"received {got}/{args.n}")
    return 0
