"""The shape every smartedge service shares: a transport-free node and the Zenoh runner around it.

A service is a :class:`ServiceNode`: it declares what it subscribes to, handles decoded
messages, and is ticked periodically; it returns what to publish as :class:`Outgoing` items. It
never touches Zenoh, so it can be driven by a scripted inbox in tests (:class:`ScriptedRunner`)
or by :class:`ZenohRunner` in production.

Threading rule (ARCHITECTURE.md): Zenoh callbacks only append ``(key, bytes, recv_ns)`` to a
channel per subscription, bounded in messages and in bytes (:mod:`protocol.limits`), after
refusing a sample over the subscription's payload cap without copying it; one worker thread
decodes, calls the node, publishes, ticks, pings the systemd watchdog and publishes a
:class:`~protocol.messages.ServiceStatus` every second. Refused payloads are counted
``invalid`` and, when a limit refused them, ``invalid.<limit>``; overflowing channels count
``dropped``.
"""

from __future__ import annotations

import collections
import dataclasses
import gc
import logging
import math
import os
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final

from protocol import keys
from protocol.codec import decode, encode
from protocol.errors import DecodeError
from protocol.limits import LimitError, payload_cap, queue_byte_budget
from protocol.messages import Message, ServiceStatus

log = logging.getLogger(__name__)

STATUS_PERIOD_S: Final = 1.0
#: byte bound of a channel built without one (tests); subscriptions carry their own
DEFAULT_CHANNEL_BYTES: Final = 64 * 1024 * 1024
#: received bytes (accepted or refused) after which the worker hands freed heap memory back to
#: the system at its next status (see :func:`malloc_trim`)
TRIM_AFTER_BYTES: Final = 32 * 1024 * 1024
#: at how many consecutive statuses it does so
TRIMS_AFTER_BURST: Final = 3


# --------------------------------------------------------------------------------------------
# node interface
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Subscription:
    """A key expression the node listens on.

    ``message_type``: the only type accepted on it (``None`` for liveliness subscriptions).
    ``capacity``: bound, in messages, of the channel between the Zenoh thread and the worker.
    ``drop_oldest``: when full, drop the oldest sample (right for camera frames) instead of the
    newest (right when order matters more than freshness). Either way the drop is counted.
    ``max_queued_bytes``: bound, in payload bytes, of the same channel (``None``: the message
    type's default, :func:`protocol.limits.queue_byte_budget`); overflow drops like ``capacity``.
    ``max_payload_bytes``: larger samples are refused in the Zenoh callback, before their bytes
    are copied (``None``: the message type's cap, :func:`protocol.limits.payload_cap`).
    ``liveliness``: subscribe to liveliness tokens; the node gets ``alive(key, present)`` calls.
    ``max_queue_delay_s``: a sample that waited longer than this in the channel is shed when the
    worker reaches it (counted ``shed``, ``shed.<key_expr>``; ``None``: never): when the worker
    cannot keep up, the oldest inputs go first and the delay stays bounded instead of growing.
    """

    key_expr: str
    message_type: type[Message] | None = None
    capacity: int = 256
    drop_oldest: bool = True
    liveliness: bool = False
    max_queued_bytes: int | None = None
    max_payload_bytes: int | None = None
    max_queue_delay_s: float | None = None

    def __post_init__(self) -> None:
        if self.max_queue_delay_s is not None and not self.max_queue_delay_s > 0:
            raise ValueError(f"Subscription {self.key_expr}: max_queue_delay_s must be > 0, "
                             f"got {self.max_queue_delay_s}")

    @property
    def schema(self) -> str | None:
        return None if self.message_type is None else self.message_type.SCHEMA

    @property
    def payload_limit(self) -> int:
        """Largest payload (bytes) accepted on this subscription."""
        cap = payload_cap(self.schema)
        return cap if self.max_payload_bytes is None else min(cap, self.max_payload_bytes)

    @property
    def byte_budget(self) -> int:
        """Bound (bytes) of the queued payloads; at least one payload of the largest size."""
        budget = (queue_byte_budget(self.schema) if self.max_queued_bytes is None
                  else self.max_queued_bytes)
        return max(budget, self.payload_limit)


