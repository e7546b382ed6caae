"""The ownership of robots on the bus: the Zenoh side of :mod:`backend_service.ownership`.

:class:`OwnershipTokens` declares and undeclares a backend's owner and area liveliness tokens
and runs the liveliness gets (the start-up sync, waited for; the periodic resync, taken on a
later tick) that feed the pure :class:`~backend_service.ownership.OwnershipTable`;
:class:`BackendOwnership` bundles the two for a :class:`~core.runtime.ServiceNode` (its
liveliness subscriptions, ``attach``, ``alive``, ``tick``, ``may_publish``). The rules
themselves (membership, assignment, exclusive publishing, stalls, areas) are the table's and
are described in :mod:`backend_service.ownership`.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from backend_service.areas import AreaMap
from backend_service.ownership import (
    BACKEND_SERVICE,
    DEFAULT_CONFIRM_S,
    DEFAULT_JOIN_DELAY_S,
    DEFAULT_RESYNC_S,
    DEFAULT_STALL_S,
    DEFAULT_SYNC_TIMEOUT_S,
    SYNC_RETRY_S,
    Decision,
    OwnershipTable,
    parse_liveliness,
)
from core.runtime import Subscription
from core.session import drain_replies
from protocol import keys
from protocol.messages import NS_PER_S

log = logging.getLogger(__name__)


@dataclasses.dataclass
class _PendingSync:
    """The liveliness gets of one :meth:`OwnershipTokens.start_sync`: when they went out, their
    timeout, each key expression's reply channel, and the replies taken so far."""

    started_s: float
    timeout_s: float
    handlers: list[tuple[str, Any]]
    #: the table's vanish_seq when the gets went out (OwnershipTable.resync)
    vanish_seq: int = 0
    replies: list[tuple[str, Any]] = dataclasses.field(default_factory=list)


