"""Acknowledged ids as ranges: the same answers as a plain set of ids, in a handful of runs."""

from __future__ import annotations

import itertools

from hypothesis import given
from hypothesis import strategies as st

from gateway.recording.id_ranges import IdRanges

spans = st.lists(
    st.tuples(st.integers(1, 80), st.integers(-1, 12)).map(lambda t: (t[0], t[0] + t[1])),
    max_size=20,
)


def covered(ranges: IdRanges) -> set[int]:
    return {i for lo, hi in ranges for i in range(lo, hi + 1)}


@given(spans)
def test_adding_ranges_covers_exactly_their_ids_and_counts_only_new_ones(
    adds: list[tuple[int, int]],
) -> None:
    ranges, expected = IdRanges(), set()
    for lo, hi in adds:
        ids = set(range(lo, hi + 1))
        assert ranges.add(lo, hi) == len(ids - expected)
        expected |= ids
    assert covered(ranges) == expected
    runs = list(ranges)
    assert all(a_hi + 1 < b_lo for (_, a_hi), (b_lo, _) in itertools.pairwise(runs))


@given(spans, st.integers(0, 90), st.integers(0, 95))
def test_gaps_are_the_uncovered_ids_between_a_cursor_and_a_ceiling(
    adds: list[tuple[int, int]], after: int, ceiling: int,
) -> None:
    ranges = IdRanges(adds)
    gaps = list(ranges.gaps(after, ceiling))
    assert {i for lo, hi in gaps for i in range(lo, hi + 1)} == (
        set(range(after + 1, ceiling + 1)) - covered(ranges)
    )
    assert all(lo <= hi for lo, hi in gaps)
    assert gaps == sorted(gaps)


@given(spans)
def test_through_is_the_fully_acknowledged_prefix(adds: list[tuple[int, int]]) -> None:
    ranges = IdRanges(adds)
    ids = covered(ranges)
    w = 0
    while w + 1 in ids:
        w += 1
    assert ranges.through() == w


def test_in_order_acknowledgements_stay_one_run() -> None:
    """500-record batches acknowledged slightly out of order still end as one range."""
    ranges = IdRanges()
    for lo in (501, 1, 1501, 1001):
        ranges.add(lo, lo + 499)
    assert list(ranges) == [(1, 2000)]
    assert ranges.add_ids([3, 2, 2001, 2002]) == 2
    assert list(ranges) == [(1, 2002)] and 2002 in ranges and 2003 not in ranges
