"""``smartedge record`` / ``smartedge replay``: capture the traffic of a running system into MCAP
and play it back, the way a lab debugs with ``ros2 bag``.

Recording: every sample on the key expression (default ``smartedge/**``) becomes MCAP messages
that Foxglove and ``ros2 bag`` read (profile ``ros2``, ROS 2 schemas, CDR payloads;
:mod:`smartedge.record_ros`): on ``/<key>`` the message as a ROS 2 type (poses
``geometry_msgs/PoseWithCovarianceStamped``, odometry ``nav_msgs/Odometry``, status
``diagnostic_msgs/DiagnosticArray``, images ``sensor_msgs/CompressedImage``, clouds
``sensor_msgs/PointCloud2``, detections ``smartedge_msgs/RobotDetections``) and on
``/_smartedge_wire/<key>`` the wire payload as is (``smartedge_msgs/Wire``), which replay
publishes back. ``log_time`` = the receive time (wall clock, ns), ``publish_time`` = the
message's own ``stamp_ns`` (the receive time when the payload does not decode).
``--format msgpack`` writes the older layout (one ``msgpack`` channel per key, no schema); both
read back the same.

Replay: the messages go back onto their keys in receive order, paced by their recorded receive
times (``--rate 2``: twice as fast; ``--rate 0``: as fast as possible). :func:`read_recording`
yields ``(key, receive_ns, payload)`` for offline use: the backend's one pipeline fed with the
recorded receive times gives the estimates the live backend gave (see
``tests/smartedge/test_record_replay.py``).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from core.session import add_session_arguments, make_config, options_from_args
from protocol import keys
from protocol.codec import decode
from protocol.errors import DecodeError, SmartedgeError
from protocol.messages import Message

MESSAGE_ENCODING = "msgpack"
PROFILE = "smartedge"
ROS2_PROFILE = "ros2"
FORMATS = ("ros2", "msgpack")

log = logging.getLogger(__name__)


class RecordingError(SmartedgeError):
    """An MCAP file cannot be read (missing, not MCAP, truncated); the message names it."""


@dataclasses.dataclass
class RecordStats:
    messages: int = 0
    bytes: int = 0
    undecodable: int = 0
    #: decoded messages that have no ROS 2 form (only their wire channel holds them)
    unconverted: int = 0
    per_key: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)


class Recorder:
    """Writes samples into an MCAP file. ``fmt`` ``"ros2"`` (default): ROS 2 schemas and CDR,
    a typed channel and a wire channel per key (module docstring); ``"msgpack"``: one msgpack
    channel per key. Not thread-safe: call :meth:`write` from one thread."""

    def __init__(self, path: str | Path, fmt: str = "ros2") -> None:
        from mcap.writer import Writer

        if fmt not in FORMATS:
            raise ValueError(f"recording format {fmt!r}: expected one of {', '.join(FORMATS)}")
        self.path = Path(path)
        self.format = fmt
        if fmt == "ros2":
            from smartedge import record_ros

            record_ros.typestore()  # rosbags missing: fail here, before the file exists
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        self._writer = Writer(self._file)
        self._writer.start(profile=ROS2_PROFILE if fmt == "ros2" else PROFILE,
                           library="smartedge")
        self._channels: dict[tuple[str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._warned: set[tuple[str, str]] = set()
        self.stats = RecordStats()

    def _channel(self, key: str, ros_type: str) -> int:
        channel = self._channels.get((key, ros_type))
        if channel is not None:
            return channel
        from smartedge import record_ros

        if ros_type == "":
            channel = self._writer.register_channel(
                topic=key, message_encoding=MESSAGE_ENCODING, schema_id=0)
        else:
            schema = self._schemas.get(ros_type)
            if schema is None:
                schema = self._schemas[ros_type] = self._writer.register_schema(
                    name=ros_type, encoding="ros2msg", data=record_ros.schema_text(ros_type))
            topic = (record_ros.wire_topic(key) if ros_type == record_ros.WIRE_TYPE
                     else record_ros.ros_topic(key))
            channel = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=schema,
                metadata={record_ros.KEY_METADATA: key})
        self._channels[(key, ros_type)] = channel
        return channel

    def write(self, key: str, payload: bytes, receive_ns: int) -> None:
        msg: Message | None = None
        try:
            msg = decode(payload)
            stamp = int(getattr(msg, "stamp_ns", receive_ns))
        except DecodeError:
            stamp = receive_ns
            self.stats.undecodable += 1
        log_time, publish_time = int(receive_ns), max(stamp, 0)
        if self.format == "msgpack":
            self._writer.add_message(channel_id=self._channel(key, ""), log_time=log_time,
                                     data=payload, publish_time=publish_time,
                                     sequence=self.stats.messages)
        else:
            from smartedge import record_ros

            if msg is not None:
                try:
                    ros_type, cdr = record_ros.to_cdr(msg)
                except record_ros.RosRecordError as exc:
                    self.stats.unconverted += 1
                    if (key, type(msg).__name__) not in self._warned:
                        self._warned.add((key, type(msg).__name__))
                        log.warning("%s: %s has no ROS 2 form (%s); recorded as wire bytes only",
                                    key, type(msg).__name__, exc)
                else:
                    self._writer.add_message(
                        channel_id=self._channel(key, ros_type), log_time=log_time, data=cdr,
                        publish_time=publish_time, sequence=self.stats.messages)
            self._writer.add_message(
                channel_id=self._channel(key, record_ros.WIRE_TYPE), log_time=log_time,
                data=record_ros.wire_cdr(payload), publish_time=publish_time,
                sequence=self.stats.messages)
        self.stats.messages += 1
        self.stats.bytes += len(payload)
        self.stats.per_key[key] += 1

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


def read_recording(path: str | Path, *,
                   skip_unknown: bool = False) -> Iterator[tuple[str, int, bytes]]:
    """``(key, receive_ns, payload)`` of every message of an MCAP recording, in receive order:
    the wire payloads of a ROS 2 recording (its typed channels repeat them), the channels of an
    older msgpack recording. A file that is missing, not MCAP or damaged, a channel that
    ``smartedge record`` does not write, or a wire message that does not decode raises
    :class:`RecordingError` naming the file (and channel) and how many messages were read.
    ``skip_unknown``: pass over channels of other writers (a ``ros2 bag`` MCAP's topics)."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from smartedge import record_ros

    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    count = 0
    try:
        with p.open("rb") as f:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                if channel.message_encoding == MESSAGE_ENCODING:
                    key, payload = channel.topic, bytes(message.data)
                elif schema is not None and schema.name == record_ros.WIRE_TYPE:
                    key = channel.metadata.get(record_ros.KEY_METADATA, "")
                    if not key:
                        raise RecordingError(
                            f"{p}: channel {channel.topic} has no {record_ros.KEY_METADATA} "
                            f"metadata; {count} messages read")
                    try:
                        payload = record_ros.wire_payload(message.data)
                    except record_ros.RosRecordError as exc:
                        raise RecordingError(
                            f"{p}: channel {channel.topic}, message {message.sequence}: {exc}; "
                            f"{count} messages read") from None
                elif record_ros.KEY_METADATA in channel.metadata or skip_unknown:
                    continue  # the typed twin of a wire channel, or skipped on request
                else:
                    what = schema.name if schema is not None else "no schema"
                    raise RecordingError(
                        f"{p}: channel {channel.topic} ({channel.message_encoding}, {what}) is "
                        f"not a smartedge record channel; {count} messages read")
                count += 1
                yield key, int(message.log_time), payload
    except (McapError, ValueError, EOFError, OSError, KeyError) as exc:
        raise RecordingError(f"{p}: not a complete MCAP recording ({type(exc).__name__}: "
                             f"{exc}); {count} messages read before the damage") from None


def record_main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge record", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", help="output file (.mcap)")
    parser.add_argument("--key", default=f"{keys.ROOT}/**",
                        help=f"key expression to record (default {keys.ROOT}/**)")
    parser.add_argument("--duration", type=float, default=0.0,
                        help="stop after S seconds (default: until Ctrl-C / SIGTERM)")
    parser.add_argument("--format", choices=FORMATS, default="ros2",
                        help="ros2 (default): ROS 2 schemas + CDR, for Foxglove and ros2 bag, "
                        "with the wire bytes beside; msgpack: the wire bytes only")
    add_session_arguments(parser)
    args = parser.parse_args(list(argv))
    import zenoh

    try:
        recorder = Recorder(args.out, args.format)
    except ImportError as exc:
        print(f"smartedge record: --format ros2 needs rosbags ({exc}); install it or use "
              "--format msgpack", file=sys.stderr)
        return 2

    queue: collections.deque[tuple[str, bytes, int]] = collections.deque()
    stop = {"now": False}

    def on_signal(*_: Any) -> None:
        stop["now"] = True

    previous = signal.signal(signal.SIGTERM, on_signal)
    session = zenoh.open(make_config(options_from_args(args)))
    sub = session.declare_subscriber(
        args.key, lambda s: queue.append((str(s.key_expr), s.payload.to_bytes(),
                                          time.time_ns())))
    print(f"recording {args.key} into {args.out} (Ctrl-C to stop)", flush=True)
    deadline = time.monotonic() + args.duration if args.duration > 0 else float("inf")
    try:
        while not stop["now"] and time.monotonic() < deadline:
            while queue:
                recorder.write(*queue.popleft())
            time.sleep(0.01)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
        while queue:
            recorder.write(*queue.popleft())
        recorder.close()
        signal.signal(signal.SIGTERM, previous)
    st = recorder.stats
    print(f"recorded {st.messages} messages ({st.bytes / 1e6:.1f} MB, {st.undecodable} "
          f"undecodable, {st.unconverted} without a ROS form) on {len(st.per_key)} keys "
          f"into {args.out}")
    for key, n in sorted(st.per_key.items()):
        print(f"  {n:>7}  {key}")
    return 0