class OwnershipTokens:
    """The Zenoh side of :class:`OwnershipTable`: this backend's owner tokens on ``session``.

    :meth:`sync` runs the start-up liveliness get (backends and owner tokens already on the
    bus) into the table and marks it synced; :meth:`apply` declares and undeclares the tokens
    of a :class:`Decision`; :meth:`close` undeclares them all. Call them from one thread (the
    service's worker); the liveliness subscriptions themselves are the runner's
    (``Subscription(..., liveliness=True)`` feeding :meth:`OwnershipTable.on_liveliness`).
    """

    def __init__(self, session: Any, site: str, table: OwnershipTable) -> None:
        self.session = session
        self.site = site
        self.table = table
        self._tokens: dict[str, Any] = {}
        self._area_tokens: dict[str, Any] = {}
        self._pending: _PendingSync | None = None

    def sync(self, now_ns: Callable[[], int], timeout_s: float = DEFAULT_SYNC_TIMEOUT_S) -> int:
        """Ask the bus for the backends and owner tokens that exist and hand them to
        :meth:`OwnershipTable.resync`, waiting for the answer (the start-up sync); returns how
        many tokens came back. A failed get (or an error reply) leaves the table unsynced (no
        claims) and raises."""
        self.start_sync(timeout_s)
        while (n := self.poll_sync(now_ns)) is None:
            time.sleep(0.002)
        return n

    def start_sync(self, timeout_s: float = DEFAULT_SYNC_TIMEOUT_S) -> None:
        """Send the liveliness gets of :meth:`sync` and return at once; :meth:`poll_sync` takes
        the answer when it is in. The periodic resync runs this way: a get waits for replies
        through the routers (1-10 ms on a loaded fleet bench), which the worker spent blocked
        every second, with every robot's frame-sets queued behind it."""
        key_exprs = [keys.alive_key(self.site, BACKEND_SERVICE, "*"),
                     keys.owner_key(self.site, "*", "*")]
        if self.table.areas is not None:
            key_exprs.insert(0, keys.area_key(self.site, "*", "*"))
        liveliness = self.session.liveliness()
        seq = self.table.vanish_seq  # before the gets: what vanishes after may be in the answer
        self._pending = _PendingSync(
            time.monotonic(), timeout_s,
            [(k, liveliness.get(k, timeout=timeout_s)) for k in key_exprs], seq)

    @property
    def syncing(self) -> bool:
        """Whether the gets of :meth:`start_sync` are out and not taken yet."""
        return self._pending is not None

    def poll_sync(self, now_ns: Callable[[], int]) -> int | None:
        """The answer of :meth:`start_sync`, without waiting: ``None`` while a get is still
        out; when all are over, the tokens go to :meth:`OwnershipTable.resync` and their
        count is returned. An error reply or a get cut short by its timeout raises (the table
        stays as it was)."""
        pending = self._pending
        if pending is None:
            raise RuntimeError("poll_sync without start_sync")
        over = True
        try:
            for key_expr, handler in pending.handlers:
                replies, done = drain_replies(handler)
                pending.replies.extend((key_expr, r) for r in replies)
                over &= done
        except Exception:
            self._pending = None  # a broken channel: the next sync starts afresh
            raise
        if not over:
            return None
        self._pending = None
        elapsed = time.monotonic() - pending.started_s
        if elapsed >= 0.9 * pending.timeout_s:  # cut short: maybe not all
            raise TimeoutError(f"the liveliness get took {elapsed:.1f} s")
        members: list[str] = []
        owners: list[tuple[str, str]] = []
        areas: list[tuple[str, str]] = []
        for key_expr, reply in pending.replies:
            if reply.ok is None:
                raise RuntimeError(f"liveliness get {key_expr}: error reply {reply.err}")
            parsed = parse_liveliness(str(reply.ok.key_expr))
            if parsed is None or parsed[0] != self.site:
                continue
            if parsed[1] == "alive":
                members.append(parsed[3])
            elif parsed[1] == "area":
                areas.append((parsed[2], parsed[3]))
            else:
                owners.append((parsed[2], parsed[3]))
        self.table.resync(members, owners, now_ns(), areas, since_vanish_seq=pending.vanish_seq)
        log.debug("backend %s: ownership synced (%d backends, %d owner tokens on the bus)",
                  self.table.instance_id, len(members), len(owners))
        return len(members) + len(owners) + len(areas)

    def apply(self, decision: Decision) -> None:
        """Undeclare the released robots' tokens, then declare the claimed ones."""
        for robot in decision.release:
            token = self._tokens.pop(robot, None)
            if token is not None:
                token.undeclare()
        for robot in decision.claim:
            if robot not in self._tokens:
                self._tokens[robot] = self.session.liveliness().declare_token(
                    keys.owner_key(self.site, robot, self.table.instance_id))

    def declare_areas(self) -> None:
        """Declare this backend's area tokens (once; before its backend token, so that the
        others know its areas when it starts to count)."""
        for area in sorted(self.table.own_areas):
            if area not in self._area_tokens:
                self._area_tokens[area] = self.session.liveliness().declare_token(
                    keys.area_key(self.site, area, self.table.instance_id))

    def close(self) -> None:
        for token in [*self._tokens.values(), *self._area_tokens.values()]:
            token.undeclare()
        self._tokens.clear()
        self._area_tokens.clear()


