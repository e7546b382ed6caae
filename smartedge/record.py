"""``smartedge record`` / ``smartedge replay``: capture the traffic of a running system into MCAP
and play it back, the way a lab debugs with ``ros2 bag``.

Recording: every sample on the key expression (default ``smartedge/**``) becomes one MCAP
message on a channel named by its key (``message_encoding`` ``msgpack``, the wire payload as
is), with ``log_time`` = the receive time (wall clock, ns) and ``publish_time`` = the message's
own ``stamp_ns`` (the receive time when the payload does not decode). MCAP is the container
robotics tools read (Foxglove, the ``mcap`` CLI).

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
import signal
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from protocol import keys
from protocol.codec import decode
from protocol.errors import DecodeError, SmartedgeError
from protocol.session import add_session_arguments, make_config, options_from_args

MESSAGE_ENCODING = "msgpack"
PROFILE = "smartedge"


class RecordingError(SmartedgeError):
    """An MCAP file cannot be read (missing, not MCAP, truncated); the message names it."""


@dataclasses.dataclass
class RecordStats:
    messages: int = 0
    bytes: int = 0
    undecodable: int = 0
    per_key: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)


class Recorder:
    """Writes samples into an MCAP file (one channel per key). Not thread-safe: call
    :meth:`write` from one thread."""

    def __init__(self, path: str | Path) -> None:
        from mcap.writer import Writer

        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        self._writer = Writer(self._file)
        self._writer.start(profile=PROFILE, library="smartedge")
        self._channels: dict[str, int] = {}
        self.stats = RecordStats()

    def write(self, key: str, payload: bytes, receive_ns: int) -> None:
        channel = self._channels.get(key)
        if channel is None:
            channel = self._channels[key] = self._writer.register_channel(
                topic=key, message_encoding=MESSAGE_ENCODING, schema_id=0)
        try:
            stamp = int(getattr(decode(payload), "stamp_ns", receive_ns))
        except DecodeError:
            stamp = receive_ns
            self.stats.undecodable += 1
        self._writer.add_message(channel_id=channel, log_time=int(receive_ns), data=payload,
                                 publish_time=max(stamp, 0), sequence=self.stats.messages)
        self.stats.messages += 1
        self.stats.bytes += len(payload)
        self.stats.per_key[key] += 1

    def close(self) -> None:
        self._writer.finish()
        self._file.close()


def read_recording(path: str | Path) -> Iterator[tuple[str, int, bytes]]:
    """``(key, receive_ns, payload)`` of every message of an MCAP recording, in receive order.
    A file that is missing, not MCAP or damaged raises :class:`RecordingError` naming it and
    how many messages were read before the damage."""
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording")
    count = 0
    try:
        with p.open("rb") as f:
            reader = make_reader(f)
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                count += 1
                yield channel.topic, int(message.log_time), bytes(message.data)
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
    add_session_arguments(parser)
    args = parser.parse_args(list(argv))
    import zenoh

    queue: collections.deque[tuple[str, bytes, int]] = collections.deque()
    stop = {"now": False}

    def on_signal(*_: Any) -> None:
        stop["now"] = True

    previous = signal.signal(signal.SIGTERM, on_signal)
    recorder = Recorder(args.out)
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
          f"undecodable) on {len(st.per_key)} keys into {args.out}")
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