def replay_main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge replay", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", help="an MCAP file written by smartedge record")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="speed factor (default 1: as recorded; 0: as fast as possible)")
    add_session_arguments(parser)
    args = parser.parse_args(list(argv))
    if args.rate < 0:
        print("smartedge replay: --rate must be >= 0", file=sys.stderr)
        return 2
    import zenoh

    try:
        messages = list(read_recording(args.recording))
    except RecordingError as exc:
        print(f"smartedge replay: {exc}", file=sys.stderr)
        return 1
    if not messages:
        print(f"smartedge replay: {args.recording}: no messages", file=sys.stderr)
        return 1
    session = zenoh.open(make_config(options_from_args(args)))
    publishers: dict[str, Any] = {}
    t0_rec = messages[0][1]
    t0 = time.monotonic()
    sent = 0
    try:
        for key, receive_ns, payload in messages:
            if args.rate > 0:
                due = t0 + (receive_ns - t0_rec) * 1e-9 / args.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            pub = publishers.get(key)
            if pub is None:
                pub = publishers[key] = session.declare_publisher(key)
            pub.put(payload)
            sent += 1
    except KeyboardInterrupt:
        pass
    finally:
        for pub in publishers.values():
            pub.undeclare()
        session.close()
    span = (messages[-1][1] - t0_rec) * 1e-9
    print(f"replayed {sent} of {len(messages)} messages ({span:.1f} s recorded) in "
          f"{time.monotonic() - t0:.1f} s")
    return 0
