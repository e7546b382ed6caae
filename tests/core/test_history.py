"""core.history: the one stamped history (insert policies, look-ups, interpolation, trimming)
and the planar-pose blend."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.geometry import angle_diff, wrap_angle
from core.history import Bracket, Stamped, StampedHistory, lerp_se2

STAMPS = st.integers(min_value=0, max_value=10**12)
STAMP_LISTS = st.lists(STAMPS, max_size=40)
COORDS = st.floats(-100.0, 100.0, allow_nan=False)
HEADINGS = st.floats(-math.pi, math.pi, allow_nan=False, exclude_max=True)
POSES = st.tuples(COORDS, COORDS, HEADINGS)
FRACTIONS = st.floats(0.0, 1.0, allow_nan=False)


def _history(stamps: list[int], max_count: int | None = None,
             out_of_order: str = "insert") -> StampedHistory[int]:
    """A history whose item is the position of its insert (so "which one won" is visible)."""
    h: StampedHistory[int] = StampedHistory(max_count, out_of_order=out_of_order)
    for k, s in enumerate(stamps):
        h.insert(s, k)
    return h


# --------------------------------------------------------------------------------------------
# insert
# --------------------------------------------------------------------------------------------


@given(STAMP_LISTS, st.randoms(use_true_random=False))
def test_sorted_insertion_does_not_depend_on_arrival_order(stamps: list[int], rng) -> None:
    shuffled = stamps[:]
    rng.shuffle(shuffled)
    a = [s for s, _ in _history(stamps)]
    b = [s for s, _ in _history(shuffled)]
    assert a == b == sorted(set(stamps))


@given(STAMP_LISTS, st.integers(1, 10))
def test_insert_keeps_the_newest_stamps_and_the_first_item_of_each(stamps: list[int],
                                                                  max_count: int) -> None:
    h = _history(stamps, max_count)
    first = {}
    for k, s in enumerate(stamps):
        first.setdefault(s, k)
    expected = sorted(first)[-max_count:]
    assert [s for s, _ in h] == expected
    assert [x for _, x in h] == [first[s] for s in expected]
    assert len(h) <= max_count


@given(STAMP_LISTS, st.integers(1, 10))
def test_drop_keeps_only_what_goes_forward(stamps: list[int], max_count: int) -> None:
    h = _history(stamps, max_count, out_of_order="drop")
    forward: list[tuple[int, int]] = []
    for k, s in enumerate(stamps):
        if not forward or s > forward[-1][0]:
            forward.append((s, k))
    assert [tuple(e) for e in h] == forward[-max_count:]


def test_insert_reports_what_it_holds() -> None:
    h: StampedHistory[str] = StampedHistory(2, out_of_order="insert")
    assert h.insert(20, "a") and h.insert(10, "b")
    assert not h.insert(20, "c")  # the first item of a stamp wins
    assert not h.insert(5, "d")  # full, and it would be the oldest
    assert h.insert(15, "e")  # full, but newer than the oldest: the oldest goes
    assert list(h) == [Stamped(15, "e"), Stamped(20, "a")]
    d: StampedHistory[str] = StampedHistory(out_of_order="drop")
    assert d.insert(10, "a") and not d.insert(10, "b") and not d.insert(9, "c")
    assert d.insert(11, "d") and len(d) == 2


def test_bad_construction() -> None:
    with pytest.raises(ValueError, match="max_count"):
        StampedHistory(0)
    with pytest.raises(ValueError, match="out_of_order"):
        StampedHistory(out_of_order="sort")


# --------------------------------------------------------------------------------------------
# look-ups
# --------------------------------------------------------------------------------------------


def test_empty_and_one_element() -> None:
    h: StampedHistory[tuple[float, float, float]] = StampedHistory()
    assert not h and len(h) == 0 and list(h) == []
    assert h.latest() is None and h.oldest() is None and h.nearest(5) is None
    assert h.bracket(5) is None and h.interpolate(5, lerp_se2) is None
    assert h.newer_than(0) == [] and h.trim_before(10) == 0 and h.trim_to_age(1) == 0
    h.insert(100, (1.0, 2.0, 0.5))
    assert h.latest() == h.oldest() == Stamped(100, (1.0, 2.0, 0.5))
    assert h.nearest(0) == Stamped(100, (1.0, 2.0, 0.5))
    assert h.nearest(0, max_gap_ns=99) is None and h.nearest(199, max_gap_ns=99) is not None
    assert h.bracket(100) == Bracket(Stamped(100, (1.0, 2.0, 0.5)), Stamped(100, (1.0, 2.0, 0.5)),
                                     0.0)
    assert h.bracket(99) is None and h.bracket(101) is None
    assert h.interpolate(100, lerp_se2) == (1.0, 2.0, 0.5)
    assert h.interpolate(101, lerp_se2) is None  # no extrapolation
    assert h.trim_before(10**6) == 0 and len(h) == 1  # the last one always stays


@given(st.lists(STAMPS, min_size=1, max_size=30), STAMPS,
       st.one_of(st.none(), st.integers(0, 10**12)))
def test_nearest_is_the_closest_the_older_on_a_tie(stamps: list[int], query: int,
                                                    max_gap_ns: int | None) -> None:
    h = _history(stamps)
    held = sorted(set(stamps))
    best = min(held, key=lambda s: (abs(s - query), s))
    near = h.nearest(query, max_gap_ns)
    if max_gap_ns is not None and abs(best - query) > max_gap_ns:
        assert near is None
    else:
        assert near is not None and near.stamp_ns == best


def test_nearest_tie_goes_to_the_older() -> None:
    h = _history([10, 20])
    assert h.nearest(15).stamp_ns == 10  # type: ignore[union-attr]
    assert h.nearest(16).stamp_ns == 20  # type: ignore[union-attr]


@given(st.lists(STAMPS, min_size=1, max_size=30), STAMPS)
def test_bracket_holds_the_two_neighbours(stamps: list[int], query: int) -> None:
    h = _history(stamps)
    held = sorted(set(stamps))
    br = h.bracket(query)
    if query < held[0] or query > held[-1]:
        assert br is None
        return
    assert br is not None
    assert br.before.stamp_ns <= query <= br.after.stamp_ns
    assert 0.0 <= br.fraction <= 1.0
    if query in held:
        assert br.before == br.after and br.before.stamp_ns == query and br.fraction == 0.0
    else:
        i = held.index(br.before.stamp_ns)
        assert held[i + 1] == br.after.stamp_ns  # consecutive: nothing held in between
        assert br.fraction == (query - br.before.stamp_ns) / (br.after.stamp_ns
                                                              - br.before.stamp_ns)


@given(STAMP_LISTS, STAMPS)
def test_newer_than(stamps: list[int], query: int) -> None:
    h = _history(stamps)
    assert [s for s, _ in h.newer_than(query)] == [s for s in sorted(set(stamps)) if s > query]


# --------------------------------------------------------------------------------------------
# interpolation
# --------------------------------------------------------------------------------------------


@given(st.lists(st.tuples(STAMPS, POSES), min_size=1, max_size=20))
def test_interpolation_at_the_knots_returns_the_knots(knots) -> None:
    h: StampedHistory[tuple[float, float, float]] = StampedHistory(out_of_order="insert")
    for stamp, pose in knots:
        h.insert(stamp, pose)
    for stamp, pose in h:
        assert h.interpolate(stamp, lerp_se2) == pose
        assert h.interpolate(stamp, lerp_se2, max_gap_ns=0) == pose  # a knot needs no gap


@given(POSES, POSES, FRACTIONS)
def test_lerp_se2_takes_the_shorter_arc_and_wraps(a, b, f: float) -> None:
    x, y, th = lerp_se2(a, b, f)
    assert -math.pi <= th < math.pi
    assert x == pytest.approx(a[0] + f * (b[0] - a[0]))
    assert y == pytest.approx(a[1] + f * (b[1] - a[1]))
    # the heading moved by the fraction f of the signed shortest turn from a to b (compared
    # modulo 2 pi: a turn of almost exactly pi may round to either side of the seam)
    turned = angle_diff(th, a[2]) - f * angle_diff(b[2], a[2])
    assert abs(math.remainder(turned, 2 * math.pi)) < 1e-9


def test_interpolation_across_the_pi_seam() -> None:
    h: StampedHistory[tuple[float, float, float]] = StampedHistory()
    h.insert(0, (0.0, 0.0, math.pi - 0.1))
    h.insert(100, (1.0, 2.0, -math.pi + 0.1))
    x, y, th = h.interpolate(50, lerp_se2)  # type: ignore[misc]
    assert (x, y) == pytest.approx((0.5, 1.0))
    assert abs(abs(th) - math.pi) < 1e-9  # through +-pi, not through 0
    _, _, th = h.interpolate(75, lerp_se2)  # type: ignore[misc]
    assert th == pytest.approx(wrap_angle(math.pi + 0.05))


def test_interpolation_refuses_a_gap() -> None:
    h: StampedHistory[tuple[float, float, float]] = StampedHistory()
    h.insert(0, (0.0, 0.0, 0.0))
    h.insert(100, (1.0, 0.0, 0.0))
    assert h.interpolate(30, lerp_se2, max_gap_ns=100) == pytest.approx((0.3, 0.0, 0.0))
    assert h.interpolate(30, lerp_se2, max_gap_ns=99) is None
    calls = []
    h.interpolate(30, lambda a, b, f: calls.append((a, b, f)))
    assert calls == [((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), 0.3)]


# --------------------------------------------------------------------------------------------
# trimming
# --------------------------------------------------------------------------------------------


@given(st.lists(STAMPS, min_size=1, max_size=30), STAMPS)
def test_trim_before_keeps_what_a_lookup_at_the_stamp_needs(stamps: list[int],
                                                           query: int) -> None:
    h = _history(stamps)
    held = sorted(set(stamps))
    before = h.bracket(query)
    removed = h.trim_before(query)
    at_or_before = [s for s in held if s <= query]
    kept = held[max(len(at_or_before) - 1, 0):]
    assert [s for s, _ in h] == kept and removed == len(held) - len(kept)
    assert h.bracket(query) == before  # the lookup at the trim stamp is unchanged


@given(st.lists(STAMPS, min_size=1, max_size=30), st.integers(0, 10**12))
def test_trim_to_age_bounds_the_span(stamps: list[int], max_age_ns: int) -> None:
    h = _history(stamps)
    h.trim_to_age(max_age_ns)
    held = [s for s, _ in h]
    newest = max(stamps)
    assert held[-1] == newest
    # everything but possibly the oldest (the horizon's lower neighbour) is within the age
    assert all(newest - s <= max_age_ns for s in held[1:])
    h.clear()
    assert not h
