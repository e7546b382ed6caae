"""Recording overhead of ``smartedge record``'s formats: bytes and CPU per message, ROS 2 (typed
channel + wire channel, CDR) against the wire bytes only (``--format msgpack``).

The messages are a simulated drive of the paper lab (4 cameras' detections at 15 Hz, odometry,
ground truth), as ``smartedge record`` would receive them; each format writes them into MCAP
(zstd chunks, the writer's default) and reads them back with ``read_recording``.

    .venv/bin/python scripts/record_overhead.py [--drive-s 30]
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from pathlib import Path

from protocol import keys
from simulation.calibration_drive import drive_messages
from simulation.scenario import load_scenario
from smartedge.commands.record import FORMATS, Recorder, read_recording


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drive-s", type=float, default=30.0, help="simulated drive, s")
    parser.add_argument("--route", default="traj3x3")
    args = parser.parse_args()
    print(f"simulating a {args.drive_s:.0f} s drive ...", flush=True)
    messages = [(m.key, m.payload, m.arrival_ns) for m in
                drive_messages(load_scenario(), args.route, duration_s=args.drive_s)]
    mix = collections.Counter(keys.parse_key(k).topic for k, _, _ in messages)
    wire_bytes = sum(len(p) for _, p, _ in messages)
    print(f"{len(messages)} messages ({dict(mix)}), {wire_bytes / len(messages):.0f} B wire "
          "payload per message on average")
    print(f"{'format':<8} {'file B/msg':>10} {'write us/msg':>13} {'read us/msg':>12}")
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in FORMATS:
            path = Path(tmp) / f"{fmt}.mcap"
            t0 = time.process_time()
            rec = Recorder(path, fmt)
            for key, payload, receive_ns in messages:
                rec.write(key, payload, receive_ns)
            rec.close()
            write_s = time.process_time() - t0
            t0 = time.process_time()
            n = sum(1 for _ in read_recording(path))
            read_s = time.process_time() - t0
            assert n == len(messages), (fmt, n)
            print(f"{fmt:<8} {path.stat().st_size / n:>10.1f} {write_s / n * 1e6:>13.1f} "
                  f"{read_s / n * 1e6:>12.1f}", flush=True)


if __name__ == "__main__":
    main()
