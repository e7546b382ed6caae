"""``smartedge export``: data out of a recording, for other tools.

::

    smartedge export tum REC.mcap --key KEY --out est.tum

``tum`` writes the poses of one key (or ROS topic) of an MCAP recording as a TUM trajectory
(``stamp_s tx ty tz qx qy qz qw``, one line per stamp, the last message of a stamp wins), so
``smartedge evaluate ate`` or ``evo`` compares a real run with motion capture or a survey.
The key is a smartedge key of a ``smartedge record`` recording (``PoseEstimate``,
``PoseCorrection`` or ``Odometry`` messages, e.g. ``smartedge/lab/robot/hsr/pose``) or a topic
of any ROS 2 MCAP (``ros2 bag record -s mcap``) whose type is a pose
(``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped``,
``nav_msgs/Odometry``): the motion capture's own recording, say.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from core.geometry import yaw_to_quaternion
from core.trajectory import Trajectory
from protocol.codec import decode
from protocol.errors import DecodeError, SmartedgeError
from protocol.messages import Message, Odometry, PoseCorrection, PoseEstimate
from smartedge.commands.record import RecordingError, read_recording


class ExportError(SmartedgeError):
    """No poses to export (unknown key, wrong type, nothing decodes); the message says which."""


def _planar(x: float, y: float, theta: float) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), quaternion x, y, z, w (4,)) of a planar pose at z = 0."""
    return np.array([x, y, 0.0]), np.array(yaw_to_quaternion(theta))


def _smartedge_poses(path: Path, key: str) -> dict[int, tuple[np.ndarray, np.ndarray]] | None:
    """Poses of ``key`` from the recording's wire payloads; ``None`` when no message has it."""
    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    seen = bad = 0
    first_error = ""
    for k, _receive_ns, payload in read_recording(path, skip_unknown=True):
        if k != key:
            continue
        seen += 1
        try:
            msg: Message = decode(payload)
            if not isinstance(msg, (PoseEstimate, PoseCorrection, Odometry)):
                raise TypeError(f"a {type(msg).__name__}")
            poses[int(msg.stamp_ns)] = _planar(msg.x, msg.y, msg.theta)
        except (DecodeError, TypeError) as exc:
            bad += 1
            first_error = first_error or f"{type(exc).__name__}: {exc}"
    if not seen:
        return None
    if bad:
        print(f"smartedge export: {key}: {bad} of {seen} messages are not poses, skipped "
              f"(first: {first_error})", file=sys.stderr)
    return poses


def _ros_poses(path: Path, topic: str) -> dict[int, tuple[np.ndarray, np.ndarray]] | None:
    """Poses of a ROS 2 pose topic (CDR) of any MCAP; ``None`` when there is no such topic."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from smartedge import record_ros

    poses: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    found = False
    try:
        with path.open("rb") as f:
            for schema, channel, message in make_reader(f).iter_messages(topics=[topic]):
                found = True
                ros_type = schema.name if schema is not None else "no schema"
                if channel.message_encoding != "cdr":
                    raise ExportError(f"{path}: topic {topic} is {channel.message_encoding}, "
                                      "not a ROS 2 (CDR) topic")
                if ros_type.count("/") == 1:  # some writers name types pkg/Type
                    ros_type = ros_type.replace("/", "/msg/")
                try:
                    stamp_ns, pos, quat = record_ros.pose_from_ros(ros_type, message.data)
                except record_ros.RosRecordError as exc:
                    raise ExportError(f"{path}: topic {topic}: {exc}") from None
                poses[stamp_ns] = (pos, quat)
    except (McapError, ValueError, EOFError, OSError, KeyError) as exc:
        raise RecordingError(f"{path}: not a complete MCAP recording ({type(exc).__name__}: "
                             f"{exc})") from None
    return poses if found else None


def read_poses(path: str | Path, key: str) -> Trajectory:
    """The trajectory of ``key`` (a smartedge key or a ROS 2 pose topic) in a recording,
    sorted by stamp. :class:`ExportError` / :class:`RecordingError` name what is wrong."""
    p = Path(path)
    poses = None
    if not key.startswith("/"):
        poses = _smartedge_poses(p, key)
    if poses is None:
        poses = _ros_poses(p, key if key.startswith("/") else "/" + key)
    if poses is None:
        raise ExportError(f"{p}: no key or topic {key!r} in the recording "
                          "(smartedge echo / the mcap CLI list them)")
    if not poses:
        raise ExportError(f"{p}: {key}: none of its messages is a pose")
    stamps = sorted(poses)
    return Trajectory(np.array(stamps, dtype=np.float64) * 1e-9,
                      np.array([poses[s][0] for s in stamps], dtype=np.float64),
                      np.array([poses[s][1] for s in stamps], dtype=np.float64))


def _tum(args: argparse.Namespace) -> int:
    from core.trajectory import write_tum

    try:
        traj = read_poses(args.recording, args.key)
    except SmartedgeError as exc:
        print(f"smartedge export tum: {exc}", file=sys.stderr)
        return 1
    write_tum(args.out, traj)
    span = traj.stamps_s[-1] - traj.stamps_s[0]
    print(f"wrote {len(traj.stamps_s)} poses of {args.key} ({span:.1f} s) to {args.out}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="smartedge export", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    p_tum = sub.add_parser("tum", help="the poses of one key / topic as a TUM trajectory")
    p_tum.add_argument("recording", help="an MCAP file (smartedge record, or ros2 bag -s mcap)")
    p_tum.add_argument("--key", required=True,
                       help="smartedge key (e.g. smartedge/lab/robot/hsr/pose) or ROS topic")
    p_tum.add_argument("--out", required=True, help="output TUM file")
    args = parser.parse_args(None if argv is None else list(argv))
    return _tum(args)