class BackendOwnership:
    """Ownership for a backend :class:`~core.runtime.ServiceNode`: add
    :meth:`subscriptions` to the node's, and call :meth:`attach`, :meth:`alive` and
    :meth:`tick` from the node's methods of the same names; publish an estimate of robot R only
    while :meth:`may_publish` (R, now).

    Off until :meth:`attach` (a node driven by :class:`~core.runtime.ScriptedRunner` has no
    bus and publishes every robot); on a bus, nothing is published before the start-up
    liveliness get has returned (retried every :data:`SYNC_RETRY_S` when it failed), and the
    get runs again every ``resync_s`` (:data:`DEFAULT_RESYNC_S`) to correct what the
    subscriptions missed.
    """

    def __init__(self, site: str, instance_id: str, robots: Sequence[str], *, started_ns: int,
                 pinned: Mapping[str, str] | None = None,
                 confirm_s: float = DEFAULT_CONFIRM_S,
                 join_delay_s: float = DEFAULT_JOIN_DELAY_S,
                 stall_s: float = DEFAULT_STALL_S,
                 resync_s: float = DEFAULT_RESYNC_S,
                 areas: AreaMap | None = None,
                 own_areas: Sequence[str] = ()) -> None:
        self.site = site
        self.resync_ns = round(resync_s * NS_PER_S)
        self.table = OwnershipTable(instance_id, robots, started_ns=started_ns, pinned=pinned,
                                    confirm_s=confirm_s, join_delay_s=join_delay_s,
                                    stall_s=stall_s, areas=areas, own_areas=own_areas)
        self.tokens: OwnershipTokens | None = None
        self._clock: Callable[[], int] | None = None
        self._next_sync_ns = 0
        self._online = True
        self._was_synced = False  # whether the table was synced when the gets went out
        #: another backend with this instance id was on the bus at start: publish nothing
        self.duplicate = False

    @property
    def active(self) -> bool:
        """Whether a bus is attached (ownership decides what is published)."""
        return self.tokens is not None

    def subscriptions(self, *, members: bool = True) -> list[Subscription]:
        """The liveliness the table needs: the owner tokens of the site and, with ``members``,
        the backends' tokens (leave it out when the node already watches ``alive/*/*``: route
        those events to :meth:`alive` too)."""
        subs = [Subscription(keys.owner_key(self.site, "*", "*"), liveliness=True)]
        if self.table.areas is not None:
            subs.append(Subscription(keys.area_key(self.site, "*", "*"), liveliness=True))
        if members:
            subs.append(Subscription(keys.alive_key(self.site, BACKEND_SERVICE, "*"),
                                     liveliness=True))
        return subs

    def attach(self, session: Any, clock: Callable[[], int]) -> None:
        """The node's session is open, its own liveliness token not declared yet: refuse to
        publish anything if a backend with this instance id is already on the bus (both would
        take its tokens for their own), else sync the tokens on the bus (``clock``: the
        node's)."""
        self.tokens = OwnershipTokens(session, self.site, self.table)
        self._clock = clock
        me = self.table.instance_id
        if session_connected(session):
            try:
                twins = list(session.liveliness().get(
                    keys.alive_key(self.site, BACKEND_SERVICE, me), timeout=DEFAULT_SYNC_TIMEOUT_S))
            except Exception:
                log.exception("backend %s: the liveliness get for its own id failed", me)
                twins = []
            if any(reply.ok is not None for reply in twins):
                self.duplicate = True
                self.table.counters["ownership.duplicate_instance"] += 1
                log.error("backend %s: another backend with the id %r is on the bus; this one "
                          "publishes nothing (give each backend its own --id)", me, me)
                return
        self.tokens.declare_areas()
        self._sync(wait=True)

    def _sync(self, wait: bool = False) -> None:
        """Start the liveliness gets (``wait``: and take their answer now, the start-up sync;
        else a later :meth:`tick` takes it, :meth:`_take_sync`)."""
        assert self.tokens is not None and self._clock is not None
        if not session_connected(self.tokens.session):
            return  # nobody to ask: the next tick with a link tries
        self._was_synced = self.table.is_synced
        try:
            if wait:
                self._synced(self.tokens.sync(self._clock))
            else:
                self.tokens.start_sync()
        except Exception:
            self._sync_failed()

    def _take_sync(self) -> None:
        """The answer of the gets :meth:`_sync` sent, if it is in (never waits)."""
        assert self.tokens is not None and self._clock is not None
        try:
            n = self.tokens.poll_sync(self._clock)
        except Exception:
            self._sync_failed()
        else:
            if n is not None:
                self._synced(n)

    def _sync_failed(self) -> None:
        assert self._clock is not None
        was_synced = self.table.is_synced
        self.table.counters["ownership.sync_errors"] += 1
        self._next_sync_ns = self._clock() + round(SYNC_RETRY_S * NS_PER_S)
        log.exception("backend %s: the liveliness get of the backends and owner tokens "
                      "failed%s", self.table.instance_id,
                      "" if was_synced else "; publishing nothing until it succeeds")

    def _synced(self, n: int) -> None:
        assert self._clock is not None
        self._next_sync_ns = self._clock() + self.resync_ns
        if not self._was_synced:
            log.info("backend %s: ownership synced (%d tokens on the bus)",
                     self.table.instance_id, n)

    def alive(self, key: str, present: bool, now_ns: int) -> bool:
        """One liveliness event of the runner; True when it was the table's (a backend or an
        owner token of this site), False for other services' tokens."""
        parsed = parse_liveliness(key)
        if parsed is None or parsed[0] != self.site:
            return False
        if parsed[1] == "alive" and parsed[2] != BACKEND_SERVICE:
            return False
        return self.table.on_liveliness(self.site, key, present, now_ns)

    def tick(self, now_ns: int) -> Decision:
        """Apply the claims and releases due now (before the tick publishes anything)."""
        if self.tokens is None or self.duplicate:
            return Decision()
        if not session_connected(self.tokens.session):
            if self._online:
                self._online = False
                decision = self.table.on_disconnected(now_ns)
                self.tokens.apply(decision)
                return decision
            return Decision()
        self._online = True
        if self.tokens.syncing:
            self._take_sync()
        elif now_ns >= self._next_sync_ns:  # the first sync, a retry, or the periodic one
            self._sync()
        decision = self.table.decide(now_ns)
        if decision:
            self.tokens.apply(decision)
        return decision

    def pipeline_robots(self, now_ns: int) -> frozenset[str] | None:
        """The robots whose full pipeline this backend runs (:meth:`OwnershipTable.to_run`);
        ``None``: no decision (no bus, or not synced since the start or since the view was
        dropped: whatever runs goes on running). A backend with a duplicate id runs none."""
        if self.tokens is not None and self.duplicate:
            return frozenset()
        if self.tokens is None or not self.table.is_synced:
            return None
        return self.table.to_run(now_ns)

    def observe(self, robot_id: str, x_m: float, y_m: float, stamp_ns: int) -> None:
        """A pose of ``robot_id`` seen on the bus (fused or its own localization): its area
        (:meth:`OwnershipTable.on_robot_position`)."""
        self.table.on_robot_position(robot_id, x_m, y_m, stamp_ns)

    def may_publish(self, robot_id: str, now_ns: int) -> bool:
        """Whether estimates of ``robot_id`` go out now (always, without a bus)."""
        if not self.active:
            return True
        return not self.duplicate and self.table.may_publish(robot_id, now_ns)

    def detail(self, now_ns: int) -> str:
        """Status text: ``ownership: backends ...; owns ...; pending ...`` (empty without a
        bus)."""
        if self.duplicate:
            return (f"ownership: another backend runs with the id {self.table.instance_id!r}; "
                    f"this one publishes nothing")
        return f"ownership: {self.table.summary(now_ns)}" if self.active else ""

    def counters(self) -> dict[str, int]:
        return dict(self.table.counters)

    def close(self) -> None:
        if self.tokens is not None:
            self.tokens.close()


def session_connected(session: Any) -> bool:
    """Whether a Zenoh session has a link to any other session (router, peer or client)."""
    info = session.info
    transports = getattr(info, "transports", None)  # eclipse-zenoh >= 1.5; lists clients too
    if transports is not None:
        return any(True for _ in transports())
    return any(True for _ in info.routers_zid()) or any(True for _ in info.peers_zid())
