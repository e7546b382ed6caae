"""Publish a simulated run over Zenoh: the same messages real edge cameras and a real robot
bridge send, on the same keys, and pose corrections back to the simulated robot.

The only module of :mod:`simulation` that imports zenoh. ``python -m simulation.publisher``
runs the paper site's trajectories in (scaled) real time; tests and the demo call
:func:`publish_run` with their own session.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import time
from collections.abc import Callable, Sequence

import zenoh

from core.session import add_session_arguments, make_config, options_from_args
from protocol import keys
from protocol.codec import encode
from protocol.errors import DecodeError
from protocol.messages import Odometry, PoseCorrection, RobotDetections
from simulation.runner import SimulationRun
from simulation.scenario import PAPER_SCENARIO, load_scenario

log = logging.getLogger(__name__)


@dataclasses.dataclass
class PublishStats:
    """Counts of what :func:`publish_run` did."""

    detections: int = 0
    odometry: int = 0
    corrections_received: int = 0
    corrections_applied: int = 0
    corrections_invalid: int = 0


def publish_run(session: zenoh.Session, run: SimulationRun, speed: float = 0.0,
                accept_corrections: bool = True, until_s: float | None = None,
                sleep: Callable[[float], None] = time.sleep) -> PublishStats:
    """Publish every message of ``run`` in arrival order.

    ``speed``: 1.0 paces messages in real time (arrival times), 10.0 ten times faster, 0 as
    fast as possible. With ``accept_corrections``, :class:`protocol.PoseCorrection` messages on
    the robot's correction key are applied to the simulated robot (only while it is static,
    like the HSR). ``until_s``: stop after this much simulated time. Reliable, blocking
    publishers: nothing is dropped under load.
    """
    site = run.scenario.site.name
    robot_id = run.scenario.robot_id
    stats = PublishStats()
    enc = zenoh.Encoding("application/msgpack")
    qos = {"encoding": enc, "congestion_control": zenoh.CongestionControl.BLOCK,
           "reliability": zenoh.Reliability.RELIABLE}
    pubs = {cam: session.declare_publisher(keys.detections_key(site, cam), **qos)
            for cam in run.camera_ids}
    odom_pub = session.declare_publisher(keys.odom_key(site, robot_id), **qos)
    corrections = None
    if accept_corrections:
        corrections = session.declare_subscriber(keys.correction_key(site, robot_id),
                                                 zenoh.handlers.FifoChannel(64))

    def on_step(_t_s: float) -> None:
        if corrections is None:
            return
        while True:
            sample = corrections.try_recv()
            if sample is None:
                return
            stats.corrections_received += 1
            try:
                from protocol.codec import decode

                msg = decode(sample.payload.to_bytes(), PoseCorrection)
            except DecodeError as exc:
                stats.corrections_invalid += 1
                log.warning("dropping invalid correction: %s", exc.reason)
                continue
            if run.robot.apply_correction((msg.x, msg.y, msg.theta), msg.stamp_ns):
                stats.corrections_applied += 1

    wall0 = time.monotonic()
    t0_ns = run.scenario.start_stamp_ns
    try:
        for tm in run.messages(until_s=until_s, on_step=on_step):
            if speed > 0:
                due = (tm.arrival_ns - t0_ns) * 1e-9 / speed
                lag = due - (time.monotonic() - wall0)
                if lag > 0:
                    sleep(lag)
            msg = tm.message
            if isinstance(msg, RobotDetections):
                pubs[msg.camera_id].put(encode(msg))
                stats.detections += 1
            elif isinstance(msg, Odometry):
                odom_pub.put(encode(msg))
                stats.odometry += 1
    finally:
        for p in pubs.values():
            p.undeclare()
        odom_pub.undeclare()
        if corrections is not None:
            corrections.undeclare()
    return stats


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m simulation.publisher",
                                     description="Publish simulated detections and odometry.")
    parser.add_argument("--scenario", default=str(PAPER_SCENARIO), help="scenario file")
    parser.add_argument("--trajectory", default=None, help="trajectory (default: all)")
    parser.add_argument("--reverse", action="store_true", help="run the trajectory reversed")
    parser.add_argument("--speed", type=float, default=1.0, help="time scale, 0 = max speed")
    parser.add_argument("--seed", type=int, default=0)
    add_session_arguments(parser)
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    scenario = load_scenario(args.scenario)
    names = [args.trajectory] if args.trajectory else list(scenario.trajectories)
    with zenoh.open(make_config(options_from_args(args))) as session:
        for i, name in enumerate(names):
            run = SimulationRun(scenario, name, args.reverse, seed=args.seed + i)
            stats = publish_run(session, run, speed=args.speed)
            print(f"{name}: {stats}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
