"""The one stamped history: items kept in stamp order, looked up, interpolated and trimmed.

Every service that needs "what was the robot's pose at this stamp" keeps one of these: the
pose graph's odometry buffer, the backend's record of the robot's own localization, the
mapper's fused poses, the robot bridge's odometry for the ``map -> odom`` transform.

Stamps are integer nanoseconds on the sensor clock of the message they came from
(``stamp_ns``); nothing here reads a clock. A history holds at most one item per stamp. What
an insert of a stamp that is not newer than the newest held does is the history's
``out_of_order`` policy: ``"drop"`` refuses it (streams that must only go forward, e.g.
odometry), ``"insert"`` puts it in its place (streams whose messages may overtake each other on
the way; the first item of a stamp wins). Either way the items stay sorted by stamp, so
lookups are binary searches.

Memory is bounded by ``max_count`` (the oldest items go first) and, where the owner wants it,
by age (:meth:`StampedHistory.trim_to_age`, :meth:`StampedHistory.trim_before`).

Interpolation is the owner's: :meth:`StampedHistory.interpolate` brackets the stamp and calls a
``blend(a, b, fraction)``; :func:`lerp_se2` is the blend of planar poses ``(x, y, theta)``
(metres, radians; linear in x and y, the heading along the shorter arc, wrapped with
:func:`~core.geometry.wrap_angle`). The frame of a pose is whatever the owner stores (map
or odometry frame); blending never changes it. Not thread-safe: one worker loop owns a history.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, Final, Generic, NamedTuple, TypeVar

from core.geometry import wrap_angle

T = TypeVar("T")
R = TypeVar("R")

#: what :meth:`StampedHistory.insert` does with a stamp not newer than the newest held
OUT_OF_ORDER_POLICIES: Final = ("drop", "insert")


if TYPE_CHECKING:  # generic for the type checker: ``Stamped[T]``, ``Bracket[T]``

    class Stamped(NamedTuple, Generic[T]):
        stamp_ns: int
        item: T

    class Bracket(NamedTuple, Generic[T]):
        before: Stamped[T]
        after: Stamped[T]
        fraction: float

else:  # a generic NamedTuple needs Python 3.11 at run time; JetPack 6 (edge, robot) has 3.10

    class Stamped(NamedTuple):
        """One item of a history and its stamp (ns)."""

        stamp_ns: int
        item: Any

    class Bracket(NamedTuple):
        """The two items around a stamp: ``before.stamp_ns <= stamp <= after.stamp_ns`` and
        ``fraction`` = (stamp - before) / (after - before) in [0, 1]. At a stamp the history
        holds, ``before`` and ``after`` are that item and ``fraction`` is 0."""

        before: Stamped
        after: Stamped
        fraction: float


class StampedHistory(Generic[T]):
    """Items of type ``T`` keyed by ``stamp_ns`` (int ns), oldest first (module docstring).

    ``max_count``: at most this many items are kept, the newest (``None``: unbounded, the owner
    trims). ``out_of_order``: ``"drop"`` or ``"insert"`` (:data:`OUT_OF_ORDER_POLICIES`).
    """

    def __init__(self, max_count: int | None = None, *, out_of_order: str = "drop") -> None:
        if max_count is not None and max_count < 1:
            raise ValueError(f"StampedHistory: max_count must be >= 1, got {max_count}")
        if out_of_order not in OUT_OF_ORDER_POLICIES:
            raise ValueError(f"StampedHistory: out_of_order must be one of "
                             f"{OUT_OF_ORDER_POLICIES}, got {out_of_order!r}")
        self.max_count = max_count
        self.out_of_order = out_of_order
        self._stamps: list[int] = []
        self._items: list[T] = []

    # -- insert ----------------------------------------------------------------------------------

    def insert(self, stamp_ns: int, item: T) -> bool:
        """Add ``item`` at ``stamp_ns``; ``True`` when the history holds it afterwards.

        A stamp newer than the newest is appended. An older or equal one is refused under
        ``"drop"``; under ``"insert"`` it goes into its place unless the stamp is already held
        (the first item of a stamp wins) or the history is full and it would be the oldest.
        Past ``max_count`` the oldest item is dropped."""
        stamp = int(stamp_ns)
        stamps = self._stamps
        if not stamps or stamp > stamps[-1]:
            stamps.append(stamp)
            self._items.append(item)
        else:
            if self.out_of_order == "drop":
                return False
            i = bisect.bisect_left(stamps, stamp)
            if stamps[i] == stamp:
                return False
            if self.max_count is not None and len(stamps) >= self.max_count and i == 0:
                return False
            stamps.insert(i, stamp)
            self._items.insert(i, item)
        if self.max_count is not None and len(stamps) > self.max_count:
            excess = len(stamps) - self.max_count
            del stamps[:excess]
            del self._items[:excess]
        return True

    # -- look up ---------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self._stamps)

    def __bool__(self) -> bool:
        return bool(self._stamps)

    def __iter__(self) -> Iterator[Stamped[T]]:
        """The items, oldest first."""
        return (Stamped(s, x) for s, x in zip(self._stamps, self._items, strict=True))

    def oldest(self) -> Stamped[T] | None:
        """The oldest item, ``None`` when empty."""
        return Stamped(self._stamps[0], self._items[0]) if self._stamps else None

    def latest(self) -> Stamped[T] | None:
        """The newest item, ``None`` when empty."""
        return Stamped(self._stamps[-1], self._items[-1]) if self._stamps else None

    def newer_than(self, stamp_ns: int) -> list[Stamped[T]]:
        """The items stamped after ``stamp_ns``, oldest first (a copy: the history may change
        while the caller goes through them)."""
        i = bisect.bisect_right(self._stamps, stamp_ns)
        return [Stamped(s, x) for s, x in zip(self._stamps[i:], self._items[i:], strict=True)]

    def nearest(self, stamp_ns: int, max_gap_ns: int | None = None) -> Stamped[T] | None:
        """The item whose stamp is nearest ``stamp_ns`` (of two equally near, the older), if it
        is at most ``max_gap_ns`` away (``None``: any distance); ``None`` otherwise."""
        stamps = self._stamps
        if not stamps:
            return None
        i = bisect.bisect_left(stamps, stamp_ns)
        j = i if i == 0 or (i < len(stamps)
                            and stamps[i] - stamp_ns < stamp_ns - stamps[i - 1]) else i - 1
        if max_gap_ns is not None and abs(stamps[j] - stamp_ns) > max_gap_ns:
            return None
        return Stamped(stamps[j], self._items[j])

    def bracket(self, stamp_ns: int) -> Bracket[T] | None:
        """The items around ``stamp_ns`` (:class:`Bracket`), ``None`` when the stamp is outside
        [oldest, newest] (no extrapolation)."""
        stamps = self._stamps
        if not stamps or stamp_ns < stamps[0] or stamp_ns > stamps[-1]:
            return None
        j = bisect.bisect_left(stamps, stamp_ns)
        if stamps[j] == stamp_ns:
            at = Stamped(stamps[j], self._items[j])
            return Bracket(at, at, 0.0)
        t0, t1 = stamps[j - 1], stamps[j]
        return Bracket(Stamped(t0, self._items[j - 1]), Stamped(t1, self._items[j]),
                       (stamp_ns - t0) / (t1 - t0))

    def interpolate(self, stamp_ns: int, blend: Callable[[T, T, float], R], *,
                    max_gap_ns: int | None = None) -> R | None:
        """``blend(before, after, fraction)`` of the :meth:`bracket` of ``stamp_ns`` (at a held
        stamp: ``blend(item, item, 0.0)``); ``None`` outside [oldest, newest] or when the two
        items are more than ``max_gap_ns`` apart (a gap in the stream: no motion is invented)."""
        br = self.bracket(stamp_ns)
        if br is None:
            return None
        if max_gap_ns is not None and br.after.stamp_ns - br.before.stamp_ns > max_gap_ns:
            return None
        return blend(br.before.item, br.after.item, br.fraction)

    # -- trim ------------------------------------------------------------------------------------

    def trim_before(self, stamp_ns: int) -> int:
        """Drop the items older than the newest one at or before ``stamp_ns`` (that one stays,
        so a lookup at ``stamp_ns`` still has what is before it); returns how many went."""
        j = bisect.bisect_right(self._stamps, stamp_ns) - 1
        if j <= 0:
            return 0
        del self._stamps[:j]
        del self._items[:j]
        return j

    def trim_to_age(self, max_age_ns: int) -> int:
        """:meth:`trim_before` the newest stamp minus ``max_age_ns``: what is older than that
        goes, except the one item a lookup at that horizon needs; returns how many went."""
        if not self._stamps:
            return 0
        return self.trim_before(self._stamps[-1] - int(max_age_ns))

    def clear(self) -> None:
        self._stamps.clear()
        self._items.clear()


def lerp_se2(a: Sequence[float], b: Sequence[float],
             fraction: float) -> tuple[float, float, float]:
    """The planar pose a ``fraction`` (in [0, 1]) of the way from ``a`` to ``b``, both
    ``(x, y, theta)`` (m, m, rad) in one frame: x and y linear, theta along the shorter arc
    (across +-pi when that is shorter), wrapped into [-pi, pi). A blend for
    :meth:`StampedHistory.interpolate`; at ``fraction`` 0 it is ``a`` (heading wrapped)."""
    return (a[0] + fraction * (b[0] - a[0]), a[1] + fraction * (b[1] - a[1]),
            wrap_angle(a[2] + fraction * wrap_angle(b[2] - a[2])))
