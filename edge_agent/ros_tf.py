"""``/tf`` and ``/tf_static`` from the Zenoh bus into a :class:`core.tf_buffer.TfBuffer`.

A robot says where its head camera is through TF: ``tf2_msgs/msg/TFMessage`` (a sequence of
``geometry_msgs/msg/TransformStamped``) on ``/tf`` (moving joints: the head's pan and tilt) and
``/tf_static`` (bolted parts: the camera on the head). An edge board has no rosbags, so the
message is decoded here (:func:`decode_tf_message`) with the same bounded CDR reader as the
images (:mod:`edge_agent.ros_source`): the transform count is checked against the bytes left
before anything is read, strings are bounded, a truncated or hostile message raises
:class:`RosTfError` whose ``counter`` names what was wrong (``tf_truncated``,
``tf_bad_field``, ``tf_not_cdr``, ``tf_too_many``).

Keys: the same spelling as the images (:func:`edge_agent.ros_source.topic_key`), for rmw_zenoh
(``<domain>/tf/tf2_msgs::msg::dds_::TFMessage_/<hash>``) and zenoh-bridge-ros2dds
(``[<namespace>/]tf``).

``/tf_static`` is transient-local: its publisher sends each transform once, at start, and a
subscriber that joins later must ask for it. rmw_zenoh keeps the publications of a
transient-local publisher in the cache of a Zenoh ``AdvancedPublisher`` (a queryable under
``<key>/@adv/pub/<zid>/<eid>/...``, with publisher detection on). :class:`TfListener` reads
``/tf_static`` through a Zenoh ``AdvancedSubscriber`` with history and late-publisher
detection, which queries those caches when it is declared and whenever such a publisher
appears later, and receives live publications as a plain subscriber does. A publisher without
a cache (a plain Zenoh publisher, an older bridge's publication cache under another prefix)
reaches a late subscriber only if it publishes again: tf2 users then republish ``/tf_static``
periodically (the simulated robot does, at 1 Hz), which a :class:`core.tf_buffer.TfBuffer`
takes as a refresh of the same static transform.

Zenoh callbacks only queue raw payloads (bounded: :data:`TF_QUEUE` and
:data:`TF_STATIC_QUEUE` messages; overflow counted ``tf_dropped``); decoding happens in the
worker (:meth:`TfListener.drain`), which feeds the buffer.
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from typing import Any, Final

from core.tf_buffer import TfBuffer, TransformReading
from edge_agent.ros_source import (
    ERROR_LOG_PERIOD_S,
    MAX_PAYLOAD_BYTES,
    TRANSPORTS,
    CdrReader,
    RosImageError,
    topic_key,
)
from protocol.errors import SmartedgeError, UsageError

log = logging.getLogger(__name__)

TF_MESSAGE_TYPE: Final = "tf2_msgs/msg/TFMessage"
#: the default topics
TF_TOPIC: Final = "/tf"
TF_STATIC_TOPIC: Final = "/tf_static"
#: most transforms accepted in one message
MAX_TRANSFORMS: Final = 4096
#: fewest bytes one TransformStamped takes in CDR (stamp 8, two string lengths 8, 7 doubles)
MIN_TRANSFORM_BYTES: Final = 8 + 8 + 56
#: raw /tf messages queued between two worker ticks (a robot publishes a few hundred a second)
TF_QUEUE: Final = 1024
#: raw /tf_static messages queued
TF_STATIC_QUEUE: Final = 64


class RosTfError(SmartedgeError):
    """A TFMessage that cannot be used; ``counter``: the status counter it is counted under."""

    def __init__(self, counter: str, message: str) -> None:
        super().__init__(message)
        self.counter = counter


def decode_tf_message(payload: bytes | memoryview,
                      what: str = "TFMessage") -> list[TransformReading]:
    """Every transform of a ``tf2_msgs/msg/TFMessage`` from its CDR bytes, in message order
    (frame ids as sent; :class:`core.tf_buffer.TfBuffer` strips a leading ``/`` and checks
    the values). :class:`RosTfError` when the message is truncated or inconsistent."""
    try:
        cdr = CdrReader(payload, what)
        n = cdr.u32("the length of transforms")
        if n > MAX_TRANSFORMS:
            raise RosTfError("tf_too_many", f"{what}: {n} transforms (at most "
                             f"{MAX_TRANSFORMS})")
        left = len(cdr.buf) - cdr.pos
        if n * MIN_TRANSFORM_BYTES > left:
            raise RosTfError("tf_truncated", f"{what}: {n} transforms cannot fit in the "
                             f"{left} bytes left")
        out = []
        for i in range(n):
            stamp_ns, parent = cdr.header()
            child = cdr.string(f"transforms[{i}].child_frame_id")
            t = cdr.doubles(3, f"transforms[{i}].transform.translation")
            q = cdr.doubles(4, f"transforms[{i}].transform.rotation")
            out.append(TransformReading(parent, child, stamp_ns,
                                        (float(t[0]), float(t[1]), float(t[2])),
                                        (float(q[0]), float(q[1]), float(q[2]), float(q[3]))))
        return out
    except RosImageError as exc:
        counter = exc.counter.replace("ros_", "tf_", 1)
        raise RosTfError(counter, str(exc).replace("header.", "transforms[].header.")) from None


class _Queue:
    """Raw payloads of one key from a Zenoh thread to the worker, at most ``capacity``
    (the oldest pushed out and counted)."""

    def __init__(self, capacity: int) -> None:
        self.lock = threading.Lock()
        self.items: collections.deque[bytes] = collections.deque()
        self.capacity = capacity
        self.dropped = 0
        self.oversized = 0
        self.received = 0

    def put(self, sample: Any) -> None:
        if len(sample.payload) > MAX_PAYLOAD_BYTES:
            with self.lock:
                self.oversized += 1
            return
        data = sample.payload.to_bytes()
        with self.lock:
            if len(self.items) >= self.capacity:
                self.items.popleft()
                self.dropped += 1
            self.items.append(data)
            self.received += 1

    def take_all(self) -> list[bytes]:
        with self.lock:
            out = list(self.items)
            self.items.clear()
            return out


class TfListener:
    """``/tf`` and ``/tf_static`` over one transport (module docstring).

    ``transport``: rmw_zenoh or ros2dds; ``domain_id`` (rmw_zenoh), ``namespace`` (ros2dds);
    the topics. :meth:`attach` subscribes; :meth:`drain` (worker thread) decodes what arrived
    into a buffer. :attr:`counters`: ``tf_messages``, ``tf_static_messages``, ``tf_dropped``
    and the decode errors; :attr:`last_error` the latest one."""

    def __init__(self, transport: str, *, domain_id: int = 0, namespace: str = "",
                 tf_topic: str = TF_TOPIC, static_topic: str = TF_STATIC_TOPIC) -> None:
        if transport not in TRANSPORTS:
            raise UsageError(f"ROS transport {transport!r}: expected one of {TRANSPORTS}")
        self.transport = transport
        self.tf_key = topic_key(transport, tf_topic, TF_MESSAGE_TYPE, domain_id=domain_id,
                                namespace=namespace)
        self.static_key = topic_key(transport, static_topic, TF_MESSAGE_TYPE,
                                    domain_id=domain_id, namespace=namespace)
        self._tf = _Queue(TF_QUEUE)
        self._static = _Queue(TF_STATIC_QUEUE)
        self._subscribers: list[Any] = []
        self._seen_dropped = 0
        self.counters: dict[str, int] = collections.Counter()
        self.last_error = ""
        self.last_error_s = 0.0
        self._last_logged: dict[str, float] = {}
        #: whether /tf_static is read with history (an AdvancedSubscriber)
        self.static_history = False

    def attach(self, session: Any) -> None:
        """Subscribe on ``session``: ``/tf`` plainly, ``/tf_static`` with history (falls back
        to a plain subscriber, logged, where this Zenoh has no ``zenoh.ext``)."""
        self._subscribers.append(session.declare_subscriber(self.tf_key, self._tf.put))
        try:
            import zenoh.ext as zext

            sub = zext.declare_advanced_subscriber(
                session, self.static_key, self._static.put,
                history=zext.HistoryConfig(detect_late_publishers=True))
            self.static_history = True
        except (ImportError, AttributeError) as exc:
            log.warning("%s: no Zenoh AdvancedSubscriber (%s): /tf_static is read live only; "
                        "the robot must republish it", self.static_key, exc)
            sub = session.declare_subscriber(self.static_key, self._static.put)
        self._subscribers.append(sub)
        log.info("tf on %s, tf_static on %s%s", self.tf_key, self.static_key,
                 " (with history: late-joiner queries)" if self.static_history else "")

    def close(self) -> None:
        for sub in self._subscribers:
            try:
                sub.undeclare()
            except Exception:  # the session is already closed
                log.debug("undeclare failed", exc_info=True)
        self._subscribers = []

    def _fail(self, exc: RosTfError) -> None:
        self.counters[exc.counter] += 1
        self.last_error = str(exc)
        self.last_error_s = time.monotonic()
        last = self._last_logged.get(exc.counter)
        if last is None or time.monotonic() - last >= ERROR_LOG_PERIOD_S:
            self._last_logged[exc.counter] = time.monotonic()
            log.error("%s (counted %s; the message is dropped)", exc, exc.counter)

    def feed(self, buffer: TfBuffer, payload: bytes, *, static: bool) -> int:
        """Decode one payload into ``buffer``; returns how many transforms it held."""
        key = self.static_key if static else self.tf_key
        try:
            readings = decode_tf_message(payload, f"TFMessage on {key}")
        except RosTfError as exc:
            self._fail(exc)
            return 0
        self.counters["tf_static_messages" if static else "tf_messages"] += 1
        return buffer.add_readings(readings, static=static)

    def drain(self, buffer: TfBuffer) -> int:
        """Everything that arrived since the last call into ``buffer`` (static first); returns
        how many transforms were held."""
        held = sum(self.feed(buffer, p, static=True) for p in self._static.take_all())
        held += sum(self.feed(buffer, p, static=False) for p in self._tf.take_all())
        with self._tf.lock, self._static.lock:
            dropped = self._tf.dropped + self._static.dropped
            oversized = self._tf.oversized + self._static.oversized
        if dropped > self._seen_dropped:
            self.counters["tf_dropped"] += dropped - self._seen_dropped
            self._seen_dropped = dropped
        if oversized > self.counters.get("tf_oversized", 0):
            self._fail(RosTfError("tf_oversized", f"{oversized} TF message(s) over "
                                  f"{MAX_PAYLOAD_BYTES} bytes refused"))
            self.counters["tf_oversized"] = oversized
        return held

    def received(self) -> tuple[int, int]:
        """(/tf, /tf_static) messages received so far."""
        return self._tf.received, self._static.received