@dataclasses.dataclass(frozen=True)
class Outgoing:
    """A message to publish on ``key``; ``reliable`` selects reliable + BLOCK congestion control
    (poses, odometry, corrections) instead of best effort + DROP (detections, clouds)."""

    key: str
    message: Message
    reliable: bool = True


class ServiceNode:
    """Base class of service logic. Subclasses override what they need."""

    service: str = "service"

    def __init__(self, site: str, instance_id: str) -> None:
        self.site = site
        self.instance_id = instance_id
        self.stats = Stats()
        #: the runner's clock (ns since the Unix epoch): the wall clock under
        #: :class:`ZenohRunner`, the scripted time under :class:`ScriptedRunner`. For decisions
        #: about the transport (is an output still fresh when published), never for algorithms.
        self.clock: Callable[[], int] = time.time_ns

    def subscriptions(self) -> Sequence[Subscription]:
        return ()

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        """One decoded, validated message that arrived on ``key`` (a concrete key)."""
        return ()

    def alive(self, key: str, present: bool) -> None:
        """A liveliness token appeared (``present``) or disappeared."""

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        """Called every ``tick_period_s`` from the worker loop (wall clock ``now_ns``)."""
        return ()

    tick_period_s: float = 0.05

    def idle(self, now_ns: int) -> bool:
        """Called when no received message waits: one slice of deferred upkeep (the backend's
        pose-graph marginalizations), so that it never delays a message. Return True when a
        slice ran: the runner looks at its channels again before the next one."""
        return False

    def state(self) -> tuple[str, str]:
        """(state, detail) for the status message; override to report degradation."""
        return "ok", ""

    def peers_alive(self) -> Sequence[str]:
        return ()

    def counters(self) -> dict[str, int]:
        """Counters for the status message (override to add those of inner components)."""
        return self.stats.snapshot_counters()

    def attach(self, session: Any) -> None:
        """Called once with the open Zenoh session, before any message: for adapters that are
        Zenoh clients themselves (the ROS 2 adapter). Most nodes ignore it."""

    def close(self) -> None:
        """Release resources (files, recordings) on shutdown."""


# --------------------------------------------------------------------------------------------
# statistics
# --------------------------------------------------------------------------------------------


class Stats:
    """Counters, rates and latency percentiles of one service (worker thread only, except the
    ``dropped`` counters, which the Zenoh threads bump under the lock)."""

    def __init__(self, window: int = 2048) -> None:
        self.counters: collections.Counter[str] = collections.Counter()
        self._latencies: dict[str, collections.deque[float]] = {}
        self._events: dict[str, collections.deque[float]] = {}
        self._window = window
        self.lock = threading.Lock()

    def count(self, name: str, n: int = 1) -> None:
        with self.lock:
            self.counters[name] += n

    def event(self, stream: str, t_s: float | None = None) -> None:
        """Record one message on ``stream`` (for rates)."""
        q = self._events.setdefault(stream, collections.deque(maxlen=self._window))
        q.append(time.monotonic() if t_s is None else t_s)

    def latency(self, stage: str, seconds: float) -> None:
        q = self._latencies.setdefault(stage, collections.deque(maxlen=self._window))
        q.append(seconds)

    def rates_hz(self, horizon_s: float = 5.0) -> dict[str, float]:
        now = time.monotonic()
        out = {}
        for name, q in self._events.items():
            recent = [t for t in q if now - t <= horizon_s]
            out[name] = len(recent) / horizon_s
        return out

    def percentiles_ms(self, q: float) -> dict[str, float]:
        out = {}
        for stage, values in self._latencies.items():
            if values:
                ordered = sorted(values)
                idx = min(len(ordered) - 1, max(0, math.ceil(q * len(ordered)) - 1))
                out[stage] = ordered[idx] * 1e3
        return out

    def snapshot_counters(self) -> dict[str, int]:
        with self.lock:
            return dict(self.counters)


def make_status(
    node: ServiceNode, seq: int, started_s: float, state: str | None = None
) -> ServiceStatus:
    node_state, detail = node.state()
    return ServiceStatus(
        service=node.service,
        instance_id=node.instance_id,
        stamp_ns=time.time_ns(),
        seq=seq,
        state=state or node_state,
        uptime_s=max(0.0, time.monotonic() - started_s),
        rates_hz=node.stats.rates_hz(),
        latency_p50_ms=node.stats.percentiles_ms(0.50),
        latency_p99_ms=node.stats.percentiles_ms(0.99),
        counters=node.counters(),
        peers_alive=tuple(node.peers_alive()),
        detail=detail[:4000],
    )


