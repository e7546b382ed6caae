"""``smartedge bench ros-source``: the edge agent's frames/s from a ROS 2 topic.

A separate process publishes a rendered 848x480 view of the paper lab's cam2 with the robot in
it as ``sensor_msgs/Image`` rgb8 the rmw_zenoh way (keys and attachment; rosbags CDR made once,
re-stamped per frame) at ``--rate`` frames/s, with ``--depth`` also an aligned 16UC1 depth image
per frame (the agent pairs them by stamp and makes semantic clouds at 1 Hz). This process runs
the edge agent under its own service loop (``ZenohRunner``) with the shipped models and counts
the detections messages it publishes per second; then prints the rate as a ratio of what was
published and of the 30 frames/s target, and the node's per-stage latencies (p50 / p95).

    smartedge bench ros-source [--seconds 20] [--rate 60] [--depth] [--threads 2]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import struct
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

TARGET_FPS = 30.0
TOPIC = "/camera/color/image_raw"
DEPTH_TOPIC = "/camera/aligned_depth_to_color/image_raw"


def publisher(endpoint: str, stop: Any, sent: Any, depth: bool, rate_hz: float) -> None:
    """The robot's camera driver: rendered frames as ROS images at ``rate_hz``."""
    import zenoh
    from rosbags.typesys import Stores, get_typestore

    from core.session import loopback_config
    from robot_bridge.adapters.rmw_zenoh_wire import encode_attachment, topic_key
    from simulation.dataset import SampleGenerator
    from simulation.scenario import load_scenario

    gen = SampleGenerator(load_scenario(), "site", seed=11)
    s = next(s for s in (gen(i) for i in range(200)) if s.camera.camera_id == "cam2"
             and s.robots[0].bbox_xyxy is not None and s.robots[0].in_image.sum() >= 8
             and s.robots[0].bbox_xyxy[3] - s.robots[0].bbox_xyxy[1] >= 40)  # robot in view
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types

    def cdr(pixels: np.ndarray, enc: str) -> bytearray:
        h, w = pixels.shape[:2]
        raw = np.ascontiguousarray(pixels).view(np.uint8).reshape(h, -1)
        msg = T["sensor_msgs/msg/Image"](T["std_msgs/msg/Header"](
            T["builtin_interfaces/msg/Time"](0, 0), "cam"), h, w, enc, 0, raw.shape[1],
            raw.reshape(-1))
        return bytearray(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))

    rgb = cdr(s.image_rgb, "rgb8")
    mm = cdr(np.where(np.isfinite(s.depth_m), s.depth_m * 1000, 0).astype(np.uint16), "16UC1")
    session = zenoh.open(loopback_config(connect=[endpoint]))
    pub = session.declare_publisher(topic_key(0, TOPIC, "sensor_msgs/msg/Image"))
    dpub = session.declare_publisher(topic_key(0, DEPTH_TOPIC, "sensor_msgs/msg/Image"))
    gid = bytes(range(16))
    seq = 0
    time.sleep(1.0)
    next_t = time.monotonic()
    while not stop.is_set():
        seq += 1
        now = time.time_ns()
        for buf in (rgb, mm):
            struct.pack_into("<iI", buf, 4, *divmod(now, 1_000_000_000))  # header stamp
        pub.put(bytes(rgb), attachment=encode_attachment(seq, now, gid))
        if depth:
            dpub.put(bytes(mm), attachment=encode_attachment(seq, now, gid[::-1]))
        with sent.get_lock():
            sent.value += 1
        # rate_hz frames a second (the agent keeps only the newest)
        next_t += 1.0 / rate_hz
        time.sleep(max(0.0, next_t - time.monotonic()))
    session.close()


def main(argv: Sequence[str] | None = None) -> int:
    import zenoh

    from core.runtime import ZenohRunner
    from core.session import loopback_config
    from edge_agent.service import build_node, build_parser
    from lab.launcher import free_port
    from protocol import codec, keys
    from protocol.messages import RobotDetections
    from simulation.scenario import SITES_DIR

    parser = argparse.ArgumentParser(prog="smartedge bench ros-source",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds (20)")
    parser.add_argument("--rate", type=float, default=60.0,
                        help="frames/s the driver publishes (60: twice the target)")
    parser.add_argument("--depth", action="store_true",
                        help="also aligned 16UC1 depth, semantic clouds at 1 Hz")
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime threads (2)")
    args = parser.parse_args(None if argv is None else list(argv))
    if not (args.seconds > 0 and args.rate > 0 and args.threads >= 1):
        parser.error("--seconds and --rate must be > 0, --threads >= 1")
    site = str(Path(SITES_DIR) / "paper_lab.yaml")
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # the agent's session listens here
    ep_out = f"tcp/127.0.0.1:{free_port()}"
    listener = zenoh.open(loopback_config(listen=[ep_out]))
    extra = ["--ros-depth-topic", DEPTH_TOPIC] if args.depth else ["--cloud-rate", "0"]
    node = build_node(build_parser().parse_args([
        "--site", site, "--camera", "cam2", "--source", "ros", "--threads", str(args.threads),
        "--ros-image-topic", TOPIC, "--ros-camera-info-topic", "none", "--ros-domain-id", "0",
        *extra]))
    runner = ZenohRunner(node, loopback_config(listen=[endpoint], connect=[ep_out]))
    thread = threading.Thread(target=runner.run, daemon=True)
    stamps: list[float] = []
    sub = listener.declare_subscriber(
        keys.detections_key("paper_lab", "cam2"),
        lambda smp: stamps.append(time.monotonic()) if codec.decode(
            smp.payload.to_bytes(), RobotDetections) else None)
    ctx = mp.get_context("spawn")
    stop, sent = ctx.Event(), ctx.Value("i", 0)
    proc = ctx.Process(target=publisher, args=(endpoint, stop, sent, args.depth, args.rate))
    print(f"edge agent on a ROS topic: 848x480 rgb8{' + 16UC1 depth' if args.depth else ''} "
          f"at {args.rate:g} frames/s, {args.seconds:g} s ...", flush=True)
    thread.start()
    try:
        runner.started.wait(30)
        proc.start()
        deadline = time.monotonic() + 90
        while not stamps:
            if time.monotonic() > deadline or not proc.is_alive():
                print(f"no detections: published {sent.value}, agent {node.state()}, "
                      f"publisher exit {proc.exitcode}")
                return 1
            time.sleep(0.1)
        time.sleep(2.0)  # warm up
        n0, s0, t0 = len(stamps), sent.value, time.monotonic()
        time.sleep(args.seconds)
        n1, s1, t1 = len(stamps), sent.value, time.monotonic()
    finally:
        stop.set()
        proc.join(10)
        runner.stop()
        thread.join(10)
        sub.undeclare()
        listener.close()
    published = (s1 - s0) / (t1 - t0)
    fps = (n1 - n0) / (t1 - t0)
    print(f"published {published:.1f} frames/s; detections {fps:.1f} /s = "
          f"{fps / published:.2f}x of published, {fps / TARGET_FPS:.2f}x the "
          f"{TARGET_FPS:g} frames/s target")
    p50, p95 = node.stats.percentiles_ms(0.5), node.stats.percentiles_ms(0.95)
    print(f"{'stage':<24} {'p50 ms':>8} {'p95 ms':>8}")
    for name in sorted(p50):
        print(f"{name:<24} {p50[name]:>8.2f} {p95.get(name, float('nan')):>8.2f}")
    counters = node.stats.snapshot_counters()
    print("counters:", {k: v for k, v in sorted(counters.items()) if not k.startswith("lat")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
