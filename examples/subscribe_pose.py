"""Subscribe to a robot's fused pose, as a robot's navigation stack or a dashboard would.

The backend publishes :class:`protocol.PoseEstimate` (world frame: x, y in metres, theta in
radians, a 3x3 covariance) on ``smartedge/<site>/robot/<robot>/pose`` at the odometry rate.
Run it next to ``smartedge demo`` with ``--site simulation/sites/paper_lab.yaml``. Exits 1
when no pose arrived at all (a health check can use it).

    .venv/bin/python examples/subscribe_pose.py --robot hsr --count 20 --timeout-s 30
"""

from __future__ import annotations

import argparse
import contextlib
import math
import queue
import sys
from pathlib import Path

import zenoh

import protocol
from core.session import add_session_arguments, make_config, options_from_args
from core.site import load_site
from protocol import keys

EXAMPLE_SITE = Path(__file__).resolve().parents[1] / "deploy" / "site.example.yaml"


def main(conf: zenoh.Config, site_path: Path, robot_id: str | None, count: int,
         timeout_s: float) -> int:
    """Print ``count`` poses (0: no limit); returns how many arrived before ``timeout_s``."""
    site = load_site(site_path)
    robot_id = robot_id or next(iter(site.robots))
    key = keys.pose_key(site.name, robot_id)
    # Zenoh calls the handler on its own thread; hand the samples to this one through a queue
    samples: queue.Queue[zenoh.Sample] = queue.Queue()

    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(key, samples.put)
        print(f"subscribed to {key}", flush=True)
        received = 0
        while count <= 0 or received < count:
            try:
                sample = samples.get(timeout=timeout_s)
            except queue.Empty:
                print(f"no pose for {timeout_s:g} s: stopping", flush=True)
                break
            try:  # with the expected type, anything else is a DecodeError too
                pose = protocol.decode(sample.payload.to_bytes(), protocol.PoseEstimate)
            except protocol.DecodeError as exc:  # anything may be put on a key: skip it
                print(f"undecodable message on {sample.key_expr}: {exc}", flush=True)
                continue
            std_m = math.sqrt(max(pose.covariance[0, 0] + pose.covariance[1, 1], 0.0))
            print(f"seq={pose.seq} stamp_ns={pose.stamp_ns} x={pose.x:.3f} m y={pose.y:.3f} m "
                  f"theta={math.degrees(pose.theta):.1f} deg std={100 * std_m:.1f} cm "
                  f"source={pose.source}", flush=True)
            received += 1
        subscriber.undeclare()
    return received


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--site", type=Path, default=EXAMPLE_SITE, help="site file (YAML)")
    parser.add_argument("--robot", default=None, help="robot id (default: the site's first)")
    parser.add_argument("--count", type=int, default=0, help="stop after N poses (0: never)")
    parser.add_argument("--timeout-s", type=float, default=10.0,
                        help="stop when no pose came for this long")
    add_session_arguments(parser)  # --mode, --connect, --listen, --config (as zenoh's examples)
    args = parser.parse_args()
    conf = make_config(options_from_args(args))  # default: a peer on tcp/127.0.0.1:7447
    received = 0
    with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C: close the session and stop
        received = main(conf, args.site, args.robot, args.count, args.timeout_s)
    sys.exit(0 if received else 1)  # no pose at all: say so to a script or a health check