def count_invalid(node: ServiceNode, key: str, exc: DecodeError) -> None:
    """Count and log one refused payload: ``invalid``, plus ``invalid.<limit>`` when a limit of
    :mod:`protocol.limits` refused it (thread-safe: the Zenoh callbacks refuse oversized
    samples themselves)."""
    node.stats.count("invalid")
    if isinstance(exc, LimitError):
        node.stats.count(f"invalid.{exc.limit}")
    log.warning("invalid message on %s: %s", key, exc.reason)


def dispatch(
    node: ServiceNode, sub: Subscription, key: str, payload: bytes, recv_ns: int
) -> list[Outgoing]:
    """Decode one payload and hand it to the node; bad input is logged, counted and dropped.

    Never raises: a node that raises on a message is counted under ``handler_errors`` and the
    service keeps running."""
    node.stats.count("received")
    try:
        check_subscription_size(sub, len(payload))
        message = decode(payload, expected=sub.message_type)
    except DecodeError as exc:
        count_invalid(node, key, exc)
        return []
    try:
        return list(node.handle(key, message, recv_ns) or ())
    except Exception:
        node.stats.count("handler_errors")
        log.exception("%s failed to handle a message on %s", node.service, key)
        return []


def check_subscription_size(sub: Subscription, size: int) -> None:
    """Raise :class:`~protocol.limits.LimitError` when a payload of ``size`` bytes is over the
    subscription's limit (its message type's cap, or a tighter ``max_payload_bytes``)."""
    if size > sub.payload_limit:
        raise LimitError("payload_too_large", f"payload of {size} bytes exceeds the "
                         f"{sub.payload_limit}-byte limit of {sub.key_expr}")


# --------------------------------------------------------------------------------------------
# systemd notify (no dependency: the protocol is one datagram)
# --------------------------------------------------------------------------------------------


