"""Read an MCAP recording made by ``smartedge record``: messages per key and the first poses.

A recording holds every sample of the recorded keys as it arrived, with the receive time in
nanoseconds: per Zenoh key a ROS 2 channel (standard types where they exist, CDR) for Foxglove
and ``ros2 bag``, and a wire channel with the msgpack bytes as published, which
:func:`smartedge.commands.record.read_recording` returns (:func:`protocol.decode` reads them).

    .venv/bin/smartedge record run.mcap --duration 30     # while the system runs
    .venv/bin/python examples/read_recording.py run.mcap --poses 5
"""

from __future__ import annotations

import argparse
import collections
import math
from pathlib import Path

import protocol
from smartedge.commands.record import RecordingError, read_recording


def main(path: Path, first_poses: int) -> None:
    count_per_key: collections.Counter[str] = collections.Counter()
    poses: list[tuple[str, protocol.PoseEstimate]] = []
    first_ns = last_ns = 0

    # (key, receive time in ns, payload) in receive order
    for key, receive_ns, payload in read_recording(path):
        count_per_key[key] += 1
        first_ns = first_ns or receive_ns
        last_ns = receive_ns
        if len(poses) < first_poses:
            try:
                msg: protocol.Message = protocol.decode(payload)
            except protocol.DecodeError:
                continue  # a recording keeps whatever was on the keys, garbage too
            if isinstance(msg, protocol.PoseEstimate):
                poses.append((key, msg))

    total = sum(count_per_key.values())
    print(f"{path}: {total} messages on {len(count_per_key)} keys over "
          f"{(last_ns - first_ns) * 1e-9:.1f} s")
    for key, n in sorted(count_per_key.items()):
        print(f"  {n:>7}  {key}")
    print(f"first {len(poses)} poses:")
    for key, pose in poses:
        print(f"  {key}  stamp_ns={pose.stamp_ns} x={pose.x:.3f} m y={pose.y:.3f} m "
              f"theta={math.degrees(pose.theta):.1f} deg source={pose.source}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path, help="an .mcap file from smartedge record")
    parser.add_argument("--poses", type=int, default=5, help="how many poses to print")
    args = parser.parse_args()
    try:
        main(args.recording, args.poses)
    except RecordingError as exc:  # missing, not MCAP, or cut short: the message says which
        raise SystemExit(f"error: {exc}") from None
