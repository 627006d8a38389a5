"""ISO 7256-1 / Kachman & Smith spacing indices, with hand-computed answers."""

from __future__ import annotations

import math
import random
import statistics

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gateway.recording.spacing_quality import (
    QUALITY_WINDOW,
    RowQualityAccumulator,
    spacing_quality,
)


def test_known_answer_for_a_mixed_row() -> None:
    """8 spacings at x_ref 0.2 m: 2 multiples, 2 misses, 4 singles of SD 0.01633 m."""
    xs = [0.2, 0.2, 0.1, 0.4, 0.22, 0.18, 0.31, 0.09]
    q = spacing_quality(xs, x_ref=0.2)
    assert q.n == 8
    assert q.multiples_index == pytest.approx(25.0)
    assert q.miss_index == pytest.approx(25.0)
    assert q.quality_of_feed_index == pytest.approx(50.0)
    assert q.precision == pytest.approx(100 * math.sqrt(0.0008 / 3) / 0.2)
    assert q.mean_spacing_m == pytest.approx(sum(xs) / 8)


def test_boundaries_half_is_a_multiple_and_one_and_a_half_is_still_a_single() -> None:
    q = spacing_quality([0.125, 0.375, 0.25], x_ref=0.25)
    assert q.multiples_index == pytest.approx(100 / 3)
    assert q.miss_index == pytest.approx(0.0)
    q2 = spacing_quality([0.3751], x_ref=0.25)
    assert q2.miss_index == pytest.approx(100.0)


def test_perfect_spacing_is_all_singles_with_zero_precision() -> None:
    q = spacing_quality([0.2] * 10, x_ref=0.2)
    assert (q.multiples_index, q.miss_index, q.quality_of_feed_index) == (0.0, 0.0, 100.0)
    assert q.precision == pytest.approx(0.0)


def test_without_a_target_x_ref_is_the_median() -> None:
    xs = [0.19, 0.2, 0.21, 0.05, 0.6]
    q = spacing_quality(xs)
    assert q.x_ref_m == pytest.approx(0.2)
    assert q.multiples_index == pytest.approx(20.0) and q.miss_index == pytest.approx(20.0)


def test_no_spacings_gives_no_indices() -> None:
    q = spacing_quality([], x_ref=0.2)
    assert q.n == 0 and q.quality_of_feed_index is None and q.precision is None


def test_a_single_single_has_no_precision_yet() -> None:
    assert spacing_quality([0.2], x_ref=0.2).precision is None


def test_streaming_accumulator_agrees_with_the_list_function() -> None:
    rng = random.Random(5)
    xs = [max(0.0, rng.gauss(0.2, 0.05)) for _ in range(500)] + [0.05] * 20 + [0.45] * 15
    rng.shuffle(xs)
    acc = RowQualityAccumulator(0.2)
    for x in xs:
        acc.add(x)
    streamed, batch = acc.result(), spacing_quality(xs, x_ref=0.2)
    assert streamed.n == batch.n == len(xs)
    assert streamed.multiples_index == pytest.approx(batch.multiples_index)
    assert streamed.precision == pytest.approx(batch.precision)
    singles = [x for x in xs if 0.1 < x <= 0.3]
    assert streamed.precision == pytest.approx(100 * statistics.stdev(singles) / 0.2)


def test_accumulator_without_target_uses_a_bounded_window() -> None:
    acc = RowQualityAccumulator()
    for _ in range(QUALITY_WINDOW + 50):
        acc.add(0.2)
    q = acc.result()
    assert q.n == QUALITY_WINDOW and q.x_ref_m == pytest.approx(0.2)


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf])
def test_impossible_spacings_are_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="spacing must be"):
        RowQualityAccumulator(0.2).add(bad)


def test_a_non_positive_target_is_refused() -> None:
    with pytest.raises(ValueError, match="x_ref must be > 0"):
        RowQualityAccumulator(0.0)


@given(
    first=st.lists(st.floats(min_value=0.0, max_value=2.0), max_size=30),
    second=st.lists(st.floats(min_value=0.0, max_value=2.0), max_size=30),
    x_ref=st.sampled_from([0.05, 0.2, None]),
)
def test_adding_many_at_once_leaves_exactly_the_state_of_adding_one_by_one(
    first: list[float], second: list[float], x_ref: float | None
) -> None:
    """The recorder feeds each row's spacings in one call; nothing may differ in the last bit."""
    one, many = RowQualityAccumulator(x_ref), RowQualityAccumulator(x_ref)
    for x in first + second:
        one.add(x)
    many.add_many(first)
    many.add_many(second)
    assert vars(many) == vars(one)
    assert many.result() == one.result()


@pytest.mark.parametrize("x_ref", [0.2, None])
@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf])
def test_a_bad_spacing_among_many_is_refused_after_the_good_ones_before_it(
    bad: float, x_ref: float | None
) -> None:
    acc, one = RowQualityAccumulator(x_ref), RowQualityAccumulator(x_ref)
    with pytest.raises(ValueError, match="spacing must be"):
        acc.add_many([0.2, 0.21, bad, 0.19])
    one.add(0.2)
    one.add(0.21)
    assert vars(acc) == vars(one)


def test_a_row_whose_seeds_mostly_share_one_spot_has_no_indices_instead_of_an_error() -> None:
    """A flood of edges stamped together (median spacing 0) made the snapshot raise."""
    acc = RowQualityAccumulator()
    acc.add_many([0.0] * 50 + [0.1] * 10)
    result = acc.result()
    assert result.n == 60 and result.x_ref_m is None and result.multiples_index is None