def sd_notify(state: str) -> bool:
    """Send ``state`` (``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``, ``STATUS=...``) to systemd.

    A no-op returning False when not started by systemd with ``Type=notify``."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
        return True
    except OSError as exc:
        log.debug("sd_notify failed: %s", exc)
        return False


def watchdog_period_s() -> float | None:
    """Half the systemd watchdog interval (``WATCHDOG_USEC``), or None when not supervised."""
    usec = os.environ.get("WATCHDOG_USEC")
    if not usec or not usec.isdigit():
        return None
    return int(usec) / 2e6


# --------------------------------------------------------------------------------------------
# runners
# --------------------------------------------------------------------------------------------


class _Channel:
    """Bounded FIFO between Zenoh threads and the worker, bounded in messages (``capacity``) and
    in payload bytes (``max_bytes``); overflow drops the oldest or the newest sample and counts
    it (``dropped``, ``dropped.<name>``, and ``dropped.byte_budget`` when the bytes overflowed).
    With ``max_delay_ns``, :meth:`pop` sheds the samples that waited longer than that (counted
    ``shed``, ``shed.<name>``): load shedding, oldest first."""

    def __init__(self, capacity: int, drop_oldest: bool, stats: Stats, name: str,
                 max_bytes: int = DEFAULT_CHANNEL_BYTES, max_delay_ns: int | None = None) -> None:
        self._q: collections.deque[tuple[str, bytes, int]] = collections.deque()
        self._capacity = max(1, capacity)
        self._max_bytes = max(1, max_bytes)
        self._bytes = 0
        self._drop_oldest = drop_oldest
        self._stats = stats
        self._name = name
        self._max_delay_ns = max_delay_ns
        self._lock = threading.Lock()  # Zenoh threads put, the worker pops

    def put(self, item: tuple[str, bytes, int]) -> None:
        size = len(item[1])
        dropped = over_bytes = 0
        with self._lock:
            while len(self._q) >= self._capacity or self._bytes + size > self._max_bytes:
                over_bytes += int(len(self._q) < self._capacity)  # not full in count
                dropped += 1
                if not self._drop_oldest or not self._q:
                    break
                self._bytes -= len(self._q.popleft()[1])
            else:
                self._q.append(item)
                self._bytes += size
        if dropped:
            self._stats.count("dropped", dropped)
            self._stats.count(f"dropped.{self._name}", dropped)
        if over_bytes:
            self._stats.count("dropped.byte_budget", over_bytes)

    def pop(self, now_ns: int | None = None) -> tuple[str, bytes, int] | None:
        """The oldest sample, or ``None``; with a delay bound, samples received before
        ``now_ns`` minus the bound are shed on the way (``now_ns`` defaults to the wall clock,
        the clock of the receive stamps)."""
        shed = 0
        with self._lock:
            if self._max_delay_ns is not None and self._q:
                oldest_ok = (time.time_ns() if now_ns is None else now_ns) - self._max_delay_ns
                while self._q and self._q[0][2] < oldest_ok:
                    self._bytes -= len(self._q.popleft()[1])
                    shed += 1
            try:
                item = self._q.popleft()
            except IndexError:
                item = None
            else:
                self._bytes -= len(item[1])
        if shed:
            self._stats.count("shed", shed)
            self._stats.count(f"shed.{self._name}", shed)
        return item

    @property
    def queued_bytes(self) -> int:
        return self._bytes

    def __len__(self) -> int:
        return len(self._q)


def _load_malloc_trim() -> Callable[[], object] | None:
    try:
        import ctypes

        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return lambda: trim(0)


_MALLOC_TRIM: Final = _load_malloc_trim()


def malloc_trim() -> bool:
    """Hand the C heap's free memory back to the system (glibc ``malloc_trim(0)``, every arena;
    ~0.2 ms); False where the C library has none.

    Zenoh reassembles large samples in its own threads' malloc arenas, and glibc keeps those
    pages after they are freed: 20 refused samples of 50 MB left the backend ~90 MiB above its
    baseline for good; trimmed, it came back to within ~25 MiB of it (docs/reliability.md)."""
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM()
    return True


class ZenohRunner:
    """Runs a node on a Zenoh session until :meth:`stop` (or SIGINT/SIGTERM via
    :meth:`install_signal_handlers`).

    The worker loop: drain the channels (round-robin, bounded per pass), tick the node on its
    period, publish outputs, publish the status every second, ping the systemd watchdog.
    """

    def __init__(self, node: ServiceNode, zenoh_config: Any, *, status: bool = True) -> None:
        self.node = node
        self._config = zenoh_config
        self._status = status
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._publishers: dict[tuple[str, bool], Any] = {}
        self.session: Any = None
        self.started = threading.Event()
        #: bytes received since the last trim, bumped by the Zenoh callbacks (racy: a hint)
        self._received_bytes = 0

    def stop(self, *_: object) -> None:
        """Stop the worker loop (from another thread; a signal handler: :meth:`_on_signal`)."""
        self._stop.set()
        self._wake.set()

    def _on_signal(self, *_: object) -> None:
        """SIGINT / SIGTERM. Python runs the handler in the main thread between two bytecodes
        of the worker loop, which may be inside the wake event's lock (clearing it, or in its
        wait): setting that event here would wait for the lock forever, and the service would
        hang until killed (seen once in a CI run: a backend that did not stop within 20 s).
        Only the stop flag then, whose lock the loop never takes; its wait is bounded
        (50 ms), so it sees the flag on its next pass."""
        self._stop.set()

    def install_signal_handlers(self) -> None:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._on_signal)

    def _publisher(self, key: str, reliable: bool) -> Any:
        import zenoh

        pub = self._publishers.get((key, reliable))
        if pub is None:
            pub = self.session.declare_publisher(
                key,
                encoding=zenoh.Encoding("application/msgpack"),
                congestion_control=(
                    zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
                ),
                reliability=zenoh.Reliability.RELIABLE
                if reliable
                else zenoh.Reliability.BEST_EFFORT,
            )
            self._publishers[(key, reliable)] = pub
        return pub

    def publish(self, items: Iterable[Outgoing]) -> None:
        for item in items:
            try:
                self._publisher(item.key, item.reliable).put(encode(item.message))
                self.node.stats.count("published")
            except Exception:
                self.node.stats.count("publish_errors")
                log.exception("publishing on %s failed", item.key)

    def run(self) -> int:
        """Blocking: returns 0 after a clean stop."""
        import zenoh

        node = self.node
        started_s = time.monotonic()
        channels: list[tuple[Subscription, _Channel]] = []
        liveliness_events: collections.deque[tuple[str, bool]] = collections.deque(maxlen=4096)
        with zenoh.open(self._config) as session:
            self.session = session
            node.attach(session)
            handles = []
            for sub in node.subscriptions():
                if sub.liveliness:

                    def on_token(sample: Any, _q=liveliness_events) -> None:
                        _q.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))
                        self._wake.set()

                    handles.append(
                        session.liveliness().declare_subscriber(
                            sub.key_expr, on_token, history=True
                        )
                    )
                    continue
                max_delay_ns = (None if sub.max_queue_delay_s is None
                                else round(sub.max_queue_delay_s * 1e9))
                channel = _Channel(sub.capacity, sub.drop_oldest, node.stats, sub.key_expr,
                                   sub.byte_budget, max_delay_ns)
                channels.append((sub, channel))

                def on_sample(sample: Any, _c: _Channel = channel, _s: Subscription = sub) -> None:
                    key = str(sample.key_expr)
                    size = len(sample.payload)
                    self._received_bytes += size
                    try:  # an oversized sample is refused before its bytes are copied
                        check_subscription_size(_s, size)
                    except LimitError as exc:
                        node.stats.count("received")
                        count_invalid(node, key, exc)
                        return
                    _c.put((key, sample.payload.to_bytes(), time.time_ns()))
                    self._wake.set()

                handles.append(session.declare_subscriber(sub.key_expr, on_sample))
            token = session.liveliness().declare_token(
                keys.alive_key(node.site, node.service, node.instance_id)
            )
            status_key = keys.status_key(node.site, node.service, node.instance_id)
            # what start-up made (modules, the site, compiled solvers, Zenoh's handles) lives as
            # long as the service: out of the collector's view, so that a full collection scans
            # only what the service made since (one took 147 ms in a fleet backend without this)
            gc.collect()
            gc.freeze()
            sd_notify("READY=1")
            self.started.set()
            log.info("%s %s running", node.service, node.instance_id)
            watchdog = watchdog_period_s()
            next_tick = next_status = next_watchdog = time.monotonic()
            if not self._status:
                next_status = math.inf  # never due (the idle wait would spin on it)
            status_seq = 0
            trims_left = 0
            try:
                while not self._stop.is_set():
                    self._wake.clear()
                    busy = False
                    while liveliness_events:
                        key, present = liveliness_events.popleft()
                        node.alive(key, present)
                    for sub, channel in channels:
                        if not channel:
                            continue  # empty (a length read, no lock): most of them, mostly
                        for _ in range(64):  # bounded per pass: fairness between keys
                            if self._stop.is_set():  # a stop waits for one message, not a pass
                                break
                            item = channel.pop()
                            if item is None:
                                break
                            busy = True
                            self.publish(dispatch(node, sub, *item))
                    now = time.monotonic()
                    if now >= next_tick:
                        next_tick = now + node.tick_period_s
                        try:
                            self.publish(node.tick(time.time_ns()) or ())
                        except Exception:
                            node.stats.count("handler_errors")
                            log.exception("%s tick failed", node.service)
                    if self._status and now >= next_status:
                        next_status = now + STATUS_PERIOD_S
                        try:
                            status = make_status(node, status_seq, started_s)
                        except Exception:
                            node.stats.count("status_errors")
                            log.exception("%s: building the status failed", node.service)
                        else:
                            self.publish([Outgoing(status_key, status)])
                            status_seq += 1
                        if self._received_bytes >= TRIM_AFTER_BYTES:
                            self._received_bytes = 0
                            trims_left = TRIMS_AFTER_BURST
                        if trims_left:  # Zenoh frees its buffers a little after the burst
                            trims_left -= 1
                            malloc_trim()
                    if watchdog is not None and now >= next_watchdog:
                        next_watchdog = now + watchdog
                        sd_notify("WATCHDOG=1")
                    if not busy:
                        try:
                            upkeep = node.idle(time.time_ns())
                        except Exception:
                            upkeep = False
                            node.stats.count("handler_errors")
                            log.exception("%s idle upkeep failed", node.service)
                        if upkeep:
                            continue  # the channels first, then the next slice
                        timeout = max(0.0, min(next_tick, next_status) - time.monotonic())
                        self._wake.wait(min(timeout, 0.05))
            finally:
                sd_notify("STOPPING=1")
                unprocessed = sum(len(channel) for _, channel in channels)
                if unprocessed:
                    node.stats.count("unprocessed_at_stop", unprocessed)
                log.info("%s %s stopping (%d received messages left unprocessed)", node.service,
                         node.instance_id, unprocessed)
                if self._status:
                    try:
                        final = make_status(node, status_seq, started_s, "stopping")
                        self.publish([Outgoing(status_key, final)])
                    except Exception:
                        log.exception("%s: building the final status failed", node.service)
                token.undeclare()
                for h in handles:
                    h.undeclare()
                node.close()
                self.session = None
        return 0


class ScriptedRunner:
    """Drives a node without Zenoh: feed ``(key, payload_bytes)`` items, collect outputs.

    The same decode/dispatch path as :class:`ZenohRunner`, so node logic (including bad-input
    handling) is tested without a network. The node's :attr:`~ServiceNode.clock` reads the
    scripted time: the ``recv_ns`` of the last :meth:`feed` or the ``now_ns`` of the last
    :meth:`tick`."""

    def __init__(self, node: ServiceNode) -> None:
        self.node = node
        self.published: list[Outgoing] = []
        self._subs = list(node.subscriptions())
        self._now_ns = time.time_ns()
        node.clock = lambda: self._now_ns  # the scripted time: the last feed's or tick's

    def _match(self, key: str) -> Subscription | None:
        import fnmatch

        for sub in self._subs:
            pattern = sub.key_expr.replace("**", "\0").replace("*", "[!/]*").replace("\0", "*")
            if not sub.liveliness and fnmatch.fnmatchcase(key, pattern):
                return sub
        return None

    def feed(self, key: str, payload: bytes, recv_ns: int | None = None) -> list[Outgoing]:
        sub = self._match(key)
        if sub is None:
            raise KeyError(f"node does not subscribe to {key}")
        self._now_ns = time.time_ns() if recv_ns is None else recv_ns
        out = dispatch(self.node, sub, key, payload, self._now_ns)
        self.published.extend(out)
        return out

    def tick(self, now_ns: int) -> list[Outgoing]:
        """The node's tick at ``now_ns``, then its idle upkeep (a scripted run has no message
        waiting between two calls, as a worker between two bursts)."""
        self._now_ns = now_ns
        out = list(self.node.tick(now_ns) or ())
        self.published.extend(out)
        self.idle()
        return out

    def idle(self) -> int:
        """Run the node's idle upkeep until it has none left; the number of slices."""
        slices = 0
        while self.node.idle(self._now_ns):
            slices += 1
        return slices


