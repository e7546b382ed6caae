"""Which backend publishes which robot, when several ``smartedge backend`` processes share a site.

Zenoh is the distributed engine (docs/architecture.md, "Several robots, several machines"): the
membership is the backends' liveliness tokens, the ownership their owner tokens; nothing here
sends a message of its own.

- **Membership**: the live backends of the site are the liveliness tokens
  ``smartedge/<site>/alive/backend/<instance>`` that every backend's runner declares
  (:class:`~core.runtime.ZenohRunner`). A backend that appeared counts after
  ``join_delay_s`` (a flapping backend moves no robot); one that vanished stops counting at once.
- **Assignment**: each robot goes to the counted backend of highest rendezvous
  (highest-random-weight) score ``blake2b(robot, instance)``: every backend computes the same
  choice from the same members, and a backend joining or leaving moves only the robots it takes
  or held. The site file may pin a robot to an instance (``backend: {owners: {robot:
  instance}}``); a pinned robot goes to its instance whenever that one is live, else by score.
- **Exclusive publishing**: a backend publishes estimates of robot R only while it holds R's
  owner token ``smartedge/<site>/owner/<R>/<instance>`` (:func:`protocol.keys.owner_key`). The
  handover rules:

  1. it claims R (declares the token) only when it is R's choice, has synced the tokens that
     already exist (a liveliness get at start), and sees no other owner token for R;
  2. it publishes R only once the token is ``confirm_s`` old and still no other owner token of R
     is in sight;
  3. a backend that stops being R's choice stops publishing R at once and then undeclares;
  4. two backends that claimed at once both see the other's token within the bus's propagation
     delay: the lower-ranked one (pin, then score, then instance name) withdraws at once, the
     higher one publishes after the withdrawn token vanished.

  Rule 3 orders a handover (the old owner stops before its token goes, the new one claims after
  seeing it go); rule 2 covers simultaneous claims as long as a token reaches every backend within
  ``confirm_s / 2`` (milliseconds through a router; ``confirm_s`` defaults to 0.2 s). When an owner
  dies, Zenoh drops its tokens as soon as the router sees its session go (a SIGKILL closes the TCP
  link at once; a frozen host is noticed at the session lease), and the next backend by score
  claims and publishes ``confirm_s`` later.
- **Stalls and lost links**: a backend whose worker did not decide for ``stall_s`` (frozen,
  swapped out, SIGSTOP), or whose session has no link left, drops every claim (and its tokens)
  and its view of the others, and starts over from a liveliness get like a new one. A frozen
  backend's session may re-declare its old tokens when it reconnects, before its worker runs:
  the other backend stops publishing at the sight of them, and the thawed one withdraws them
  on its first decision.
- **Areas** (backend_service/areas.py): on a site split into areas, a backend started with
  ``--area`` announces each area it serves with a liveliness token
  ``smartedge/<site>/area/<area>/<instance>`` (declared before its backend token; a backend
  without one serves every area). A robot's candidates are the counted backends that serve
  the area it is in (:meth:`OwnershipTable.on_robot_position`, fed with the poses on the bus);
  the rendezvous score picks among them, a pin still wins, and a robot whose area has no live
  backend (or whose area is not known yet) goes by score over all of them. A robot that
  crosses into another area changes its choice like a backend leaving: the old owner stops
  publishing at once and releases (rule 3), the new one claims when the token is gone and
  publishes ``confirm_s`` later (its estimates meanwhile are withheld and counted), so the
  hand-over costs a few frame-sets and never two publishers. The backends agree on the area
  up to the bus's delay; where two views briefly differ, rules 1, 2 and 4 still allow one
  publisher.
- **Missed events**: a synced backend runs the liveliness get again every ``resync_s`` and
  adds what its subscriptions missed (they do not replay what happened while a session was cut
  off); it removes nothing on a get's word, only on a vanishing token, and it does not bring
  back a token whose vanishing event came after the get went out (the answer predates it; a
  hand-over during a get would otherwise wait for a gone token for good). Only the start-up get
  is waited for; the periodic one goes out on one tick and its answer is taken on a later one
  (:mod:`backend_service.ownership_tokens`: ``start_sync``, ``poll_sync``), so the worker
  never stands still for its round trip through the routers.

This module is the pure part (injected time, no Zenoh): :class:`OwnershipTable`; feed it
members and owner tokens, call :meth:`~OwnershipTable.decide` on the tick and gate every
published estimate on :meth:`~OwnershipTable.may_publish`. The Zenoh side is
:mod:`backend_service.ownership_tokens`: ``OwnershipTokens`` applies the decisions (declares and
undeclares the tokens, runs the liveliness gets) and ``BackendOwnership`` bundles both for a
:class:`~core.runtime.ServiceNode` (its liveliness subscriptions, ``attach``, ``alive``,
``tick`` and status calls).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import hashlib
import logging
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Final

from backend_service.areas import AreaMap
from protocol import keys
from protocol.errors import ValidationError
from protocol.messages import NS_PER_S
from protocol.validation import check_id

log = logging.getLogger(__name__)

#: the liveliness service name of a backend (``alive/backend/<instance>``)
BACKEND_SERVICE: Final = "backend"
#: how long a claimed owner token must stand, with no other owner token of the robot in sight,
#: before the backend publishes the robot: at least twice the time a token takes to reach every
#: backend (rule 2 of the module docstring)
DEFAULT_CONFIRM_S: Final = 0.2
#: how long a backend that appeared must stay before it counts (damps a flapping backend)
DEFAULT_JOIN_DELAY_S: Final = 0.5
#: a worker that did not decide for this long stalled: it publishes nothing until it has
#: re-synced the tokens and re-confirmed its claims (keep it below the session lease, so that
#: a stall long enough for the router to drop the session always trips it)
DEFAULT_STALL_S: Final = 1.0
#: on a site with areas, how long after its start a backend waits for a robot's first pose on
#: the bus before it treats the robot's area as unknown (and the robot as anybody's): claiming
#: it at once by score over all backends would hand it to the backend of its area a moment
#: later (a release and a claim per robot at every cold start)
DEFAULT_AREA_GRACE_S: Final = 1.0
#: how long the start-up liveliness get waits for the router's replies
DEFAULT_SYNC_TIMEOUT_S: Final = 2.0
#: how long after a failed start-up liveliness get the next one is tried
SYNC_RETRY_S: Final = 1.0
#: how often a synced backend re-reads the tokens on the bus anyway: a liveliness subscription
#: does not replay what happened while the session was cut off (seen with zenoh 1.10 after a
#: frozen backend reconnected: it missed the other backends), and a get over a link that has
#: died unnoticed answers nothing
DEFAULT_RESYNC_S: Final = 1.0


@functools.lru_cache(maxsize=4096)
def hrw_score(robot_id: str, instance_id: str) -> int:
    """Rendezvous (highest-random-weight) score of ``instance_id`` for ``robot_id``: 64 bits of
    BLAKE2b over both ids, the same on every machine and Python version (not ``hash()``)."""
    digest = hashlib.blake2b(f"{robot_id}\0{instance_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def rank(robot_id: str, instance_id: str, pinned: Mapping[str, str]) -> tuple[bool, int, str]:
    """Sort key of ``instance_id`` for ``robot_id``, highest first: the pinned instance, then
    the rendezvous score, then the name (a tie of 64-bit scores is still deterministic)."""
    return (pinned.get(robot_id) == instance_id, hrw_score(robot_id, instance_id), instance_id)


def choose_owner(robot_id: str, members: Iterable[str],
                 pinned: Mapping[str, str] | None = None) -> str | None:
    """The backend among ``members`` that should own ``robot_id`` (``None`` without members)."""
    pins = pinned or {}
    return max(members, key=lambda inst: rank(robot_id, inst, pins), default=None)


def pinned_owners(section: Mapping[str, Any] | None, robots: Iterable[str],
                  source: str = "site file") -> dict[str, str]:
    """The ``owners`` map of a site file's ``backend`` section (``{robot: instance}``),
    validated: every robot must be one of ``robots``, every instance a valid id. Raises
    :class:`~protocol.errors.ValidationError` naming ``source`` and the key."""
    if not section:
        return {}
    if not isinstance(section, Mapping):
        raise ValidationError("backend", f"{source}: expected a map, got "
                              f"{type(section).__name__}")
    owners = section.get("owners") or {}
    if not isinstance(owners, Mapping):
        raise ValidationError("backend.owners", f"{source}: expected a map robot: instance, "
                              f"got {type(owners).__name__}")
    known = set(robots)
    out: dict[str, str] = {}
    for robot, instance in owners.items():
        if robot not in known:
            raise ValidationError(f"backend.owners.{robot}", f"{source}: no robot {robot!r} "
                                  f"in the site (robots: {', '.join(sorted(known)) or '-'})")
        out[str(robot)] = check_id(f"backend.owners.{robot}", instance)
    return out


@dataclasses.dataclass(frozen=True)
class Decision:
    """What :meth:`OwnershipTable.decide` asks the adapter to do now: declare the owner tokens
    of ``claim``, undeclare those of ``release`` (robot ids, sorted)."""

    claim: tuple[str, ...] = ()
    release: tuple[str, ...] = ()

    def __bool__(self) -> bool:
        return bool(self.claim or self.release)


class OwnershipTable:
    """One backend's view of who owns which robot; pure (time is passed in, ns).

    Feed it the backends' liveliness (:meth:`on_member`) and the owner tokens
    (:meth:`on_owner_token`), mark it :meth:`synced` once the tokens that existed at start are
    in, call :meth:`decide` on every tick and apply its :class:`Decision`; publish robot R only
    while :meth:`may_publish` (R, now) is true. Own tokens echoed back by the bus are ignored:
    what this backend holds is what :meth:`decide` claimed.

    Counters (:attr:`counters`): ``ownership.claims``, ``ownership.releases`` (handed to the
    robot's new choice), ``ownership.withdrawals`` (a simultaneous claim lost),
    ``ownership.takeovers`` (a robot another backend had held is published here),
    ``ownership.owner_lost`` (another backend's owner token vanished while it was the only one),
    ``ownership.member_joined``, ``ownership.member_left``, ``ownership.stalls`` (claims
    re-confirmed after the worker stalled), ``ownership.disconnects`` (every claim dropped: the
    session lost its links), ``ownership.area_changes`` (a robot moved to another area),
    ``ownership.unknown_area_tokens`` (an area token of an area the site does not have).

    Areas: ``areas`` (the site's :class:`~backend_service.areas.AreaMap`) and ``own_areas``
    (the areas this backend serves; empty: every area) make a robot's candidates the backends
    of its area (module doc, "Areas"); without areas every counted backend is a candidate.
    """

    def __init__(
        self,
        instance_id: str,
        robots: Sequence[str],
        *,
        started_ns: int,
        pinned: Mapping[str, str] | None = None,
        confirm_s: float = DEFAULT_CONFIRM_S,
        join_delay_s: float = DEFAULT_JOIN_DELAY_S,
        stall_s: float = DEFAULT_STALL_S,
        areas: AreaMap | None = None,
        own_areas: Sequence[str] = (),
    ) -> None:
        if not confirm_s >= 0 or not join_delay_s >= 0 or not stall_s > 0:
            raise ValueError(f"confirm_s and join_delay_s must be >= 0 and stall_s > 0, got "
                             f"{confirm_s}, {join_delay_s}, {stall_s}")
        self.instance_id = check_id("instance_id", instance_id)
        self.robots: tuple[str, ...] = tuple(dict.fromkeys(robots))
        self.pinned = dict(pinned or {})
        self.confirm_ns = round(confirm_s * NS_PER_S)
        self.join_delay_ns = round(join_delay_s * NS_PER_S)
        self.stall_ns = round(stall_s * NS_PER_S)
        self._last_decide_ns: int | None = None
        self._started_ns = started_ns
        self.area_grace_ns = round(DEFAULT_AREA_GRACE_S * NS_PER_S)
        #: live backends -> when this table first saw them (self: from ``started_ns``)
        self._members: dict[str, int] = {self.instance_id: started_ns}
        #: robot -> other backends whose owner token for it is in sight
        self._tokens: dict[str, set[str]] = {r: set() for r in self.robots}
        #: vanishing tokens, numbered: a liveliness get's answer taken after such an event may
        #: still hold the token (the routers answered before it vanished); :meth:`resync`
        #: must not bring it back (``("owner", robot, instance)``, ``("alive", instance, "")``,
        #: ``("area", area, instance)`` -> event number)
        self.vanish_seq = 0
        self._vanished: dict[tuple[str, str, str], int] = {}
        #: robots whose owner token this backend holds -> when it claimed them
        self._held: dict[str, int] = {}
        #: robots another backend held since this one last published them (for takeovers)
        self._held_elsewhere: set[str] = set()
        self._publishing: set[str] = set()
        self._synced = False
        self.counters: collections.Counter[str] = collections.Counter()
        self.areas: AreaMap | None = areas if areas else None
        self.own_areas: frozenset[str] = frozenset(own_areas)
        if self.own_areas and (self.areas is None
                               or not self.own_areas <= set(self.areas.areas)):
            raise ValueError(f"own_areas {sorted(self.own_areas)}: not all areas of the site "
                             f"({sorted(self.areas.areas) if self.areas else '-'})")
        #: other backends -> the areas their tokens say they serve (none: every area)
        self._member_areas: dict[str, set[str]] = {}
        #: members() at one now_ns (dropped whenever _members changes)
        self._members_memo: tuple[int, tuple[str, ...]] | None = None
        #: robot -> (stamp ns, area) of its newest position on the bus
        self._robot_area: dict[str, tuple[int, str | None]] = {}

    # ---------------------------------------------------------------- inputs

    def resync(self, members: Iterable[str], owner_tokens: Iterable[tuple[str, str]],
               now_ns: int, area_tokens: Iterable[tuple[str, str]] = (),
               since_vanish_seq: int | None = None) -> None:
        """The answer of a liveliness get: backends (``members``) and owner tokens
        (``(robot, instance)``) on the bus. It adds what the events missed and removes nothing:
        a get's answer can lack tokens that stand (seen with zenoh 1.10 under load), so only a
        vanishing token (an event) or :meth:`forget` removes one. Backends it adds while the
        table is not synced yet (at start, after :meth:`forget`) were there before: they count
        at once; later ones are new and count after the join delay. This backend's own tokens
        are ignored. ``area_tokens``: ``(area, instance)`` of the area tokens on the bus.
        ``since_vanish_seq``: :attr:`vanish_seq` when the get went out; a token whose vanishing
        event came after that is not brought back (the answer predates the event: a hand-over
        during a periodic get would otherwise wait for a token that is gone, for good).
        Claims may begin."""
        since = self.vanish_seq if since_vanish_seq is None else since_vanish_seq

        def gone(kind: str, a: str, b: str = "") -> bool:
            return self._vanished.get((kind, a, b), -1) > since

        for area, inst in area_tokens:
            if not gone("area", area, inst):
                self.on_area_token(area, inst, True)
        established = not self._synced
        for inst in sorted(set(members) - {self.instance_id}):
            if inst not in self._members and not gone("alive", inst):
                self.on_member(inst, True, now_ns - (self.join_delay_ns if established else 0))
        for robot, inst in owner_tokens:
            if (robot in self._tokens and inst not in self._tokens[robot]
                    and not gone("owner", robot, inst)):
                self.on_owner_token(robot, inst, True)
        # what vanished before this get went out cannot be in a later answer's way
        self._vanished = {k: v for k, v in self._vanished.items() if v > since}
        self._synced = True

    def _vanish(self, kind: str, a: str, b: str = "") -> None:
        self.vanish_seq += 1
        self._vanished[(kind, a, b)] = self.vanish_seq

    @property
    def is_synced(self) -> bool:
        return self._synced

    def forget(self, now_ns: int) -> Decision:
        """Stop publishing, drop every claim (undeclare the returned robots' tokens) and forget
        the other backends and their tokens: the view can no longer be trusted (the session
        lost its links, or this worker stood still for ``stall_s`` while events may have been
        lost). The next liveliness get starts over."""
        release = tuple(sorted(self._held))
        self._held.clear()
        self._publishing.clear()
        for holders in self._tokens.values():
            holders.clear()
        self._member_areas.clear()
        self._members = {self.instance_id: now_ns - self.join_delay_ns}
        self._members_memo = None
        self._synced = False
        return Decision(release=release)

    def on_disconnected(self, now_ns: int) -> Decision:
        """The session has no link left: :meth:`forget` (its tokens must go too: the session
        would re-declare them on reconnection)."""
        decision = self.forget(now_ns)
        self.counters["ownership.disconnects"] += 1
        log.warning("backend %s: the session lost its links; dropped %s", self.instance_id,
                    ", ".join(decision.release) or "no robot")
        return decision

    def on_member(self, instance_id: str, present: bool, now_ns: int) -> None:
        """A backend's liveliness token ``alive/backend/<instance_id>`` appeared or vanished."""
        if instance_id == self.instance_id:
            return  # this backend counts itself from its start
        if present:
            if instance_id not in self._members:
                self._members[instance_id] = now_ns
                self._members_memo = None
                self.counters["ownership.member_joined"] += 1
                log.info("backend %s: backend %s joined", self.instance_id, instance_id)
            return
        self._vanish("alive", instance_id)
        if self._members.pop(instance_id, None) is not None:
            self._members_memo = None
            self.counters["ownership.member_left"] += 1
            log.info("backend %s: backend %s left", self.instance_id, instance_id)

    def on_owner_token(self, robot_id: str, instance_id: str, present: bool) -> None:
        """Backend ``instance_id``'s owner token of ``robot_id`` appeared or vanished. Tokens of
        robots this backend does not know are ignored (and counted)."""
        if instance_id == self.instance_id:
            return
        holders = self._tokens.get(robot_id)
        if holders is None:
            self.counters["ownership.unknown_robot_tokens"] += 1
            return
        if present:
            holders.add(instance_id)
            self._held_elsewhere.add(robot_id)
            if robot_id in self._publishing:
                # rule 4: a claim this backend did not see coming; stop at once, decide() sorts
                # out who withdraws
                self._publishing.discard(robot_id)
                log.warning("backend %s: %s also claims %s; publishing of it stopped",
                            self.instance_id, instance_id, robot_id)
            return
        self._vanish("owner", robot_id, instance_id)
        if instance_id in holders:
            holders.discard(instance_id)
            if not holders:
                self.counters["ownership.owner_lost"] += 1

    def on_area_token(self, area: str, instance_id: str, present: bool) -> None:
        """Backend ``instance_id``'s token of area ``area`` appeared or vanished (this
        backend's own are ignored: it knows its areas)."""
        if instance_id == self.instance_id:
            return
        if self.areas is not None and area not in self.areas.areas:
            self.counters["ownership.unknown_area_tokens"] += 1
            return
        if present:
            self._member_areas.setdefault(instance_id, set()).add(area)
        else:
            self._vanish("area", area, instance_id)
            served = self._member_areas.get(instance_id)
            if served is not None:
                served.discard(area)
                if not served:
                    del self._member_areas[instance_id]

    def on_robot_position(self, robot_id: str, x_m: float, y_m: float, stamp_ns: int) -> None:
        """A pose of ``robot_id`` on the bus (its owner's fused pose or its own localization,
        world x, y in m): updates the robot's area (older stamps than the newest are ignored)."""
        if self.areas is None or robot_id not in self._tokens:
            return
        last_ns, current = self._robot_area.get(robot_id, (-1, None))
        if stamp_ns < last_ns:
            return
        area = self.areas.area_of(x_m, y_m, current)
        if current is not None and area != current:
            self.counters["ownership.area_changes"] += 1
            log.info("backend %s: %s moved from area %s to %s", self.instance_id, robot_id,
                     current, area)
        self._robot_area[robot_id] = (stamp_ns, area)

    def robot_area(self, robot_id: str) -> str | None:
        """The area ``robot_id`` is in, as far as this table knows (``None``: not known)."""
        return self._robot_area.get(robot_id, (0, None))[1]

    def serves(self, instance_id: str, area: str) -> bool:
        """Whether backend ``instance_id`` serves ``area`` (one without area tokens serves
        every area)."""
        if instance_id == self.instance_id:
            return not self.own_areas or area in self.own_areas
        served = self._member_areas.get(instance_id)
        return not served or area in served

    # ---------------------------------------------------------------- decisions

    def members(self, now_ns: int) -> list[str]:
        """The backends that count now (appeared at least ``join_delay_s`` ago), sorted. (Kept
        for the same ``now_ns`` until a backend joins or leaves: a decision asks once per robot.)
        """
        memo = self._members_memo
        if memo is not None and memo[0] == now_ns:
            return list(memo[1])
        out = sorted(inst for inst, since in self._members.items()
                     if now_ns - since >= self.join_delay_ns)
        self._members_memo = (now_ns, tuple(out))
        return out

    def candidates(self, robot_id: str, now_ns: int) -> list[str]:
        """The counted backends that may own ``robot_id`` now: those serving its area (and its
        pinned instance); all counted backends when the site has no areas, no counted backend
        serves the robot's area, or its area is still not known :data:`DEFAULT_AREA_GRACE_S`
        after this backend's start (none before: nobody claims it yet)."""
        members = self.members(now_ns)
        if self.areas is None:
            return members
        area = self.robot_area(robot_id)
        if area is None:
            return members if now_ns - self._started_ns >= self.area_grace_ns else []
        out = [m for m in members if self.serves(m, area) or self.pinned.get(robot_id) == m]
        return out or members

    def owner_of(self, robot_id: str, now_ns: int) -> str | None:
        """The backend that should own ``robot_id`` now, in this table's view."""
        return choose_owner(robot_id, self.candidates(robot_id, now_ns), self.pinned)

    def _outranks(self, robot_id: str, a: str, b: str) -> bool:
        return rank(robot_id, a, self.pinned) > rank(robot_id, b, self.pinned)

    def decide(self, now_ns: int) -> Decision:
        """The claims and releases due now (the table counts them held or released already:
        apply the decision before publishing anything else)."""
        last, self._last_decide_ns = self._last_decide_ns, now_ns
        if last is not None and now_ns - last > self.stall_ns:
            # the bus may have moved on while this worker stood still, and its session may
            # have been cut off and back unnoticed: start over from a liveliness get
            self.counters["ownership.stalls"] += 1
            decision = self.forget(now_ns)
            log.warning("backend %s: no decision for %.1f s; dropped %s, re-syncing",
                        self.instance_id, (now_ns - last) / NS_PER_S,
                        ", ".join(decision.release) or "no robot")
            return decision
        claim: list[str] = []
        release: list[str] = []
        for robot in self.robots:
            others = self._tokens[robot]
            mine = self.owner_of(robot, now_ns) == self.instance_id
            if robot in self._held:
                higher = [o for o in others if self._outranks(robot, o, self.instance_id)]
                if not mine or higher:
                    del self._held[robot]
                    self._publishing.discard(robot)
                    release.append(robot)
                    self.counters["ownership.withdrawals" if mine else "ownership.releases"] += 1
                    log.info("backend %s releases %s (%s)", self.instance_id, robot,
                             f"{', '.join(sorted(higher))} claimed it too" if mine
                             else f"now {self.owner_of(robot, now_ns)}'s")
            elif mine and self._synced and not others:
                self._held[robot] = now_ns
                claim.append(robot)
                self.counters["ownership.claims"] += 1
                log.info("backend %s claims %s", self.instance_id, robot)
        for robot in self.robots:  # publishing starts here, after the decision is known
            if robot not in self._publishing and self.may_publish(robot, now_ns):
                self._publishing.add(robot)
                if robot in self._held_elsewhere:
                    self.counters["ownership.takeovers"] += 1
                    self._held_elsewhere.discard(robot)
                log.info("backend %s publishes %s", self.instance_id, robot)
        return Decision(tuple(claim), tuple(release))

    def may_publish(self, robot_id: str, now_ns: int) -> bool:
        """Whether this backend may publish estimates of ``robot_id`` at ``now_ns``: it holds
        the robot's owner token since at least ``confirm_s``, sees no other owner token of it,
        is still its choice, is synced and decided less than ``stall_s`` ago."""
        claimed_ns = self._held.get(robot_id)
        return (claimed_ns is not None and now_ns - claimed_ns >= self.confirm_ns
                and self._synced and self._last_decide_ns is not None
                and now_ns - self._last_decide_ns <= self.stall_ns
                and not self._tokens[robot_id]
                and self.owner_of(robot_id, now_ns) == self.instance_id)

    # ---------------------------------------------------------------- status

    def owned(self) -> list[str]:
        """Robots whose owner token this backend holds, sorted."""
        return sorted(self._held)

    def to_run(self, now_ns: int) -> frozenset[str]:
        """Robots whose pipeline this backend runs: those it holds and those it should own
        now (its claim is due or waits for the old owner's token), so that their pipeline is
        running when it starts publishing."""
        return frozenset(self._held) | frozenset(
            r for r in self.robots if self.owner_of(r, now_ns) == self.instance_id)

    def pending(self, now_ns: int) -> dict[str, str]:
        """Robots this backend should own but does not publish yet, and why."""
        out: dict[str, str] = {}
        for robot in self.robots:
            if self.owner_of(robot, now_ns) != self.instance_id or \
                    self.may_publish(robot, now_ns):
                continue
            others = sorted(self._tokens[robot])
            if not self._synced:
                out[robot] = "waiting for the liveliness sync"
            elif others:
                out[robot] = f"waiting for the owner token of {', '.join(others)} to vanish"
            elif robot in self._held:
                left_ms = (self.confirm_ns - (now_ns - self._held[robot])) / 1e6
                out[robot] = f"confirming the claim ({max(0.0, left_ms):.0f} ms left)"
            else:
                out[robot] = "claim due at the next decision"
        return out

    def summary(self, now_ns: int) -> str:
        """One line for the status detail: members, owned robots, pending claims."""
        pending = self.pending(now_ns)
        text = (f"backends: {','.join(self.members(now_ns)) or '-'}; "
                f"owns: {','.join(self.owned()) or '-'}")
        if self.areas is not None:
            text += f"; areas: {','.join(sorted(self.own_areas)) or 'all'}"
        if pending:
            text += "; pending: " + ", ".join(f"{r} ({why})" for r, why in sorted(pending.items()))
        return text

    def on_liveliness(self, site: str, key: str, present: bool, now_ns: int) -> bool:
        """Feed one liveliness event of the bus (``alive/backend/<id>`` or
        ``owner/<robot>/<id>`` of ``site``); returns whether it was one of those. Keys of other
        services, sites or shapes are ignored (a foreign or malformed key is counted
        ``ownership.foreign_keys``)."""
        parsed = parse_liveliness(key)
        if parsed is None or parsed[0] != site:
            self.counters["ownership.foreign_keys"] += 1
            return False
        _, kind, a, b = parsed
        if kind == "alive":
            if a != BACKEND_SERVICE:
                return False
            self.on_member(b, present, now_ns)
        elif kind == "area":
            self.on_area_token(a, b, present)
        else:
            self.on_owner_token(a, b, present)
        return True


def parse_liveliness(key: str) -> tuple[str, str, str, str] | None:
    """``(site, 'alive', service, instance)``, ``(site, 'owner', robot, instance)`` or
    ``(site, 'area', area, instance)`` of a liveliness key, ``None`` when it is none of
    those."""
    try:
        parsed = keys.parse_key(key)
    except ValidationError:
        return None
    if parsed.scope == "alive":
        return parsed.site, "alive", parsed.topic, parsed.source_id
    if parsed.scope in ("owner", "area"):
        return parsed.site, parsed.scope, parsed.source_id, parsed.topic
    return None