def run_node(
    node: ServiceNode, zenoh_config: Any, *, on_started: Callable[[ZenohRunner], None] | None = None
) -> int:
    """Run ``node`` until SIGINT/SIGTERM (the ``main`` of every service)."""
    runner = ZenohRunner(node, zenoh_config)
    runner.install_signal_handlers()
    if on_started is not None:
        threading.Thread(
            target=lambda: (runner.started.wait(), on_started(runner)), daemon=True
        ).start()
    return runner.run()


#: exit status of a service that cannot start with its configuration (sysexits.h EX_CONFIG)
EXIT_CONFIG: Final = 78


def service_main(
    name: str,
    argv: Sequence[str],
    build_parser: Callable[[], Any],
    build_node: Callable[[Any], ServiceNode],
) -> int:
    """The ``main`` of a service: parse ``argv``, build the node and the Zenoh config, run until
    SIGINT/SIGTERM. A bad site file, id, model or option (a
    :class:`~protocol.errors.SmartedgeError`) is reported on stderr with exit code
    :data:`EXIT_CONFIG` (78), which the systemd units list in ``RestartPreventExitStatus``: a
    configuration error waits for a person instead of restarting every few seconds. Anything
    else is a bug and surfaces with its traceback (exit 1, so systemd restarts the service)."""
    import sys

    from core.session import make_config, options_from_args
    from protocol.errors import SmartedgeError

    args = build_parser().parse_args(list(argv))
    try:
        node = build_node(args)
        config = make_config(options_from_args(args))
    except SmartedgeError as exc:
        print(f"smartedge {name}: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    return run_node(node, config)
